"""The bridge: the receiving end of a node's remote links, on one follower thread."""

from __future__ import annotations

import os
import time

import pytest
from conftest import eventually

from pb3a.node.bridge import Bridge, NoHandshake
from pb3a.transport.auth import ClusterKey
from pb3a.transport.replication import Replicator
from pb3a.transport.ring import ShmRing
from pb3a.transport.shm import segment_name


def test_a_stalled_reader_holds_up_no_other_remote_link_into_its_node() -> None:
    """The bridge writes every remote link's values into its ring on one thread. A
    reader that stalls (frozen, its worker stopped) leaves its ring full, and each
    delivery to it waited for room the write timeout, 0.1 s: every other link into
    the node waited with it (p99 198 ms against 1.8 ms). Once a ring was found full
    after that wait, its writes do not wait until it has room again."""
    key = ClusterKey(os.urandom(32))
    rings = {topic: ShmRing.create(segment_name("ring"), 64) for topic in ("stalled", "read")}
    replicator, bridge = Replicator(key, "127.0.0.1"), Bridge(key)
    bells = [os.eventfd(0) for _ in rings]
    reader = ShmRing.attach(rings["read"].name)
    latencies: list[float] = []
    try:
        for (topic, ring), bell in zip(rings.items(), bells, strict=True):
            replicator.add(f"m.{topic}")
            bridge.open(f"m.{topic}->r.x", f"m.{topic}", ring.name, bell)
        bridge.follow([(f"m.{topic}", replicator.data_address, replicator.control_address,
                        replicator.incarnation) for topic in rings])

        def publish_and_read(count: int) -> None:
            for _ in range(count):
                replicator.publish("m.stalled", time.monotonic())   # (never read)
                replicator.publish("m.read", time.monotonic())
                time.sleep(0.005)
                values, _, _ = reader.drain(1024)
                latencies.extend(time.monotonic() - sent for sent in values)

        eventually(lambda: publish_and_read(1) or latencies, what="the links followed")
        publish_and_read(100)                     # the stalled ring fills (64 slots)
        latencies.clear()
        publish_and_read(200)
    finally:
        bridge.shutdown()
        replicator.close()
        reader.close()
        for ring in rings.values():
            ring.close()
        for bell in bells:
            os.close(bell)
    assert len(latencies) > 150
    slowest = sorted(latencies)[int(0.99 * len(latencies))]
    assert slowest < 0.05, f"p99 {slowest * 1000:.0f} ms"


def test_a_sender_whose_host_does_not_resolve_here_is_named_so() -> None:
    """A node following a publication at a host name its machine does not resolve (the
    sender's node named in the workstation's /etc/hosts only) had no hand-shake, and
    was told only that, as if the ports were closed; the resolver's answer is added."""
    bridge = Bridge(ClusterKey(os.urandom(32)))
    try:
        with pytest.raises(NoHandshake, match=r"no hand-shake with the sender of m\.out at "
                                              r"tcp://no-such-host\.invalid:7 within 0\.5 s "
                                              r"\(no address is known for host "
                                              r"'no-such-host\.invalid'.*on this node's "
                                              r"machine\)"):
            bridge.follow([("m.out", "tcp://no-such-host.invalid:7",
                            "tcp://no-such-host.invalid:8", b"incarnation")], timeout=0.5)
    finally:
        bridge.shutdown()
