"""``pb3a run``: launch a system, show a live status table, stop cleanly.

Ctrl-C, SIGTERM or the end of ``--for`` leave the ``with`` block, which stops
every module in reverse start order and frees every process and segment.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import math
import os
import re
import signal
import sys
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, TextIO

from pb3a.cli.standard_output import output_gone
from pb3a.launch.running import launch
from pb3a.node.remote import ON_THEIR_OWN, SILENT_S
from pb3a.processes import INTERRUPTED, end_on_signals, start_resource_tracker

if TYPE_CHECKING:
    from pb3a.config.plan import Plan
    from pb3a.stats import NodeStats, SystemStats

REFRESH_S = 1.0
LAST_ERROR_WIDTH = 60        # characters of a module's last error in the table
STUCK_S = 1.0                # a call this long is shown beside the module's status
# a ConfigError's first line (``pb3a.errors``), the problems on the lines after it
_PROBLEMS_HEAD = re.compile(r"\b\d+ problems? in the configuration:\s*")


def format_table(stats: SystemStats) -> str:
    """The status table: one row per module, one per link, one per node (the rows
    ``pb3a nodes`` prints: it left out the embedded nodes, which ``pb3a nodes`` showed).
    A module's status says the call it is stuck in, and the change in progress that
    acts on it ("running (migrate slow to b for 5 s)"); its period, the one it steps at
    now (set live too), "-" for one run only on events (a period its class sets
    without a step() included), "0.02 fixed" for a fixed rate, whose status says the
    periods it skipped ("(overruns 3)"), if any; its last error, how long ago it was
    raised. A link whose reader is silent shows "-" for its values and rate, which are
    not known."""
    rows = [("module", "node", "pid", "status", "period s", "steps", "events", "cpu s",
             "errors", "last error")]
    now = time.time()
    for name, m in stats.modules.items():
        fixed = m.fixed_rate and m.period is not None
        status = m.status + (" (silent)" if m.silent else "") \
            + (f" (in {m.calling} for {m.calling_s:.0f} s)" if m.calling_s >= STUCK_S else "") \
            + (f" ({m.change} for {m.change_s:.0f} s)" if m.change else "") \
            + (f" (restarts {m.restarts})" if m.restarts else "") \
            + (f" (overruns {m.overruns})" if fixed and m.overruns else "")
        rows.append((name, m.node, str(m.pid or "-"), status,
                     "-" if m.period is None else f"{m.period:g}" + " fixed" * fixed,
                     str(m.steps), str(m.events), f"{m.cpu:.2f}", str(m.errors),
                     _shortened(_dated(m.last_error, m.last_error_at, now))))
    lines = _columns(rows)
    if stats.links:
        lines.append("")
        # (lost: values known lost with a node or a cut link, which drops do not count)
        link_rows = [("link", "transport", "policy", "values", "rate/s", "drops", "lost",
                      "waits", "latency")]
        for link in stats.links.values():
            latency = link.latency
            # (a silent reader's values and rate are not known now: those of its
            # node's last report, or 0 for a worker that did not answer)
            link_rows.append((f"{link.src} -> {link.dst}", link.transport, link.policy,
                              "-" if link.silent else str(link.values),
                              "-" if link.silent else f"{link.rate:.0f}", str(link.drops),
                              str(link.link_failures), str(link.waits),
                              "-" if math.isnan(latency) else f"{latency * 1e6:.0f} us"))
        lines += _columns(link_rows)
    if stats.nodes:
        lines += ["", format_nodes(stats.nodes)]
    for failure in stats.failures[-5:]:
        lines.append(f"! {failure}")
    return "\n".join(lines)


def format_nodes(nodes: dict[str, NodeStats]) -> str:
    """One row per node: its address, health (its epoch once it rejoined, its silence
    once it has missed two heartbeats: "up (silent 0.9 s)", its modules then shown as
    its last report had them; it said "up" until it was lost) and round-trip time (the
    last measured)."""
    rows = [("node", "address", "health", "rtt")]
    refusals = []
    for name, node in nodes.items():
        said = [f"epoch {node.epoch}"] * (node.epoch != 1) \
            + [f"silent {node.silent_s:.1f} s"] * (node.silent_s > SILENT_S)
        health = "LOST" if not node.up else "up" + (f" ({', '.join(said)})" if said else "")
        if node.refused and not node.up:        # (what keeps it from rejoining)
            health += " (refuses us: see below)"
            refusals.append(f"{name}: {node.refused}")
        rows.append((name, node.address or "(embedded)", health,
                     "-" if math.isnan(node.rtt) else f"{node.rtt * 1e3:.1f} ms"))
    return "\n".join(_columns(rows) + refusals)


def _dated(error: str, at: float | None, now: float) -> str:
    """A module's last ``error``, how long ago it was raised first ("3 s ago: ..."), so
    that one long past, its cause since mended, is not taken for a fresh one."""
    if not error or at is None:
        return error
    ago = max(0.0, now - at)
    age = (f"{ago:.0f} s" if ago < 120 else f"{ago / 60:.0f} min" if ago < 7200
           else f"{ago / 3600:.0f} h")
    return f"{age} ago: {error}"


def _shortened(text: str, most: int = LAST_ERROR_WIDTH) -> str:
    """``text`` on one line of ``most`` characters at most: its lines joined by "; ",
    a ``ConfigError``'s "N problems in the configuration:" dropped, so that the cause
    shows (its first line alone was shown, the cause on a row of its own, breaking the
    table)."""
    text = "; ".join(line.strip() for line in _PROBLEMS_HEAD.sub("", text).splitlines()
                     if line.strip())
    return text if len(text) <= most else text[:most - 3] + "..."


def _columns(rows: list[tuple[str, ...]]) -> list[str]:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return ["  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
            for row in rows]


def run_with_status(plan: Plan, seconds: float | None, out: TextIO | None = None,
                    listen: str | None = None, final: bool = False) -> int:
    """Run ``plan`` until ``seconds`` pass (None: until Ctrl-C, SIGTERM or SIGHUP), the
    table on ``out`` (default: stdout); 0 once stopped (the nodes that did not confirm
    their stop, if any, named). The launcher takes ``pb3a.connect``
    and ``pb3a status ADDR`` ... at ``listen`` (default: where the remote nodes reach
    it, else loopback). ``final``: the process ends once it returns (``patient_stop``)."""
    # (no stdout at all when started with it closed: `pb3a run F >&-`)
    out = out or sys.stdout or open(os.devnull, "w")  # noqa: SIM115
    live = out.isatty()
    started = time.monotonic()

    def show(text: str) -> None:
        """Write ``text``; a reader gone (`pb3a run F | head`) stops no system: the
        output goes nowhere from then on (it was taken for an address error)."""
        try:
            out.write(text)
            out.flush()
        except BrokenPipeError:
            if out is sys.stdout:
                output_gone()

    with patient_stop(show, final=final) as stop:
        with launch(plan, listen=listen) as run:
            stop.running()       # (from the first line on, a signal means a clean stop)
            # a stop left unfinished, as the signal that does so asks, is not finished
            # as the program exits (the close's own hook would, for seconds, and name
            # the modules it gave up on)
            stop.on_leaving(functools.partial(atexit.unregister, run.close_at_exit))
            try:
                address = run.address or run.listen()
                show(f"pb3a: system {run.name!r} running"
                     f"{f' for {seconds:g} s' if seconds else ''}; Ctrl-C stops it; "
                     f"launcher at {address}\n")
                while seconds is None or time.monotonic() - started < seconds:
                    left = REFRESH_S if seconds is None else min(
                        REFRESH_S, seconds - (time.monotonic() - started))
                    if run.wait(max(0.0, left)):
                        break
                    table = format_table(run.stats())
                    show(("\x1b[H\x1b[2J" if live else "\n") + table + "\n")
                stop.begin()     # (a signal just before it is caught below, as the first)
            except KeyboardInterrupt:      # (the stop began with it: ``patient_stop``)
                show("\npb3a: stopping\n")
            final_stats = run.stats()
        stop.end()
        show("\n" + format_table(final_stats) + "\n")
        stuck = run.not_torn_down
        if stuck:       # (it said "stopped cleanly" with a module's teardown not run)
            many = len(stuck) > 1
            show(f"pb3a: stopped; module{'s' if many else ''} {', '.join(stuck)} did not "
                 f"stop in time: {'their workers were' if many else 'its worker was'} "
                 "killed, teardown not run (see the warnings above)\n")
        # (it said "stopped cleanly" with a node's executor running; and a module of a
        # node cut off was said killed, its teardown not run, where that node ran it)
        for node in run.unconfirmed:
            show(f"pb3a: stopped; {_on_their_own(node, run.unreached.get(node, []))}\n")
        if not stuck and not run.unconfirmed:
            show("pb3a: stopped cleanly\n")
        return 0


def _on_their_own(node: str, modules: list[str]) -> str:
    """What becomes of remote node ``node``, whose stop was not confirmed, and of its
    ``modules`` whose stop did not reach it."""
    what = (f"its module {modules[0]} stops on its own" if len(modules) == 1 else
            f"its modules {', '.join(modules)} stop on their own" if modules else
            "its executor stops itself")
    return (f"node {node} did not confirm its stop (cut off, frozen, or out of time): "
            f"{what} {ON_THEIR_OWN} (its log says how)")


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """Inside the block, SIGTERM and SIGHUP (the terminal closed, an ssh session cut)
    raise KeyboardInterrupt as Ctrl-C does: each ends a run the same clean way (a
    SIGHUP killed it, its segments left behind)."""
    start_resource_tracker()
    previous = {signum: signal.signal(signum, _interrupt)
                for signum in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


_STOPPING = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class _Stop:
    """What ``patient_stop`` makes of a signal: where the run is (starting, running,
    stopping, stopped), and how many signals its stop has had."""

    def __init__(self, show: Callable[[str], None]) -> None:
        self._show = show
        self._running = False
        self._stopping = False
        self._stopped = False
        self._unheeded = 0       # the signals that came while it stopped
        self._leave: Callable[[], None] = lambda: None

    def running(self) -> None:
        """The system runs: the next signal begins its stop."""
        self._running = True

    def begin(self) -> None:
        """The stop begins (the run's time is up)."""
        self._stopping = True

    def end(self) -> None:
        """The stop is over: a signal changes nothing any more (what is left is to say
        how it went)."""
        self._stopped = True

    @property
    def over(self) -> bool:
        """Whether the stop is over (``end``)."""
        return self._stopped

    def on_leaving(self, leave: Callable[[], None]) -> None:
        """Call ``leave`` as a signal leaves the stop unfinished."""
        self._leave = leave

    def interrupted(self, signum: int, frame: object) -> None:
        """The handler of ``_STOPPING``."""
        if self._stopped:
            return
        if self._stopping:
            self._unheeded += 1
            if self._unheeded == 1:
                self._show("pb3a: still stopping (seconds at most); interrupt once more "
                           "to leave it unfinished\n")
                return
            self._leave()
        self._stopping = self._running
        raise KeyboardInterrupt


@contextlib.contextmanager
def patient_stop(show: Callable[[str], None], final: bool = False) -> Iterator[_Stop]:
    """Inside the block, Ctrl-C, SIGTERM and SIGHUP (the terminal closed, an ssh session
    cut) raise KeyboardInterrupt (a SIGHUP killed a run, its segments left behind), until
    it gives the system as running (``_Stop.running``). From then on the first begins
    the stop (raising KeyboardInterrupt there), as does the run's end (``_Stop.begin``);
    one while it stops is answered with a line and the stop goes on, which takes
    seconds at most; the next leaves it unfinished (KeyboardInterrupt); once it is over
    (``_Stop.end``), they change nothing. An impatient second Ctrl-C cut the stop short:
    exit 130 after "stopping", and teardown noise (BufferError, "leaked shared_memory
    objects") on the terminal.

    Each signal is counted by its handler, as it comes: one that came as the first was
    being answered, before the stop was said to have begun, was taken for a third.
    ``final`` (the ``pb3a`` program, which ends once the block is left): from then on
    the three end it at once with the status decided (``end_on_signals``), not given
    back. Two quick Ctrl-Cs (the first stops the workers too, so the stop takes a
    tenth of a second) ended a clean stop with exit 130: the second, once the stop was
    over, raised KeyboardInterrupt after "stopped cleanly", or killed the interpreter
    as it exited (SIGINT's default by then)."""
    start_resource_tracker()
    stop = _Stop(show)
    previous = {signum: signal.signal(signum, stop.interrupted) for signum in _STOPPING}
    try:
        yield stop
    finally:
        if final:           # (its status decided: 0 once the stop is over, else 130)
            end_on_signals(0 if stop.over else INTERRUPTED)
        else:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
