"""Case-based reasoning over flat feature dicts: retrieve, adapt, retain.

A case pairs symptoms (feature name -> expected value) with a solution (a dict whose
strings may hold ``{placeholders}``) and counts how often it was tried and worked.
Cases live in TOML files a user can read and extend; several files load into one
base, a later file's case replacing an earlier one of the same id. Nothing here knows
of PB3A or of robots: the remedy agent gives the features and the placeholder values.

File format (``[weights]``, ``[scales]`` and the two thresholds are optional)::

    min_similarity = 0.75        # below it a case is not retrieved at all
    new_case_below = 0.95        # a worked solution retrieved at less is retained anew

    [weights]                    # per feature; 1 when not given
    fault = 4.0

    [scales]                     # numeric distance at which a feature stops matching
    failed_sensors = 16

    [[case]]
    id = "motors-standby"
    note = "why this case exists"
    tried = 0
    worked = 0
    [case.symptoms]              # a string or boolean (equal or not), a number, or a
    fault = "motors"             # [low, high] range (numbers: by distance over scale)
    probability = [0.5, 1.0]
    [case.remedy]
    action = "move_macro"
    to = "{standby_node}"
"""

from __future__ import annotations

import copy
import json
import math
import numbers
import os
import re
import string
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agents.limits import finite, whole
from pb3a.atomic_write import write_text_atomically

Feature = str | bool | int | float
SETTINGS = {"min_similarity": 0.75, "new_case_below": 0.95}
_CASE_KEYS = {"id", "note", "tried", "worked", "symptoms", "remedy"}
_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


class CaseFileError(ValueError):
    """A case file that cannot be read as a case base; the message names file and case."""


class AdaptationError(ValueError):
    """A solution that cannot be adapted to the situation (a placeholder without value,
    or a result that makes no sense there)."""


@dataclass
class Case:
    """One experience: in a situation like ``symptoms``, ``remedy`` was tried."""

    id: str
    symptoms: dict[str, Feature | list[float]]
    remedy: dict[str, Any]
    note: str = ""
    tried: int = 0
    worked: int = 0
    source: str = ""           # the file it came from, or the one retention moved it to

    @property
    def reliability(self) -> float:
        """How often it worked, with Laplace's rule so an untried case counts as 1/2."""
        return (self.worked + 1) / (self.tried + 2)


@dataclass(frozen=True)
class Match:
    """A case retrieved for a situation, and how similar the two are (0 to 1)."""

    case: Case
    similarity: float


