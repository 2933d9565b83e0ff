"""Every TCP socket a running system listens on, bombarded with garbage, unsigned,
wrongly signed, replayed and oversized frames: nothing is deserialized, nothing
crashes, and the system goes on."""

from __future__ import annotations

import contextlib
import pickle
import random

import psutil
import pytest
import zmq
from conftest import eventually
from sample_modules import Collector, Counter

from pb3a import System
from pb3a.daemons.node_controller import Limits, NodeController
from pb3a.transport.auth import ClusterKey, Sealer

exploded: list[str] = []


class Bomb:
    """Unpickling this would append to ``exploded``: proof of deserialization."""

    def __reduce__(self) -> tuple:
        return (exploded.append, ("boom",))


def _listening(pids: set[int]) -> list[str]:
    return sorted({f"tcp://{c.laddr.ip}:{c.laddr.port}" for c in psutil.net_connections("tcp")
                   if c.status == psutil.CONN_LISTEN and c.pid in pids})


def _frames(rng: random.Random, genuine: list[bytes]) -> list[list[bytes]]:
    bomb = pickle.dumps(Bomb())
    wrong = Sealer(ClusterKey.load({"PB3A_KEY": "w" * 40}))
    stale = Sealer(ClusterKey.load(), epoch=1)
    return [
        [b"garbage"], [bomb], [b"\0"], [b""] * 3, [bomb] * 70,
        [rng.randbytes(rng.randrange(1, 200)) for _ in range(rng.randrange(1, 5))],
        wrong.seal(1, [b"t\0", bomb]), wrong.seal(10, [b"\0" * 8, bomb]),
        genuine, genuine,                                  # genuine once, then replayed
        stale.seal(10, [b"\2" * 8, pickle.dumps(("shutdown", {}))]),   # an earlier epoch
        [b"x" * (3 << 20)],                                # large, unsigned
    ]


@pytest.mark.parametrize("remote", [False, True], ids=["embedded", "node-controller"])
def test_every_listening_socket_refuses_bad_frames_and_the_system_goes_on(remote) -> None:
    controller = NodeController("b", ClusterKey.load(), limits=Limits(max_cpu_percent=101.0))
    system = System("fuzzed")
    system.node("a")
    system.node("b", address=controller.address if remote else None)
    system.add("src", Counter, node="a", period=0.002)
    system.add("dst", Collector, node="b")
    system.link("src.out", "dst.x")
    rng = random.Random(7)
    with contextlib.closing(controller), system.launch() as run:
        run.listen()
        eventually(lambda: run.state("dst")["received"] > 10, what="values flowing")
        me = psutil.Process()
        pids = {me.pid, *(child.pid for child in me.children(recursive=True))}
        addresses = _listening(pids)
        assert run.address in addresses and len(addresses) >= 3    # launcher, PUB, ROUTER
        assert controller.address in addresses                   # ... the controller too
        assert len(addresses) >= (5 if remote else 4)            # ... and b's executor
        context = zmq.Context.instance()
        genuine = Sealer(ClusterKey.load()).seal(10, [b"\1" * 8, bytes(16),   # (no instance:
                                                      pickle.dumps(("stats", {}))])  # told it)
        for address in addresses:
            for kind in (zmq.DEALER, zmq.PUB):
                sock = context.socket(kind)
                sock.setsockopt(zmq.LINGER, 200)
                sock.setsockopt(zmq.SNDTIMEO, 500)     # a DEALER no peer accepts would block
                sock.connect(address)
                with contextlib.suppress(zmq.Again):
                    for frames in _frames(rng, genuine):
                        sock.send_multipart(frames)
                sock.close()
        received = run.state("dst")["received"]
        eventually(lambda: run.state("dst")["received"] > received + 10,
                   what="values still flowing after the bombardment")
        state = run.state("dst")
        alive = [psutil.pid_exists(pid) for pid in pids]
    assert exploded == []
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert all(alive)
