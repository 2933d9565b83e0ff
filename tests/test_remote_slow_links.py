"""Remote links over a slow radio link, end to end: two nodes, the reader's node
reaching the writer's through a rate-limited proxy (``throttle``). A dropping link
slower than its writer does not send what it cannot carry; what it did not send is
counted in the link's ``drops`` in ``run.stats()``, exactly."""

from __future__ import annotations

import functools
import time
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import eventually
from sample_modules import Frames, FrameSink
from throttle import Throttle

from pb3a import System
from pb3a.transport import replication
from pb3a.transport.auth import Opener
from pb3a.transport.replication import Follower

FRAMES = 60                # 64 KiB frames, 20 a second: 3 s of writing
LINK = "camera.out->viewer.x"


@pytest.fixture
def radio(monkeypatch: pytest.MonkeyPatch) -> Iterator[Throttle]:
    """A 2 Mbit/s link (a 64 KiB frame takes 0.26 s) that the followers of this process
    (node b, embedded) reach every writer through."""
    follow = Follower.follow
    with Throttle(2e6) as link:
        def slow_follow(self: Follower, topic: str, data: str, control: str,
                        **kwargs: Any) -> None:
            follow(self, topic, link.route(data), link.route(control), **kwargs)
        monkeypatch.setattr(Follower, "follow", slow_follow)
        yield link


def _camera_to_viewer(name: str, policy: str = "queue:1000") -> System:
    system = System(name)
    system.node("a")
    system.node("b")
    system.add("camera", Frames, node="a", state={"limit": FRAMES})
    system.add("viewer", FrameSink, node="b")
    system.link("camera.out", "viewer.x", policy=policy)
    return system


def _settled(run: Any) -> tuple[Any, dict[str, Any], Follower]:
    """Once the camera wrote every frame and each was received or counted dropped: the
    link's figures, the viewer's state and node b's follower; checked again a second
    later (two heartbeats, whose SYNC repeats what was not sent), so a count that
    overshoots fails too."""
    eventually(lambda: run.state("camera")["sent"] == FRAMES, timeout=30.0,
               what="the camera's frames written")

    def accounted() -> Any:
        link = run.stats().links[LINK]
        return link.values + link.drops >= FRAMES and link.pending == 0 and link
    eventually(accounted, timeout=20.0, what="every frame received or counted dropped")
    time.sleep(2 * replication.HEARTBEAT_S)     # (what a count overshoots by, if it does)
    follower = run._launcher.nodes["b"].bridge._follower
    return run.stats().links[LINK], run.state("viewer"), follower


@pytest.mark.timeout(90)
def test_a_slow_dropping_link_counts_what_its_sender_did_not_send_in_the_link_drops(
        radio: Throttle) -> None:
    """A camera faster than its link: the frames its sender did not send are the link's
    ``drops`` in ``run.stats()``, and every frame written is either received or one of
    them (received + drops = written), once; the viewer gets the others in order."""
    with _camera_to_viewer("slow-link-drops").launch() as run:
        link, viewer, follower = _settled(run)
    numbers = viewer["numbers"]
    assert link.values + link.drops == FRAMES, (link.values, link.drops)
    assert link.values == len(numbers)
    assert link.drops == follower.dropped["camera.out"] > 0      # the link's, not the ring's
    assert numbers == sorted(set(numbers)) and numbers[0] == 1
    assert viewer["duplicates"] == viewer["out_of_order"] == 0
    assert link.link_failures == 0 and not follower.link_failures
    assert list(radio.connections.values()) == [1, 1]            # never cut


@pytest.mark.timeout(90)
def test_a_repair_over_values_not_sent_is_answered_skipped_and_the_viewer_sees_no_harm(
        radio: Throttle, monkeypatch: pytest.MonkeyPatch) -> None:
    """The notices that announce values not sent are lost on the way (as in a
    reconnection): the follower sees a gap before the next frame and asks for a repair;
    the sender answers that those values were not sent (SKIPPED), so the viewer gets
    every frame that went, in order, once, nothing is counted lost, and the drops are
    still exact."""
    handle, lost, answered = Follower._handle, [], []

    def losing(self: Follower, message: Any, live: bool) -> Any:
        if message.kind == replication.SKIPPED:
            if live:
                lost.append(message)
                return None                      # lost on the way
            answered.append(message)
        return handle(self, message, live)
    monkeypatch.setattr(Follower, "_handle", losing)
    with _camera_to_viewer("slow-link-repairs").launch() as run:
        link, viewer, follower = _settled(run)
    numbers = viewer["numbers"]
    assert lost and answered, "no notice was lost, or no repair was answered SKIPPED"
    assert link.values + link.drops == FRAMES, (link.values, link.drops)
    assert link.values == len(numbers) and link.drops > 0
    assert numbers == sorted(set(numbers)) and numbers[0] == 1
    assert viewer["duplicates"] == viewer["out_of_order"] == 0
    assert link.link_failures == 0 and not follower.link_failures
    assert not follower.duplicates


@pytest.mark.timeout(90)
def test_a_lossless_link_further_behind_than_the_freshness_window_takes_each_value_once(
        radio: Throttle, monkeypatch: pytest.MonkeyPatch) -> None:
    """A lossless link whose values wait in the slow link's queue longer than the
    freshness window (here 1 s; 60 s as shipped: 1 MiB frames at 2 Mbit/s queue 134 s
    behind) takes each as it comes: its sender is known by then, and its counters order
    them. Each was refused as not fresh, asked for again and sent again behind the rest
    (40 frames of 256 KiB over 1 Mbit/s took 115 s, not 84, and 13.9 MB crossed)."""
    monkeypatch.setattr(replication, "Opener", functools.partial(Opener, fresh_s=1.0))
    with _camera_to_viewer("slow-lossless", policy="lossless:64").launch() as run:
        eventually(lambda: len(run.state("viewer")["numbers"]) == FRAMES, timeout=60.0,
                   what="every frame at the viewer")
        follower = run._launcher.nodes["b"].bridge._follower
        viewer = run.state("viewer")
        link = run.stats().links[LINK]
    assert viewer["numbers"] == list(range(1, FRAMES + 1))
    assert viewer["duplicates"] == viewer["out_of_order"] == 0
    assert follower._opener.rejected["not fresh"] == 0, follower._opener.rejected
    assert link.drops == 0 and link.link_failures == 0