@dataclass
class CaseBase:
    """Cases with the settings of retrieval; ``settings`` maps each file to its own
    settings (in load order), so that saving a file keeps what that file said."""

    cases: list[Case] = field(default_factory=list)
    settings: dict[str, dict[str, Any]] = field(default_factory=dict)

    # -- loading and saving ------------------------------------------------------------
    @classmethod
    def load(cls, paths: list[str | Path]) -> CaseBase:
        """The cases of ``paths`` in order; a case replaces an earlier one of the same
        id, and settings merge with the later file winning."""
        base = cls()
        for path in paths:
            cases, settings = _read(_key(path))
            base.settings[_key(path)] = settings
            ids = {case.id for case in cases}
            base.cases = [case for case in base.cases if case.id not in ids] + cases
        return base

    def save(self, path: str | Path) -> None:
        """Write the file ``path`` atomically (temp file, then rename): the settings it
        had and every case whose source it is."""
        target, key = Path(path).expanduser(), _key(path)
        text = _to_toml(self.settings.get(key, {}),
                        [case for case in self.cases if case.source == key])
        target.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomically(target, text)

    def to_dict(self) -> dict[str, Any]:
        """The base as plain data (for a module's state), sharing nothing with it."""
        return copy.deepcopy({"cases": [vars(case) for case in self.cases],
                              "settings": self.settings})

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "case_base") -> CaseBase:
        """The base ``to_dict`` gave, sharing nothing with ``data``. ``CaseFileError``
        names (as ``where``) what does not fit, checked as a file's cases are: a case
        base set in a module's state went unchecked, and failed at its first failure
        with a bare ``KeyError``."""
        data = copy.deepcopy(data)
        if not (isinstance(data, dict) and isinstance(data.get("cases"), list)
                and isinstance(data.get("settings"), dict)):
            raise CaseFileError(f"{where}: give what CaseBase.to_dict() gives: "
                                "{'cases': [...], 'settings': {file: {...}}}")
        for source, settings in data["settings"].items():
            _check_settings(f"{where} (the settings of {source})", settings)
        sources = [case.pop("source", "") if isinstance(case, dict) else ""
                   for case in data["cases"]]
        cases = _cases(where, data["cases"])
        for case, source in zip(cases, sources, strict=True):
            case.source = source
        return cls(cases, data["settings"])

    # -- settings ------------------------------------------------------------------------
    def setting(self, name: str) -> float:
        """``min_similarity`` or ``new_case_below``: the last file's that gives it."""
        value = SETTINGS[name]
        for settings in self.settings.values():
            value = settings.get(name, value)
        return value

    def _table(self, name: str) -> dict[str, float]:
        merged: dict[str, float] = {}
        for settings in self.settings.values():
            merged.update(settings.get(name, {}))
        return merged

    # -- retrieve, retain --------------------------------------------------------------
    def case(self, case_id: str) -> Case:
        """The case with id ``case_id`` (KeyError if none)."""
        for case in self.cases:
            if case.id == case_id:
                return case
        raise KeyError(f"no case {case_id!r}")

    def similarity(self, case: Case, situation: dict[str, Feature]) -> float:
        """Weighted mean of the per-feature similarities over the case's symptoms: 1 or 0
        for strings and booleans, ``1 - distance / scale`` (not below 0) for numbers."""
        weights, scales = self._table("weights"), self._table("scales")
        total = score = 0.0
        for name, wanted in case.symptoms.items():
            weight = weights.get(name, 1.0)
            total += weight
            score += weight * _feature_similarity(wanted, situation.get(name),
                                                  scales.get(name, 1.0))
        return score / total if total else 0.0

    def retrieve(self, situation: dict[str, Feature]) -> list[Match]:
        """The cases at least ``min_similarity`` similar to ``situation``, best first;
        ties go to the case with more symptoms (the more specific), then the more
        reliable, then the one loaded last (a user's file over the shipped one)."""
        least = self.setting("min_similarity")
        ranked = []
        for order, case in enumerate(self.cases):
            similarity = self.similarity(case, situation)
            if similarity >= least:
                key = (similarity, len(case.symptoms), case.reliability, order)
                ranked.append((key, Match(case, similarity)))
        ranked.sort(key=lambda item: item[0], reverse=True)
        return [match for _, match in ranked]

    def retain(self, match: Match, situation: dict[str, Feature], worked: bool,
               into: str | Path) -> Case:
        """Learn from applying ``match``'s remedy in ``situation``: a remedy that worked
        although the case matched less than ``new_case_below`` becomes a new case (the
        situation as symptoms, the same remedy); otherwise the case counts the attempt.
        The case changed is returned; it now belongs to the file ``into`` (``save``
        writes it there, and never to the file it was read from before)."""
        source = _key(into)
        if worked and match.similarity < self.setting("new_case_below"):
            learned = Case(self._new_id(match.case.id), dict(situation),
                           copy.deepcopy(match.case.remedy),
                           f"learned from case {match.case.id!r}", 1, 1, source)
            self.cases.append(learned)
            return learned
        match.case.tried += 1
        match.case.worked += int(worked)
        match.case.source = source
        return match.case

    def _new_id(self, parent: str) -> str:
        ids = {case.id for case in self.cases}
        number = 1
        while f"{parent}/learned-{number}" in ids:
            number += 1
        return f"{parent}/learned-{number}"


def adapt(template: dict[str, Any], values: dict[str, Any]) -> dict[str, Any]:
    """``template`` with every ``{name}`` filled from ``values``; a string that is one
    placeholder alone takes the value itself (a list stays a list). AdaptationError
    names the placeholders with no value (missing, None or empty)."""
    return {key: _fill(value, values) for key, value in template.items()}


def _fill(value: Any, values: dict[str, Any]) -> Any:
    if isinstance(value, dict):
        return adapt(value, values)
    if isinstance(value, list):
        return [_fill(item, values) for item in value]
    if not isinstance(value, str):
        return value
    names = [name for _, name, _, _ in string.Formatter().parse(value) if name is not None]
    missing = [name for name in names if values.get(name) in (None, "")]
    if missing:
        raise AdaptationError("no value for " + ", ".join(f"{{{name}}}" for name in missing))
    if len(names) == 1 and value == f"{{{names[0]}}}":
        return values[names[0]]
    return value.format_map(values)


def _feature_similarity(wanted: Any, have: Any, scale: float) -> float:
    if isinstance(wanted, (str, bool)):
        return float(type(have) is type(wanted) and have == wanted)
    if isinstance(have, bool) or not isinstance(have, (int, float)):
        return 0.0
    if isinstance(wanted, list):
        low, high = wanted
        distance = max(low - have, have - high, 0.0)
    else:
        distance = abs(have - wanted)
    return max(0.0, 1.0 - distance / scale)


def _key(path: str | Path) -> str:
    # A file is known by the name it was given ("~/.pb3a/cases.toml" stays so), not by
    # its absolute path: a base carried to another node then saves to that node's file.
    return os.fspath(path)


# -- reading a case file ---------------------------------------------------------------

