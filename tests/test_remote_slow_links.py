"""Remote links over a slow radio link, end to end: two nodes, the reader's node
reaching the writer's through a rate-limited proxy (``throttle``). A dropping link
slower than its writer does not send what it cannot carry; what it did not send is
counted in the link's ``drops`` in ``run.stats()``, exactly."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from conftest import eventually
from sample_modules import Frames, FrameSink
from throttle import Throttle

from pb3a import System
from pb3a.node import wiring
from pb3a.transport import replication
from pb3a.transport.auth import Opener
from pb3a.transport.replication import Follower, follower_id
from pb3a.transport.replication import follower as follower_module

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


def _camera_to_viewer(name: str, policy: str = "queue:1000", size: int = Frames.size,
                      frames: int = FRAMES) -> System:
    system = System(name)
    system.node("a")
    system.node("b")
    system.add("camera", Frames, node="a", state={"limit": frames, "size": size})
    system.add("viewer", FrameSink, node="b")
    system.link("camera.out", "viewer.x", policy=policy)
    return system


def _settled(run: Any, accounted_in: float = 20.0,
             frames: int = FRAMES) -> tuple[Any, dict[str, Any], Follower]:
    """Once the camera wrote every frame and each was received or counted dropped: the
    link's figures, the viewer's state and node b's follower; checked again a second
    later (two heartbeats, whose SYNC repeats what was not sent), so a count that
    overshoots fails too."""
    eventually(lambda: run.state("camera")["sent"] == frames, timeout=30.0,
               what="the camera's frames written")

    def accounted() -> Any:
        link = run.stats().links[LINK]
        return link.values + link.drops >= frames and link.pending == 0 and link
    eventually(accounted, timeout=accounted_in, what="every frame received or counted dropped")
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
    (40 frames of 256 KiB over 1 Mbit/s took 115 s, not 84, and 13.9 MB crossed).
    20 frames are enough: written in 1 s, the last crosses about 4 s behind, four times
    the window (the queue's length, not its count, is the point)."""
    frames = 20
    # (the follower's, in node b's bridge here: the writer's replicator runs in its
    # worker process, which no patch here reaches)
    monkeypatch.setattr(follower_module, "Opener", functools.partial(Opener, fresh_s=1.0))
    with _camera_to_viewer("slow-lossless", policy="lossless:64",
                           frames=frames).launch() as run:
        eventually(lambda: len(run.state("viewer")["numbers"]) == frames, timeout=60.0,
                   what="every frame at the viewer")
        follower = run._launcher.nodes["b"].bridge._follower
        viewer = run.state("viewer")
        link = run.stats().links[LINK]
    assert viewer["numbers"] == list(range(1, frames + 1))
    assert viewer["duplicates"] == viewer["out_of_order"] == 0
    assert follower._opener.rejected["not fresh"] == 0, follower._opener.rejected
    assert link.drops == 0 and link.link_failures == 0


@pytest.mark.timeout(60)
def test_a_reader_whose_slow_link_outlasts_the_drain_s_own_wait_moves_in_the_move_s_time(
        radio: Throttle, monkeypatch: pytest.MonkeyPatch) -> None:
    """What is on the way to a remote reader was awaited the drain's own 10 s at most,
    whatever the move's timeout: a lossless link further behind than that (a slow
    reader's backlog, a slow radio link) failed the move after 10 s of its 25 ("values
    of fast.out still in flight after 10 s"). The drain has what is left of the move's
    time now. (Its own wait is made 0.3 s here: 12 frames of 64 KiB take 3 s over the
    link, and the camera writes them in 0.6.)"""
    frames = 12
    monkeypatch.setattr(wiring, "READY_TIMEOUT", 0.3)
    with _camera_to_viewer("slow-lossless-move", policy="lossless:64",
                           frames=frames).launch() as run:
        eventually(lambda: run.state("camera")["sent"] == frames, what="the frames written")
        assert len(run.state("viewer")["numbers"]) < frames - 3     # (most on the way)
        run.migrate("viewer", to="a", timeout=30)
        assert run.where("viewer") == "a" and run.stats().links[LINK].transport == "shm"
        viewer = eventually(lambda: len((v := run.state("viewer"))["numbers"]) == frames and v,
                            what="every frame at the viewer")
        link = run.stats().links[LINK]
    assert viewer["numbers"] == list(range(1, frames + 1))
    assert link.drops == 0 and link.link_failures == 0


@pytest.fixture
def radio_to_b(monkeypatch: pytest.MonkeyPatch) -> Iterator[Throttle]:
    """A 2 Mbit/s link that node b's follower (embedded here) reaches every writer
    through; the other nodes' followers reach them straight, over loopback."""
    follow = Follower.follow
    slow = {follower_id("b", epoch) for epoch in range(4)}
    with Throttle(2e6) as link:
        def slow_follow(self: Follower, topic: str, data: str, control: str,
                        **kwargs: Any) -> None:
            if self._identity in slow:
                data, control = link.route(data), link.route(control)
            follow(self, topic, data, control, **kwargs)
        monkeypatch.setattr(Follower, "follow", slow_follow)
        yield link


def _beside_a_fast_viewer(name: str, size: int, frames: int = FRAMES) -> System:
    """``_camera_to_viewer``, and a second viewer of the frames on node c."""
    system = _camera_to_viewer(name, size=size, frames=frames)
    system.node("c")
    system.add("fast_viewer", FrameSink, node="c")
    system.link("camera.out", "fast_viewer.x", policy="queue:1000")
    return system


