"""A remote link over a slow radio link: a camera's frames between two nodes.

A ``Camera`` on node a writes a frame every ``--period`` (10 a second by default) to a
``Viewer`` on node b, through a rate-limited TCP proxy (``tests/throttle.py``, the one
the tests use: one token bucket per direction, shared by the link's connections, and
small buffers of its own, so the writer feels the pace through TCP), for each rate
(``--mbit``), link policy (``--policies``) and frame size (``--sizes``), ``--seconds``
each. Node b is embedded: its follower reaches the writer through the proxy because
``Follower.follow`` is wrapped to follow the proxy's addresses. With ``--fast-reader``,
a second viewer on node c reads the same frames straight over loopback, beside the
slow one (a topic read by two nodes, one behind a slow link); with ``--fast-leaves S``
too, that viewer is removed ``S`` seconds into the run (its node's follower unfollows),
leaving the slow one the only follower.

Per run: the connections made through the proxy (2, data and control, for a link never
cut; each reconnection adds one) and which end closed those that ended; the repairs
the follower asked for; values lost for good (``link_failures``), frames the viewer
never saw (``skipped``: a dropping queue's overflow, a lossless writer's timeouts)
and saw twice; the writer's and the reader's memory growth (the peak RSS over the
run less the RSS at its start: the writer's worker process, this process); the
goodput (frames received, in Mbit/s) against what crossed the proxy; and the oldest
a frame was on arrival (per viewer, with ``--fast-reader``). With ``--fast-leaves``:
the writer's memory growth from the viewer's removal on (the peak less the RSS then),
and how long after it node b's follower was served over PUB again (to ``SAMPLE_S``;
None: still served on its own at the end).
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

import psutil
from _common import machine, main_guard, wait_for
from _modules import Camera, Viewer
from throttle import Throttle

from pb3a import System
from pb3a.transport import replication
from pb3a.transport.replication import Follower, follower_id, wire

SAMPLE_S = 0.5             # how often memory is read


def one_run(mbit: float, policy: str, size: int, period: float, seconds: float,
            fast_reader: bool = False, fast_leaves: float | None = None) -> dict:
    """One camera stream through the slow link for ``seconds``: its figures."""
    follow, ask = Follower.follow, Follower._ask
    asked: collections.Counter[int] = collections.Counter()
    slow_ids = {follower_id("b", epoch) for epoch in range(4)}     # (node b's follower)
    with Throttle(mbit * 1e6) as radio:
        def slow_follow(self: Follower, topic: str, data: str, control: str,
                        **kwargs: Any) -> None:
            if self._identity in slow_ids:
                data, control = radio.route(data), radio.route(control)
            follow(self, topic, data, control, **kwargs)

        def counted_ask(self: Follower, *args: Any) -> None:
            asked[args[1]] += 1
            ask(self, *args)
        Follower.follow, Follower._ask = slow_follow, counted_ask
        try:
            system = System(f"slow-link-{int(mbit)}")
            system.node("a")
            system.node("b")
            system.add("camera", Camera, node="a", period=period, state={"size": size})
            system.add("viewer", Viewer, node="b")
            system.link("camera.out", "viewer.x", policy=policy)
            if fast_reader:
                system.node("c")
                system.add("fast_viewer", Viewer, node="c")
                system.link("camera.out", "fast_viewer.x", policy=policy)
            with system.launch() as run:
                pid = wait_for(lambda: run.stats().modules["camera"].pid, 10, "a writer pid")
                writer, reader = psutil.Process(pid), psutil.Process()
                base = (writer.memory_info().rss, reader.memory_info().rss)
                grown = [0, 0]
                left, left_rss, grown_after, back_s, fast = None, 0, 0, None, None
                started = time.monotonic()
                while time.monotonic() - started < seconds:
                    time.sleep(SAMPLE_S)
                    for i, process in enumerate((writer, reader)):
                        grown[i] = max(grown[i], process.memory_info().rss - base[i])
                    if left is None and fast_leaves is not None \
                            and time.monotonic() - started >= fast_leaves:
                        fast = run.state("fast_viewer")      # (its figures until then)
                        run.remove("fast_viewer")
                        left, left_rss = time.monotonic(), writer.memory_info().rss
                    elif left is not None:
                        grown_after = max(grown_after, writer.memory_info().rss - left_rss)
                        follows = run._launcher.nodes["b"].bridge._follower._follows
                        mode = follows.get(b"camera.out\0")
                        if back_s is None and mode is not None and not mode.direct:
                            back_s = round(time.monotonic() - left, 1)
                camera, viewer = run.state("camera"), run.state("viewer")
                if fast_reader and left is None:
                    fast = run.state("fast_viewer")
                link = run.stats().links["camera.out->viewer.x"]
                # (before the nodes stop: they close their connections then)
                connections, ended = sum(radio.connections.values()), dict(radio.ended_by)
                forwarded = radio.forwarded
        finally:
            Follower.follow, Follower._ask = follow, ask
    return {"mbit": mbit, "policy": policy, "frame_bytes": size,
            "sent": camera["sent"], "write_timeouts": camera["timeouts"],
            "received": viewer["received"], "skipped": viewer["skipped"],
            "repeated": viewer["repeated"], "link_failures": link.link_failures,
            "connections": connections, "ended_by": ended,
            "repairs_asked": asked[replication.REPAIR],
            "writer_grew_mib": grown[0] >> 20, "reader_grew_mib": grown[1] >> 20,
            "goodput_mbit": round(viewer["received"] * size * 8 / seconds / 1e6, 2),
            "crossed_mbit": round(forwarded * 8 / seconds / 1e6, 2),
            "oldest_frame_s": round(viewer["max_age_s"], 1),
            **({"fast_received": fast["received"], "fast_skipped": fast["skipped"],
                "fast_oldest_frame_s": round(fast["max_age_s"], 2)} if fast else {}),
            **({"writer_grew_after_leave_mib": grown_after >> 20, "back_on_pub_s": back_s}
               if fast_leaves is not None else {})}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mbit", default="2,5,10", help="link rates, Mbit/s")
    parser.add_argument("--policies", default="queue:8,lossless:8")
    parser.add_argument("--sizes", default=str(1 << 20), help="frame sizes, bytes")
    parser.add_argument("--period", type=float, default=0.1, help="seconds between frames")
    parser.add_argument("--seconds", type=float, default=15.0, help="of each run")
    parser.add_argument("--fast-reader", action="store_true",
                        help="a second viewer, on node c, reads the frames unthrottled")
    parser.add_argument("--fast-leaves", type=float, default=None, metavar="S",
                        help="with --fast-reader: remove that viewer S seconds into each run")
    args = parser.parse_args()
    if args.fast_leaves is not None and not args.fast_reader:
        parser.error("--fast-leaves removes the viewer --fast-reader adds: give both")

    def body(result: dict[str, Any]) -> None:
        result["machine"] = machine()
        result["peer_timeout_ms"] = wire.PEER_TIMEOUT_MS
        result["runs"] = runs = []
        for size in (int(s) for s in args.sizes.split(",")):
            for mbit in (float(m) for m in args.mbit.split(",")):
                for policy in args.policies.split(","):
                    runs.append(one_run(mbit, policy, size, args.period, args.seconds,
                                        args.fast_reader, args.fast_leaves))
    main_guard(body)


if __name__ == "__main__":
    main()
