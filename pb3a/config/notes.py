"""Notes on a valid plan: what it says that likely does nothing, said but never refused.

A configuration can be valid and still leave a module idle: a class with a ``step()``
and no period is never stepped (its period may be set as it runs: ``pb3a set``, an
agent, the module itself), and an input no link feeds never gets a value (it may be fed
by a link made as the system runs). ``pb3a check`` and ``pb3a run`` print these notes
beside their answer; they change neither's exit status. Each note is said only where a
user most likely forgot something, so that they stay few:

* a step with no period, unless the class assigns ``self.period`` itself;
* an input fed by nothing, of a module some link of the file touches (a module no link
  touches stands alone, or is wired as the system runs), not of an agent or an env
  module (whose ports are often read or fed as the system runs);
* an output read by nothing only beside an input fed by nothing that it alone could
  feed (a forgotten link): an output read by nothing is common (a reading kept for
  ``pb3a state``, a driver's spare readings), and said alone it would be noise.
"""

from __future__ import annotations

import dis
import inspect
from collections.abc import Iterable

from pb3a.config.plan import FlatLink, FlatModule
from pb3a.loading.references import class_ref
from pb3a.model.agent import Agent
from pb3a.model.environment import Environment
from pb3a.model.module import Module


def plan_notes(modules: dict[str, FlatModule], links: Iterable[FlatLink],
               labels: dict[str, str]) -> list[str]:
    """The notes on a plan's ``modules`` and ``links``, each after the label of the entry
    it concerns (``labels``, by module path; the path itself if it has none)."""
    links = list(links)
    notes = [(name, text) for name, module in modules.items()
             for text in _unstepped(name, module)]
    notes += _unlinked(modules, links)
    return [f"{labels.get(name, name)}: note: {text}" for name, text in notes]


def _unstepped(name: str, module: FlatModule) -> list[str]:
    """A module whose class defines ``step()`` but that has no period: the runtime never
    calls its ``step()`` (``ModuleActor._steps``) until its period is set."""
    cls = module.cls
    if cls.step is Module.step or module.period is not None or _assigns_period(cls):
        return []
    return [f"{name} ({class_ref(cls)}) defines step() but has no period: its step() never "
            "runs (give it period = SECONDS in its entry or on its class), unless its period "
            f"is set as it runs (pb3a set ADDR {name} period=..., an agent's set_state)"]


def _assigns_period(cls: type[Module]) -> bool:
    """Whether a method of the user's classes (``cls`` and its bases, not PB3A's) assigns
    ``self.period`` (or any object's ``period``): the module may give itself a period as
    it runs, in ``setup`` say, and then it steps."""
    for klass in cls.__mro__:
        if klass.__module__.partition(".")[0] in ("pb3a", "builtins"):
            continue
        for value in vars(klass).values():
            if isinstance(value, (classmethod, staticmethod)):
                value = value.__func__
            if inspect.isfunction(value) and any(
                    op.opname == "STORE_ATTR" and op.argval == "period"
                    for op in dis.get_instructions(value)):
                return True
    return False


def _unlinked(modules: dict[str, FlatModule],
              links: list[FlatLink]) -> list[tuple[str, str]]:
    """Inputs fed by nothing, each with the output read by nothing that alone could feed
    it, if there is one (see the module's docstring for which are said)."""
    fed = {(link.dst, link.dst_port) for link in links}
    read = {(link.src, link.src_port) for link in links}
    linked = {name for link in links for name in (link.src, link.dst)}
    unread = [(name, port, spec) for name, module in modules.items()
              if not _quiet(module.cls)
              for port, spec in module.cls.outputs.items() if (name, port) not in read]
    notes = []
    for name, module in modules.items():
        if _quiet(module.cls):
            continue
        for port, spec in module.cls.inputs.items():
            if (name, port) in fed:
                continue
            could = [(source, out) for source, out, given in unread
                     if source != name and spec.accepts(given) is None]
            could = [pair for pair in could if pair[1] == port] or could
            if len(could) == 1:
                source, out = could[0]
                notes.append((name, f"{name}.{port} is fed by nothing, and {source}.{out} is "
                                    f"read by nothing: a link forgotten? ([[links]] from = "
                                    f"\"{source}.{out}\", to = \"{name}.{port}\")"))
            elif name in linked:
                notes.append((name, f"{name}.{port} is fed by nothing: no link feeds it, so "
                                    "it never gets a value (link an output to it, unless a "
                                    "link made as the system runs will)"))
    return notes


def _quiet(cls: type[Module]) -> bool:
    """Whether the ports of a module of ``cls`` are left out of the notes: an agent's
    (read and fed as it adapts the system, often by links it makes) and an env
    module's (readings for whoever wants them)."""
    return issubclass(cls, (Agent, Environment))
