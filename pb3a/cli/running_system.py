"""Commands that act on a running system through its launcher's address (``pb3a run``
prints it): ``pb3a status / state / set / migrate / swap / reload / relink / add /
remove / restart / nodes / events / logs ADDR ...``. Each goes through
``pb3a.connect``, authenticated with the cluster key, and prints a sentence, or JSON
with ``--json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable
from typing import Any

import zmq

from pb3a.cli.status import format_nodes, format_table
from pb3a.errors import PB3AError, RuntimeFailure, RuntimeTimeout, SystemStopped
from pb3a.events import Event
from pb3a.launch.connection import CONNECT_TIMEOUT, Connection, connect
from pb3a.loading.references import resolve_class
from pb3a.loading.trial import tried_first
from pb3a.model.state_edits import class_state, coerce
from pb3a.stats import plain
from pb3a.transport.auth import ClusterKeyError

CLASS_IMPORT_TIMEOUT = 10.0     # s: `pb3a add`'s own import of the class, for its defaults


def operation_command(args: argparse.Namespace) -> int:
    """``pb3a OPERATION ADDR ...``: the operation ``args.operation`` names, on the system
    whose launcher is at ADDR."""
    return _act(args.operation, OPERATIONS[args.operation], args)


def _act(name: str, run: Callable[[Connection, argparse.Namespace], Any],
         args: argparse.Namespace) -> int:
    """Connect, run one command, print its result; a sentence on any error (exit 1).
    A Ctrl-C (also the end of ``--follow``) goes on to ``main``: exit 130, one line."""
    try:
        # a --timeout below the connection's own wait bounds it too (it waited 5 s)
        wait = CONNECT_TIMEOUT if args.timeout is None else min(CONNECT_TIMEOUT, args.timeout)
        with connect(args.address, timeout=wait) as system:
            shown = run(system, args)
    except (PB3AError, ClusterKeyError, ValueError) as exc:
        print(f"pb3a {name}: {exc}", file=sys.stderr)
        return 1
    except zmq.ZMQError as exc:                 # an address ZeroMQ cannot use
        print(f"pb3a {name}: cannot reach {args.address}: {exc}", file=sys.stderr)
        return 1
    if shown is not None:
        text, data = shown
        print(json.dumps(plain(data), indent=2, default=repr, allow_nan=False)
              if args.json else text)
    return 0


def _status(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    stats = system.stats(timeout=args.timeout)
    return format_table(stats), stats.to_json()


def _state(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    state = system.state(args.module, timeout=args.timeout)
    # Shown as Python writes a NaN or an infinity (--json: null, JSON has neither), an
    # array as numpy abbreviates it (--json: whole)
    return json.dumps(plain(state, finite=False, arrays=False), indent=2, default=repr), state


def _set(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    """Each value made the type of the field's current value (``_fit``); nothing is set
    unless every field fits and the module has it. A state this process cannot read is
    set as given. The read and the edit share one timeout (the system's by default); a
    read that runs out of it (the module busy in a call) ends the command at once."""
    values, texts = _values(args.values)
    deadline = time.monotonic() + (system.timeout if args.timeout is None else args.timeout)
    try:
        now = system.state(args.module, timeout=args.timeout)
    except RuntimeTimeout:
        # (it was taken for a state that cannot be read: the edit waited the whole
        # timeout again, and said it had waited what was left of it)
        raise
    except PB3AError:
        now = {}
    wrong = _fit(args.module, values, texts, now)
    # (period is the runtime's, not in the state: set_state takes it, see Operations.retime)
    unknown = sorted(set(values) - set(now) - {"period"}) if now else []
    if unknown:             # (the worker's KeyError said it, behind "worker 'node/m-x'")
        wrong.append(f"{args.module} has no state {', '.join(map(repr, unknown))}; its "
                     f"state: {', '.join(now)} (and its period)")
    if wrong:
        raise ValueError("; ".join(wrong) + "; nothing was set")
    system.set_state(args.module, values,            # (one timeout for both calls)
                     timeout=max(0.1, deadline - time.monotonic()))
    told = ", ".join(f"{key} = {plain(value, finite=False, arrays=False)!r}"
                     for key, value in values.items())
    return f"{args.module}: {told}", {"module": args.module, "set": values}


def _fit(module: str, values: dict[str, Any], texts: list[str],
         like: dict[str, Any]) -> list[str]:
    """Make each of ``values`` the type of the same field in ``like`` (a module's state,
    or its class's defaults), as the State Editor does (``coerce``: JSON writes 4.0 as
    4, and gain=4 made Scale's float output an int, refused at every value); the
    sentences saying what does not fit. Text (not JSON) is refused for a field that
    holds no text."""
    wrong = [f"{name}={values[name]} is not JSON, and {module}.{name} is "
             f"{type(like[name]).__name__} ({like[name]!r}), not text: give it as JSON "
             "(true, false, 0.3, NaN, [1, 2], \"text\")" for name in texts
             if like.get(name) is not None and not isinstance(like[name], str)]
    for name in [name for name in values if name in like and name not in texts]:
        try:
            values[name] = coerce(name, like[name], values[name])
        except ValueError as exc:
            wrong.append(f"{module}: {exc}")
    return wrong


def _migrate(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    """What the move did; a module that runs on the node already is said to, nothing
    moved (it printed "ctl: b -> b, paused 0.0 ms, ...", as if it had moved)."""
    report = system.migrate(args.module, args.node, timeout=args.timeout)
    if not report.moved:
        return (f"{report.module} already runs on node {report.destination}; nothing moved",
                dataclasses.asdict(report))
    return (f"{report.module}: {report.source} -> {report.destination}, paused "
            f"{report.pause_s * 1e3:.1f} ms, {report.state_bytes} bytes of state, "
            f"{report.links} link{'s' * (report.links != 1)} re-wired"), dataclasses.asdict(report)


def _swap(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    """The swap's event says whether the class's module was reloaded first (its file had
    changed since the launcher imported it), which the line says too."""
    before = _newest_seq(system)
    kept = system.swap(args.module, args.cls, timeout=args.timeout)
    swapped = _own_event(system, before, "module_swapped", args.module, kept=kept)
    reloaded = swapped.get("reloaded")
    dropped = swapped.get("dropped", [])
    said = (f"module {reloaded} changed since it was imported: reloaded; "
            if reloaded else "")
    return (f"{said}{args.module} is now {args.cls}; state kept: "
            f"{', '.join(kept) or '(none)'}"
            + (f"; dropped (the class has no such fields): {', '.join(dropped)}"
               if dropped else ""),
            {"module": args.module, "class": args.cls, "kept": kept, "dropped": dropped,
             "reloaded": reloaded})


def _reload(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    system.reload(args.module, timeout=args.timeout)
    return (f"{args.module} reloaded: a swap or add from now on gets its file as "
            "it is now; running modules keep their code until swapped",
            {"module": args.module, "reloaded": True})


def _relink(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    system.relink(args.src, args.dst, policy=args.policy, timeout=args.timeout)
    return (f"{args.dst} is fed by {args.src} now",
            {"from": args.src, "to": args.dst, "policy": args.policy})


def _add(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    """Each value made the type of the class's default for that field, as ``pb3a set``
    does with the current state; a class this process cannot import (served code, say)
    is added with the values as given. The add's event says whether the class's module
    was reloaded first (its file had changed since the launcher imported it), which the
    line says too, as ``pb3a swap``'s does."""
    state, texts = _values(args.state)
    defaults = _class_defaults(args.cls, args.timeout) if state else {}
    wrong = _fit(args.module, state, texts, defaults)
    if wrong:
        raise ValueError("; ".join(wrong) + "; nothing was added")
    before = _newest_seq(system)
    system.add(args.module, args.cls, node=args.node, period=args.period,
               fixed_rate=args.fixed_rate, state=state, timeout=args.timeout)
    reloaded = _own_event(system, before, "module_added", args.module,
                          inside=True).get("reloaded")
    said = f"module {reloaded} changed since it was imported: reloaded; " if reloaded else ""
    inside = {name: module.node for name, module in system.topology(
        timeout=args.timeout).modules.items() if name.startswith(f"{args.module}/")}
    if inside:                          # a macro: its modules, each where it runs
        return (f"{said}{args.module} ({args.cls}) runs: " + ", ".join(
            f"{name} on node {node}" for name, node in inside.items()),
            {"module": args.module, "class": args.cls, "modules": inside,
             "reloaded": reloaded})
    where = system.where(args.module, timeout=args.timeout)
    return (f"{said}{args.module} ({args.cls}) runs on node {where}",
            {"module": args.module, "class": args.cls, "node": where, "reloaded": reloaded})


def _newest_seq(system: Connection) -> int:
    """The number of the system's newest event (0: none yet), read in one event: a
    change's own event is looked for after it (``_own_event``); from the whole log of a
    launcher older than ``events(last=...)``."""
    try:
        newest = system.events(timeout=0.0, last=1)
    except RuntimeFailure:
        newest = system.events(timeout=0.0)[-1:]
    return newest[-1].seq if newest else 0


def _own_event(system: Connection, since: int, kind: str, module: str, *,
               inside: bool = False, **said: Any) -> dict[str, Any]:
    """The detail of the first ``kind`` event of ``module`` (``inside``: or of a module
    inside it, a macro instance's) after event ``since``, read before the change that
    recorded it, whose detail has what the change ``said`` (a swap's ``kept``), if one
    has: that change's own ({} if the system no longer keeps it). The whole log was read
    for the newest such event, which was another's when someone changed the same module
    again between the change and the read; the first after ``since`` is another's when
    someone changed it between that read and the change."""
    found = [event.detail for event in system.events(since, timeout=0.0)
             if event.kind == kind and (event.subject == module or (
                 inside and event.subject.startswith(f"{module}/")))]
    return next((detail for detail in found
                 if all(detail.get(key) == value for key, value in said.items())),
                found[0] if found else {})


def _class_defaults(ref: str, timeout: float | None) -> dict[str, Any]:
    """The class-level state of the module class ``ref`` names, if this process can
    import it and the class reads its state by reflection (one that defines its own
    ``get_state`` alone knows its fields); else nothing. Its module file is tried in a
    child process first, within ``timeout`` (at most ``CLASS_IMPORT_TIMEOUT``): one that
    loops, exits or crashes as it is imported hung or ended this command, and is now
    left for the launcher to refuse, saying so."""
    wait = CLASS_IMPORT_TIMEOUT if timeout is None else min(timeout, CLASS_IMPORT_TIMEOUT)
    try:
        cls = resolve_class(ref, watch=tried_first(wait, "give a longer --timeout"))
    except Exception:               # (its own problems are the launcher's to name)
        return {}
    return class_state(cls)


def _remove(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    system.remove(args.module, timeout=args.timeout, force=args.force)
    return f"{args.module} removed", {"module": args.module, "removed": True}


def _restart(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    system.restart(args.module, timeout=args.timeout, force=args.force)
    return f"{args.module} restarted", {"module": args.module, "restarted": True}


def _nodes(system: Connection, args: argparse.Namespace) -> tuple[str, Any]:
    nodes = system.nodes(timeout=args.timeout)
    return format_nodes(nodes), {name: dataclasses.asdict(node) for name, node in nodes.items()}


def _events(system: Connection, args: argparse.Namespace) -> None:
    """``pb3a events``: one line per event, first its local time to the millisecond
    (``12:03:04.512``: the text had none, only ``--json`` had ``time``), then its
    number, kind, subject and detail."""
    def line(event: Event) -> str:
        detail = ", ".join(f"{k}={v}" for k, v in event.detail.items())
        clock = f"{time.strftime('%H:%M:%S', time.localtime(event.time))}." \
                f"{int(event.time % 1 * 1000):03d}"
        return f"{clock} {event.seq:>5} {event.kind:<16} {event.subject} {detail}".rstrip()
    _follow(lambda seen, wait: system.events(seen, timeout=wait), line, args)


def _logs(system: Connection, args: argparse.Namespace) -> None:
    _follow(lambda seen, wait: system.logs(seen, module=args.module, timeout=wait),
            lambda entry: entry.line(), args, every=args.module is None)


# what each command on a running system does, by its name on the command line
OPERATIONS: dict[str, Callable[[Connection, argparse.Namespace], Any]] = {
    "status": _status, "state": _state, "set": _set, "migrate": _migrate, "swap": _swap,
    "reload": _reload, "relink": _relink, "add": _add, "remove": _remove, "restart": _restart,
    "nodes": _nodes, "logs": _logs, "events": _events}


def _follow(fetch: Callable[[int, float], list[Any]], line: Callable[[Any], str],
            args: argparse.Namespace, every: bool = True) -> None:
    """Print what ``fetch`` returns after the last one printed (numbered by ``seq``), as
    a line or as JSON; with ``--follow``, until Ctrl-C. With ``every`` (it returns every
    entry, none filtered out), a number skipped is entries the system no longer keeps,
    which a follower that fell behind is told on stderr (they were skipped unsaid)."""
    seen = 0
    while True:
        try:
            items = fetch(seen, 1.0 if args.follow else 0.0)
        except SystemStopped as exc:              # a follower's normal end
            print(f"pb3a {exc}", file=sys.stderr)
            return
        for item in items:
            if every and seen and item.seq > seen + 1:
                print(f"pb3a: {item.seq - seen - 1} entries before {item.seq} are no longer "
                      "kept by the system, so they were not printed (this reader fell "
                      "behind)", file=sys.stderr, flush=True)
            seen = item.seq
            print(json.dumps(plain(dataclasses.asdict(item))) if args.json else line(item),
                  flush=True)
        if not args.follow:
            return


def _values(pairs: list[str]) -> tuple[dict[str, Any], list[str]]:
    """``NAME=VALUE`` pairs, and the names of those kept as text: a VALUE that is JSON
    is read as JSON, else kept as text."""
    values, texts = {}, []
    for pair in pairs:
        name, equals, text = pair.partition("=")
        if not equals or not name.isidentifier():
            raise ValueError(f"{pair!r} is not NAME=VALUE (e.g. gain=2.5)")
        try:
            values[name] = json.loads(text)
        except json.JSONDecodeError:
            values[name] = text
            texts.append(name)
    return values, texts