@pytest.mark.timeout(90)
def test_a_slow_follower_beside_a_fast_one_gets_fresh_frames_and_holds_nobody_back(
        radio_to_b: Throttle) -> None:
    """A camera's 128 KiB frames, 20 a second, read on node c over loopback and on node
    b through the 2 Mbit/s link: the slow follower is served on its own (over its
    control connection, one frame on the way at a time), so its frames arrive fresh (a
    frame's crossing: 0.52 s), the rest counted in its link's ``drops`` exactly, in
    order, once; the fast viewer gets every frame at once and the camera writes at its
    own pace. (Before, the publisher queued every frame for the slow follower: they
    arrived up to 28 s late, the last 31 s after the first was written.)"""
    with _beside_a_fast_viewer("slow-beside-fast", 128 * 1024).launch() as run:
        # (before, the slow link took 31 s to carry every frame queued for it)
        link, viewer, follower = _settled(run, accounted_in=45.0)
        camera, fast = run.state("camera"), run.state("fast_viewer")
    assert radio_to_b.connections, "node b's follower did not go through the slow link"
    numbers, ages = viewer["numbers"], viewer["ages"]
    assert max(ages) < 2.5, ages
    going = [age for number, age in zip(numbers, ages, strict=True) if number > FRAMES // 3]
    assert going and max(going) < 1.5, ages                      # (measured: about 0.6)
    assert link.values + link.drops == FRAMES, (link.values, link.drops)
    assert link.values == len(numbers) and link.drops > FRAMES // 2
    assert link.drops == follower.dropped["camera.out"]
    assert numbers == sorted(set(numbers))
    assert viewer["duplicates"] == viewer["out_of_order"] == 0
    assert link.link_failures == 0 and not follower.link_failures
    assert fast["numbers"] == list(range(1, FRAMES + 1))         # every frame ...
    assert max(fast["ages"]) < 1.0, fast["ages"]                 # ... at once
    assert fast["duplicates"] == fast["out_of_order"] == 0
    # the camera's pace: 20 frames a second (3 s), no write held back
    assert camera["last_at"] - camera["first_at"] < 3 * FRAMES * Frames.period, camera
    assert camera["longest_write_s"] < 0.5, camera


def _b_served_on_its_own(run: Any) -> Callable[[], Any]:
    """Node b's follow of the camera as it is at each call (``.direct``: served on its
    own), once it is served on its own."""
    follower = run._launcher.nodes["b"].bridge._follower

    def mode() -> Any:
        return follower._follows[b"camera.out\0"]
    eventually(lambda: mode().direct, timeout=10.0, what="node b served on its own")
    return mode


def _every_frame_once_or_counted(link: Any, viewer: dict, follower: Any, frames: int) -> None:
    """Every frame written is received or counted dropped, as node b's follower counted
    them; those received in order, once; no link failure."""
    numbers = viewer["numbers"]
    assert link.values + link.drops == frames, (link.values, link.drops)
    assert link.values == len(numbers) and link.drops == follower.dropped["camera.out"]
    assert numbers == sorted(set(numbers))
    assert viewer["duplicates"] == viewer["out_of_order"] == 0
    assert link.link_failures == 0 and not follower.link_failures
    assert not follower.duplicates


@pytest.mark.timeout(90)
def test_a_slow_follower_whose_link_gets_fast_goes_back_to_pub_and_gets_every_frame(
        radio_to_b: Throttle) -> None:
    """Node b's follower, served on its own while its link is slow, goes back to PUB
    once a frame crosses in time (the link got fast): from then on it gets every frame,
    in order, once (what was published before its subscription took is counted
    dropped, not replayed over the link), and the accounting stays exact."""
    frames = 120                                                 # 6 s of writing
    with _beside_a_fast_viewer("slow-then-fast", 128 * 1024, frames).launch() as run:
        mode = _b_served_on_its_own(run)
        radio_to_b.set_rate(1e9)
        eventually(lambda: not mode().direct and not mode().joining, timeout=10.0,
                   what="node b back on PUB")
        back_at = run.state("camera")["sent"]
        link, viewer, follower = _settled(run, frames=frames)
    numbers = viewer["numbers"]
    assert back_at < frames - 20, "the camera was done before node b went back to PUB"
    tail = [number for number in numbers if number > back_at + 5]
    assert tail == list(range(back_at + 6, frames + 1)), numbers
    _every_frame_once_or_counted(link, viewer, follower, frames)


@pytest.mark.timeout(90)
def test_a_slow_follower_served_on_its_own_goes_back_to_pub_once_the_fast_viewer_is_removed(
        radio_to_b: Throttle) -> None:
    """Node b's follower, served on its own beside node c's, goes back to PUB once the
    fast viewer is removed (node c's follower unfollows): it takes the RESUME in behind
    the frame on its way (a frame's crossing: 0.52 s), and from then on is a lone slow
    link; the accounting stays exact (received + drops = written), in order, once.
    Before, it stayed served on its own for as long as it followed."""
    frames = 120                                                 # 6 s of writing
    with _beside_a_fast_viewer("fast-leaves", 128 * 1024, frames).launch() as run:
        mode = _b_served_on_its_own(run)
        run.remove("fast_viewer")
        removed = time.monotonic()
        eventually(lambda: not mode().direct and not mode().joining, timeout=10.0,
                   what="node b back on PUB")
        took = time.monotonic() - removed
        back_at = run.state("camera")["sent"]
        link, viewer, follower = _settled(run, frames=frames)
    assert back_at < frames - 20, "the camera was done before node b went back to PUB"
    assert took < 3.0, f"node b back on PUB {took:.2f} s after the fast viewer went"
    assert max(viewer["ages"]) < 2.5, viewer["ages"]
    _every_frame_once_or_counted(link, viewer, follower, frames)
