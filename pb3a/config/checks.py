"""Checks of single configuration values, each returning what is wrong in words.

Every function here looks at one value of one entry (a name, a period, a
state table, ...) and returns problem texts *without* the place they are in;
``pb3a.config.compiler`` prefixes them with the file and entry. Keeping the
wording here keeps every message of one kind the same wherever it is found.
"""

from __future__ import annotations

import difflib
import dis
import inspect
import json
import numbers
import os
import re
from collections.abc import Iterable
from typing import Any

from pb3a.errors import MOST_SECONDS
from pb3a.loading.references import by_reference, class_ref
from pb3a.model.displays import declared_displays, finite
from pb3a.model.environment import PREFIX as ENV_PREFIX
from pb3a.model.module import (
    HOOKS,
    RESTART_POLICIES,
    Module,
    can_hold,
    reflective_state,
    refusals,
)
from pb3a.model.state_edits import configured
from pb3a.transport import pickling
from pb3a.transport.addresses import tcp_address_problems

NAME = re.compile(r"\A[A-Za-z0-9_-]+\Z")     # (\Z: "$" also matches before a final newline)
MAX_SPARES = 16                 # idle workers a node may keep (each an idle process)


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` when a choice is close to ``word``, case aside, else
    empty (a name that differed only in case, ``B`` for ``b``, got no suggestion)."""
    by_case = {str(choice).lower(): str(choice) for choice in reversed(list(choices))}
    close = difflib.get_close_matches(str(word).lower(), list(by_case), n=1)
    return f" (did you mean {by_case[close[0]]!r}?)" if close else ""


def listing(names: Iterable[str]) -> str:
    """Names as a comma-separated list, or ``(none)``."""
    return ", ".join(names) or "(none)"


def name(value: Any, what: str) -> list[str]:
    """A module, node, group or export name: ASCII letters, digits, ``_`` and ``-``."""
    if isinstance(value, str) and NAME.match(value):
        return []
    # (ASCII said: 'módulo' was refused for "letters", and ó is one)
    return [(f"bad {what} name {value!r}: use only ASCII letters, digits, '_' and '-' "
            "(no accents, '.', '/' or spaces)")]


def path(value: Any, what: str) -> list[str]:
    """A name that may be a macro path (``robot/mapper``): each of its parts a name."""
    if not isinstance(value, str):
        return name(value, what)
    return [problem for part in value.split("/") for problem in name(part, what)]


def unknown_keys(extra: dict[str, Any], allowed: Iterable[str]) -> list[str]:
    """One problem per key not in ``allowed`` (typos such as ``perod``)."""
    allowed = list(allowed)
    return [f"unknown key {key!r}{did_you_mean(key, allowed)}; allowed keys: {listing(allowed)}"
            for key in extra]


def period(value: Any) -> list[str]:
    """``None`` (keep the class's) or a number of seconds from 0 to ``MOST_SECONDS``: an
    int or a float, or numpy's (a period computed with numpy, ``np.float32(0.5)``, was
    refused by ``add`` as not a number)."""
    if value is None or (_real(value) and 0 <= value <= MOST_SECONDS):
        return []
    return [(f"period must be a number of seconds from 0 to {MOST_SECONDS:g} (0 = as fast as "
            f"possible; leave it out to keep the class's), got {value!r:.60}")]


def _real(value: Any) -> bool:
    """A finite real number: an int or a float, or another real type's (numpy's) whose
    float is finite; not a bool."""
    if isinstance(value, numbers.Real) and not isinstance(value, (bool, int, float)):
        try:
            value = float(value)
        except (OverflowError, ValueError):
            return False
    return finite(value)


def stepped(cls: type[Module], value: Any) -> list[str]:
    """A period given to a module is for a class with a ``step()`` of its own (one that
    has none stepped an empty body as fast as it could, with ``period = 0``: a core
    taken for nothing, and its inputs handled late)."""
    if value is None or period(value) or cls.step is not Module.step:
        return []                               # (a bad period is said once, by period())
    how = (", and it runs on_input as values come" if cls.is_event_driven()
           else ", or give the class a step()")
    return [f"period = {value!r} is given, but {class_ref(cls)} has no step() for it to "
            f"call: leave period out{how}"]


def fixed_rate(cls: type[Module] | None, value: Any, given: Any) -> list[str]:
    """``None`` (keep the class's) or a bool; true only for a module that steps, of a
    class with a ``step()`` of its own and a period, ``given`` to the module (a bad one
    is said by ``period``) or its class's: there is no rate to keep otherwise."""
    if value is None:
        return []
    if not isinstance(value, bool):
        return [f"fixed_rate must be true or false (leave it out to keep the class's), "
                f"got {value!r:.60}"]
    if not value or cls is None:
        return []
    if cls.step is Module.step:
        return [f"fixed_rate = true is given, but {class_ref(cls)} has no step() for it to "
                "time: leave fixed_rate out"]
    if given is None and cls.period is None:
        return [f"fixed_rate = true is given, but neither the module nor {class_ref(cls)} "
                "has a period: give it one (the period its steps keep)"]
    return []


def assigned_period(name: str, cls: type[Module], value: Any) -> float:
    """The period ``self.period = value`` sets in module ``name`` of class ``cls`` as it
    runs (checked as ``set_state(name, period=...)`` checks it); ``ValueError`` naming
    the module and the value, raised at the assignment, if it is none."""
    said = f"module {name!r}: self.period = {value!r:.60}"
    if value is None or period(value):
        raise ValueError(f"{said} is no period: a period is a number of seconds from 0 "
                         f"to {MOST_SECONDS:g} (0: as fast as it can)")
    if stepped(cls, value):
        raise ValueError(f"{said}, but {class_ref(cls)} has no step() for a period to call "
                         "(it runs on_input as values come)")
    return float(value)


def env_home(name: Any, nodes: Iterable[str]) -> str | None:
    """The node whose env module ``name`` is (``env-b``: node b's, when b is one of
    ``nodes``), or None."""
    if isinstance(name, str) and name.startswith(ENV_PREFIX):
        node = name.removeprefix(ENV_PREFIX)
        return node if node in nodes else None
    return None


def env_placed(name: Any, node: Any, nodes: Iterable[str]) -> list[str]:
    """An ``env-NODE`` module runs on NODE: it measures the node it runs on (one
    declared with no node measured the first node's CPUs under node b's name)."""
    home = env_home(name, nodes)
    if home is None or node is None or node == home:
        return []
    return [(f"{name} is node {home}'s env module, and an env module measures the node it "
             f"runs on, but it is placed on node {node!r}: leave 'node' out (it runs on "
             f"{home}), or read {ENV_PREFIX}{node} for node {node}'s readings")]


def fallback(value: Any, nodes: list[str]) -> list[str]:
    """``None`` or a list of declared nodes: where the module restarts, in order, when
    its node is lost."""
    if value is None:
        return []
    if not isinstance(value, (list, tuple)) or not all(isinstance(n, str) for n in value):
        return [f"fallback must be a list of node names, got {value!r}"]
    unknown = [node for node in value if node not in nodes]
    if unknown:
        return [f"fallback names unknown node{'s' if len(unknown) > 1 else ''} "
                f"{listing(map(repr, unknown))}; declared nodes: {listing(nodes)}"]
    return []


def fallback_used(value: Any, restart: Any, cls: type[Module] | None) -> list[str]:
    """Fallback nodes are for a module restarted elsewhere when its node is lost: one
    whose restart policy, ``restart`` given to it or else its class's (``cls``; None: not
    known), is ``"never"`` goes with its node, and its fallback is never used (``pb3a
    check`` said ok, and the failover said the module lost, naming the fallback it did
    not try). Said only of a list of names, the policy known (a bad fallback or restart
    is said by ``fallback`` and ``restart``)."""
    if not value or not isinstance(value, (list, tuple)) \
            or not all(isinstance(node, str) for node in value):
        return []
    policy = restart if restart is not None else getattr(cls, "restart", None)
    if policy != "never":
        return []
    owner = next((klass for klass in cls.__mro__ if "restart" in vars(klass)), Module) \
        if restart is None and cls is not None else None
    whose = ("restart = \"never\" is given" if owner is None
             else "restart is \"never\" by default" if owner is Module
             else f"{class_ref(owner)} has restart = \"never\"")
    return [f"fallback = {json.dumps(list(value))} is used only when the module is restarted "
            f"elsewhere, and {whose}: the module goes with its node. Give restart = \"fresh\" "
            "or \"last-state\", or remove fallback"]


def restart(value: Any) -> list[str]:
    """``None`` (keep the class's) or one of the restart policies."""
    if value is None or value in RESTART_POLICIES:
        return []
    return [f"restart must be one of {listing(map(repr, RESTART_POLICIES))}, got {value!r}"
            f"{did_you_mean(value, RESTART_POLICIES)}"]


def workers(value: Any) -> list[str]:
    """0 (one process per module) or a positive number of worker processes."""
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return []
    return [(f"workers must be a whole number >= 0 (0 = one process per module, N = pack the "
            f"node's modules into N processes), got {value!r}")]


def spares(value: Any) -> list[str]:
    """A whole number of idle workers from 0 to ``MAX_SPARES``."""
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_SPARES:
        return []
    return [(f"spares must be a whole number from 0 to {MAX_SPARES} (the worker processes the "
             f"node keeps booted for modules that arrive; 0 = none), got {value!r}")]


def timeout(value: Any) -> list[str]:
    """Left out (the default) or a positive, finite number of seconds."""
    if value is None or (finite(value) and 0 < value <= MOST_SECONDS):
        return []
    return [(f"timeout must be a positive number of seconds, at most {MOST_SECONDS:g} (how "
             f"long an operation on the running system may wait), got {value!r}")]


def state(cls: type[Module], value: Any) -> list[str]:
    """A table of initial state: what the class refuses of it (``refused``). When the
    class uses reflection (its ``set_state`` is ``Module``'s or marked ``reflective``, as
    a ``Driver``'s), its keys must be the class's state (or set in its ``__init__``), and
    each value of the kind of the class's default for it (``configured``); only such
    values are put to the class then."""
    if not isinstance(value, dict):
        return [f"state must be a table of attribute = value, got {value!r}"]
    if not reflective_state(cls):
        return refused(cls, value)    # the class defines its own state: it knows the keys
    problems, judged = _judged(cls, value)
    return problems + refused(cls, judged)


# An entry's own keys that configure how the runtime runs its module, never its state.
OPTIONS = ("period", "fixed_rate", "restart")


def not_state(key: str, value: Any) -> str:
    """What to do with option ``key`` (``OPTIONS``) given in a module's state: give it as
    the entry's own key (``period`` among a live edit's fields is taken, and sets the
    running module's period, as ``pb3a set`` does; so it was mistaken for state here)."""
    try:
        written = json.dumps(value)                 # (TOML's words: true, "fresh")
    except (TypeError, ValueError):
        written = repr(value)
    live = ("; a running module's is set by pb3a set ADDR NAME period=... or "
            "set_state(NAME, period=...)" if key == "period" else "")
    return (f"{key} is not state: use the entry's own `{key} = {written:.60}`, beside its "
            f"class (add(..., {key}=...) in Python){live}")


def _judged(cls: type[Module], value: dict[str, Any]) -> tuple[list[str], dict[str, Any]]:
    """The problems of the keys and kinds of ``value``, a reflective class's state, and
    the values that have none (each of the kind of the class's default)."""
    names, made = cls.state_names(), _set_in_init(cls)
    known = [*names, *sorted(made.difference(names))]
    problems, judged = [], {}
    for key, item in value.items():
        if key in names:
            try:
                judged[key] = configured(key, getattr(cls, key), item, owner=class_ref(cls))
            except (TypeError, ValueError) as exc:
                problems.append(str(exc))
        elif key in made:
            judged[key] = item          # (of no kind the class declares)
        elif key in OPTIONS:
            problems.append(not_state(key, item))
        else:
            problems.append(f"{class_ref(cls)} has no state {key!r}{did_you_mean(key, known)}; "
                            f"its state is: {listing(known)} (fix the key, or declare the "
                            "attribute on the class)")
    return problems, judged


def defaults_refused(cls: type[Module], whole: dict[str, Any],
                     said: Iterable[str] | None = None) -> list[str]:
    """What the class refuses of a module's whole state (``whole``, its entry's with its
    macro instances' overrides, and the class's own defaults for the rest) beyond what
    ``state`` said of the tables ``whole`` was made of, each judged where it is written
    (``said``; judged here, of ``whole`` as one table, if None): a default of its own
    it refuses, a driver's ``timeout = 0``, which every request then failed by ("...
    (its class's own default)"), and a rule relating fields that an entry and a
    default, or a macro's entry and an instance's override, break together (a
    controller's minimum green above its class's maximum). Judged whole, a placeholder
    default that every entry overrides is no problem (judged alone, it made such a class
    impossible to launch). A class with a ``set_state`` of its own not marked
    ``reflective`` is judged so too if it keeps ``Module``'s ``get_state`` (its
    defaults are its state then: a user's subclass of a library controller whose
    ``set_state`` logged and called the base's passed the check, and failed at the
    launch), its values as given. The class's hook is asked once here, and once more
    (its defaults alone) only when it refuses something."""
    if cls.get_state is not Module.get_state:
        return []               # (the class defines its own state: no defaults known)
    defaults = {name: getattr(cls, name) for name in cls.state_names()}
    # (a value not of its field's kind is said as such, not judged again here)
    given = _judged(cls, whole)[1] if reflective_state(cls) else whole
    problems = refused(cls, {**defaults, **given})
    if not problems:
        return []
    said = set(state(cls, whole) if said is None else said)
    own = refused(cls, defaults)
    return [f"{problem} (its class's own default)" if problem in own else problem
            for problem in problems if problem not in said]


def refused(cls: type[Module], state: dict[str, Any]) -> list[str]:
    """What module class ``cls`` refuses of ``state`` (fields to be set): its
    ``state_problems``, which its ``set_state`` asks (a value only a class's own
    ``set_state`` refused passed the check, and the launch or the running module refused
    it). A ``state_problems`` that raises or answers other than a list of texts is a
    problem itself, naming the class (the check failed with it): ``refusals``."""
    if not state:
        return []
    return refusals(cls, state)


def _set_in_init(cls: type[Module]) -> set[str]:
    """The public attributes the class's ``__init__`` (or a base's) sets on the instance
    (``self.kp = 1.0``): state too, which only an instance holds (a file setting it was
    refused). Not a store through a property (it sets no field), nor one on another
    object (``self.pid.gain = 2.0``)."""
    names = set()
    for klass in cls.__mro__:
        init = vars(klass).get("__init__")
        if klass is Module or not hasattr(init, "__code__") or not init.__code__.co_varnames:
            continue
        me, loaded = init.__code__.co_varnames[0], None
        for op in dis.get_instructions(init):
            if op.opname == "STORE_ATTR" and loaded == me:     # (self.NAME = ...)
                names.add(op.argval)
            # the local loaded last, the object a STORE_ATTR stores on (3.13 loads two at
            # once: then the second)
            loaded = op.argval if op.opname.startswith("LOAD_FAST") else None
            if isinstance(loaded, tuple):
                loaded = loaded[-1]
    return {name for name in names if not name.startswith("_") and can_hold(cls, name)}


def macro_state(value: Any) -> list[str]:
    """A macro instance's state: a table of its modules' paths, each a table of state
    for that module (which overrides the macro's own)."""
    if isinstance(value, dict) and all(isinstance(v, dict) for v in value.values()):
        return []
    return [("a macro instance's state is a table of its modules, each a table of their "
             "state, e.g. state = { driver = { resource = \"tcp://...\" } }, got "
             f"{value!r}")]


def module_class(cls: type[Module]) -> list[str]:
    """What a module class declares itself: its ``period`` and ``restart`` (a module the
    configuration gives none of runs with them), that it is made with no arguments, and
    its ``displays`` table. A bad period on the class passed every check, and its step
    thread died after one step, the module shown running. (State defaults it refuses
    itself are judged with each entry's state: ``state``.)"""
    ref = class_ref(cls)
    problems = []
    if cls.period is not None and not (finite(cls.period) and 0 <= cls.period <= MOST_SECONDS):
        problems.append(f"{ref} has period = {cls.period!r}: a class's period is None (no "
                        f"steps, only on_input) or a number of seconds from 0 to "
                        f"{MOST_SECONDS:g}")
    if not isinstance(cls.fixed_rate, bool):
        problems.append(f"{ref} has fixed_rate = {cls.fixed_rate!r:.60}: a class's "
                        "fixed_rate is True or False")
    if cls.restart not in RESTART_POLICIES:
        problems.append(f"{ref} has restart = {cls.restart!r}: a class's restart is one of "
                        f"{listing(map(repr, RESTART_POLICIES))}")
    return (problems + made_bare(cls) + displays(cls) + misspelled_hooks(cls)
            + state_hook(cls) + sendable(cls))


def state_hook(cls: type[Module]) -> list[str]:
    """A ``state_problems`` of the user's classes that is a plain method, not a
    classmethod: it is asked of the class, with no instance (``cls.state_problems(state)``,
    by the checks, ``add`` and the State Editor as by ``set_state``), and a plain method
    failed each time, said only as "raised TypeError: ... missing 1 required positional
    argument". The definition asked is judged, a mixin's too (one in a class that is no
    ``Module`` was passed over)."""
    klass = next(klass for klass in cls.__mro__ if "state_problems" in vars(klass))
    if inspect.isfunction(vars(klass)["state_problems"]):
        return [f"{class_ref(klass)} defines state_problems as a plain method: it is asked "
                "of the class, before any instance is made, so make it a classmethod "
                "(@classmethod, def state_problems(cls, state), returning a list of texts)"]
    return []


def sendable(cls: type[Module]) -> list[str]:
    """A class defined in a script or a function goes to its worker by value, its class
    attributes with it, so one holding a lock, a file or a socket cannot be sent (the
    checks passed it, and the launch then refused it)."""
    if by_reference(cls):
        return []
    try:
        pickling.dumps(cls)
    except Exception as exc:
        return [pickling.unsendable_class_reason(cls, exc)]
    return []


def misspelled_hooks(cls: type[Module]) -> list[str]:
    """Each method of the user's classes (``cls`` and its bases, not PB3A's) whose name is
    a near miss of a hook the class does not define (``on_inputs``, ``stpe``,
    ``teardwon``): it is never called, and the module ran doing nothing, with no word
    said; so is a near miss of ``state_problems`` (``state_problem``), which no check asked.
    A near miss: difflib's close match (cutoff 0.8, the names' case aside), or
    the hook's letters in another order; a private name (``_step``) is left alone."""
    missing = [hook for hook in (*HOOKS, "state_problems")
               if inspect.getattr_static(cls, hook) is inspect.getattr_static(Module, hook)]
    problems = []
    for klass in cls.__mro__:
        if not issubclass(klass, Module) or klass.__module__.partition(".")[0] == "pb3a":
            continue
        for name, value in vars(klass).items():
            if name.startswith("_") or not (inspect.isfunction(value) or isinstance(
                    value, (staticmethod, classmethod))):
                continue
            close = difflib.get_close_matches(name.lower(), missing, n=1, cutoff=0.8) or [
                hook for hook in missing if sorted(hook) == sorted(name.lower())]
            if close:
                problems.append(
                    f"{class_ref(cls)} defines {name}(): did you mean {close[0]}()? a "
                    f"module's hooks are {', '.join(f'{hook}()' for hook in HOOKS)} and "
                    "the classmethod state_problems(), and "
                    f"only they are called: {name}() never is (a helper of your own: give "
                    "it a name less like a hook's)")
    return problems


def made_bare(cls: type[Module]) -> list[str]:
    """The class can be made with no arguments, as the runtime makes every module (one
    whose ``__init__`` needs one passed the check, and its launch failed in the worker)."""
    try:
        parameters = inspect.signature(cls).parameters.values()
    except (TypeError, ValueError):         # (no signature to read: left to the worker)
        return []
    needed = [p.name for p in parameters if p.default is p.empty
              and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    if not needed:
        return []
    them = "them" if len(needed) > 1 else "it"
    return [(f"{class_ref(cls)} cannot be made with no arguments, as every module is: its "
             f"__init__ needs {listing(needed)}; give {them} a default, or make {them} state "
             "(a class attribute, which the entry's state sets)")]


def displays(cls: type[Module]) -> list[str]:
    """The class's ``displays`` table is well formed. (The fields it names are not
    checked: state may be set first in ``setup``.)"""
    try:
        declared_displays(cls)
    except ValueError as exc:
        return [f"{exc} (fix the class's displays table)"]
    return []


def cpus(value: Any, remote: bool = False) -> list[str]:
    """Left out (any CPU) or a non-empty list of CPU numbers: on this machine, those this
    process may run on; on a ``remote`` node's machine (its executor checks them), any."""
    if value is None:
        return []
    usable = None if remote else sorted(os.sched_getaffinity(0))
    if isinstance(value, list) and value and all(
            isinstance(cpu, int) and not isinstance(cpu, bool) and cpu >= 0
            and (usable is None or cpu in usable) for cpu in value):
        return []
    which = ("numbers, 0 or more" if usable is None
             else f"numbers among this machine's {listing(map(str, usable))}")
    return [(f"cpus must be a non-empty list of CPU {which} (the CPUs the node's workers may "
             f"run on), got {value!r}")]


def advertise(value: Any) -> list[str]:
    """Left out (found) or a host: a name or an IP address, no scheme, no port (one
    colon means HOST:PORT; an IPv6 address has several)."""
    if value is None or (isinstance(value, str) and value and value.count(":") != 1
                         and not any(c in value for c in "/ ")):
        return []
    return [(f"advertise must be the host other nodes reach this node at, a name or an IP "
             f"address such as '10.0.0.7' (no tcp://, no port), got {value!r}")]


def node_address(value: Any) -> list[str]:
    """A node's address, ``tcp://HOST:PORT``, or None: started on this machine."""
    if value is None:
        return []
    return tcp_address_problems(value, "address",
                                " (or left out to start the node on this machine)")


def server_address(value: Any) -> list[str]:
    """A module server's address, ``tcp://HOST:PORT``."""
    return tcp_address_problems(value, "each of module_servers")



def group_apart(name: Any, group: Any, node: Any, modules: Iterable[Any]) -> list[str]:
    """A group shares one worker process on one node: the problem of module ``name``, in
    ``group`` on ``node``, if one of ``modules`` (``FlatModule``s) has that group on
    another node."""
    other = next((module for module in modules if group is not None
                  and module.group == group and module.node != node), None)
    if other is None:
        return []
    return [f"group {group!r} would span nodes {other.node!r} ({other.name}) and {node!r} "
            f"({name}); a group shares one worker process on one node: give them the same "
            "node or different groups"]