def _read(path: str) -> tuple[list[Case], dict[str, Any]]:
    try:
        with Path(path).expanduser().open("rb") as handle:
            data = tomllib.load(handle)
    except OSError as exc:
        raise CaseFileError(f"{path}: cannot read the case file: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise CaseFileError(f"{path}: not valid TOML: {exc}") from None
    settings = {name: data.pop(name) for name in (*SETTINGS, "weights", "scales")
                if name in data}
    raw_cases = data.pop("case", [])
    if data:
        raise CaseFileError(f"{path}: unknown entries {', '.join(map(repr, data))}; a case "
                            f"file has {', '.join(SETTINGS)}, [weights], [scales], [[case]]")
    _check_settings(path, settings)
    if not isinstance(raw_cases, list):
        raise CaseFileError(f"{path}: 'case' must be an array of tables: write [[case]]")
    return _cases(path, raw_cases), settings


def _cases(path: str, raw_cases: list[Any]) -> list[Case]:
    cases: list[Case] = []
    for number, raw in enumerate(raw_cases, 1):
        case = _case(path, number, raw)
        if any(case.id == other.id for other in cases):
            raise CaseFileError(f"{path}: case {case.id!r} is defined twice")
        cases.append(case)
    return cases


def _check_settings(path: str, settings: dict[str, Any]) -> None:
    for name in SETTINGS:
        value = settings.get(name, 0.0)
        if not finite(value) or not 0.0 <= value <= 1.0:
            raise CaseFileError(f"{path}: {name} must be a number from 0 to 1, got {value!r}")
    for table in ("weights", "scales"):
        entries = settings.get(table, {})
        if not isinstance(entries, dict):
            raise CaseFileError(f"{path}: [{table}] must be a table of feature = number")
        for name, value in entries.items():
            if not finite(value) or value < 0 or (table == "scales" and value == 0):
                bound = "positive" if table == "scales" else "zero or more"
                raise CaseFileError(f"{path}: [{table}] {name} must be a number, {bound}; "
                                    f"got {value!r}")


def _case(path: str, number: int, raw: Any) -> Case:
    if not isinstance(raw, dict):
        raise CaseFileError(f"{path}: case number {number} is not a table: {raw!r}")
    case_id = raw.get("id")
    if not isinstance(case_id, str) or not case_id:
        raise CaseFileError(f"{path}: case number {number} has no id (id = \"...\")")

    def fail(problem: str) -> CaseFileError:
        return CaseFileError(f"{path}: case {case_id!r}: {problem}")

    unknown = sorted(set(raw) - _CASE_KEYS)
    if unknown:
        raise fail(f"unknown keys {', '.join(map(repr, unknown))}; a case has "
                   f"{', '.join(sorted(_CASE_KEYS))}")
    symptoms, remedy = raw.get("symptoms"), raw.get("remedy")
    if not isinstance(symptoms, dict) or not symptoms:
        raise fail("no symptoms: add a [case.symptoms] table after its [[case]]")
    for name, value in symptoms.items():
        if not _is_symptom(value):
            raise fail(f"symptom {name} = {value!r} is not a string, boolean, number or "
                       "[low, high] range with low <= high")
    if not isinstance(remedy, dict) or not isinstance(remedy.get("action"), str):
        raise fail("no remedy action: add a [case.remedy] table with action = \"...\"")
    tried, worked = raw.get("tried", 0), raw.get("worked", 0)
    if not (whole(tried) and whole(worked) and worked <= tried):
        raise fail(f"tried = {tried!r} and worked = {worked!r} must be whole numbers with "
                   "0 <= worked <= tried")
    note = raw.get("note", "")
    if not isinstance(note, str):
        raise fail(f"note must be a string, got {note!r}")
    return Case(case_id, symptoms, remedy, note, tried, worked, path)


def _is_symptom(value: Any) -> bool:
    if isinstance(value, list):
        return len(value) == 2 and all(map(finite, value)) and value[0] <= value[1]
    return isinstance(value, (str, bool)) or finite(value)


# -- writing a case file ---------------------------------------------------------------

def _to_toml(settings: dict[str, Any], cases: list[Case]) -> str:
    lines = ["# A PB3A case base (agents.case_base), rewritten by the remedy agent when it",
             "# learns: its settings and cases are kept, its comments are not."]
    scalars = [f"{name} = {_toml(settings[name])}" for name in SETTINGS if name in settings]
    if scalars:
        lines += ["", *scalars]
    for table in ("weights", "scales"):
        if settings.get(table):
            lines += ["", f"[{table}]", *_entries(settings[table])]
    for case in cases:
        lines += ["", "[[case]]", f"id = {_toml(case.id)}"]
        if case.note:
            lines.append(f"note = {_toml(case.note)}")
        lines += [f"tried = {case.tried}", f"worked = {case.worked}",
                  "[case.symptoms]", *_entries(case.symptoms),
                  "[case.remedy]", *_entries(case.remedy)]
    return "\n".join(lines) + "\n"


def _entries(table: dict[str, Any]) -> list[str]:
    return [f"{_toml_key(name)} = {_toml(value)}" for name, value in table.items()]


def _toml_key(name: str) -> str:
    return name if _BARE_KEY.match(name) else _toml(name)


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, numbers.Integral):
        return repr(int(value))                 # (numpy's repr is no TOML)
    if isinstance(value, numbers.Real):
        if not math.isfinite(value):
            raise ValueError(f"a case base holds finite numbers only, got {value!r}")
        return repr(float(value))
    if isinstance(value, str):
        # JSON's escapes are TOML's, except that TOML also forbids a raw DEL
        return json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml(v)}" for k, v in value.items()) + " }"
    raise ValueError(f"a case base cannot hold {type(value).__name__} values: {value!r}")
