"""Authenticated frames: the cluster key, sealing, and everything the opener refuses."""

from __future__ import annotations

import errno
import os
import pwd
import random
import shutil
import stat
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np
import pytest
import zmq

from pb3a.transport import auth
from pb3a.transport.auth import ClusterKey, ClusterKeyError, Opener, Rejected, Sealer

KEY = ClusterKey.load({"PB3A_KEY": "k" * 40})


def _rejected(opener: Opener, frames: list, reason: str) -> None:
    before = opener.rejected[reason]
    with pytest.raises(Rejected) as caught:
        opener.open(frames)
    assert caught.value.reason == reason
    assert opener.rejected[reason] == before + 1


# -- the key ------------------------------------------------------------------------
def test_the_key_comes_from_the_environment_then_the_key_file_then_home(tmp_path) -> None:
    key_file = tmp_path / "cluster.key"
    key_file.write_text("f" * 64 + "\n")
    key_file.chmod(0o600)
    from_env = ClusterKey.load({"PB3A_KEY": "e" * 64, "PB3A_KEY_FILE": str(key_file)})
    from_file = ClusterKey.load({"PB3A_KEY_FILE": str(key_file)})
    assert from_env == ClusterKey.load({"PB3A_KEY": "e" * 64})
    assert from_file == ClusterKey.load({"PB3A_KEY": "f" * 64})     # newline stripped
    assert from_env != from_file


def test_a_missing_home_key_is_created_private_and_then_reused(tmp_path) -> None:
    first = ClusterKey.load({}, home=tmp_path)
    path = tmp_path / ".pb3a" / "cluster.key"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    assert ClusterKey.load({}, home=tmp_path) == first


def test_two_loaders_making_the_first_key_at_once_both_read_the_whole_key(
        tmp_path, monkeypatch) -> None:
    """The first made the key file, then wrote the key into it: the second, loading the
    key in between, read the file empty and failed ("the cluster key from ... is 0
    bytes": 68 times in 200 with two processes). Here the first waits before its write
    until the second has read the file, or is writing a key of its own."""
    home, fdopen, read = tmp_path, os.fdopen, ClusterKey._read
    writing, moved, writers, results = threading.Event(), threading.Event(), [], {}

    def held_write(fd: int, *args, **kwargs):
        if threading.current_thread().name in ("first", "second"):
            writers.append(threading.current_thread().name)
            if len(writers) == 1:
                writing.set()
                moved.wait(10)
            else:
                moved.set()
        return fdopen(fd, *args, **kwargs)

    def reading(cls, *args, **kwargs):
        try:
            return read(*args, **kwargs)
        finally:
            moved.set()

    def load(name: str) -> None:
        try:
            results[name] = ClusterKey.load({}, home=home)
        except Exception as exc:
            results[name] = exc

    monkeypatch.setattr(os, "fdopen", held_write)
    monkeypatch.setattr(ClusterKey, "_read", classmethod(reading))
    first = threading.Thread(target=load, args=("first",), name="first")
    second = threading.Thread(target=load, args=("second",), name="second")
    first.start()
    assert writing.wait(10)
    second.start()
    for thread in (first, second):
        thread.join(10)
        assert not thread.is_alive()
    assert isinstance(results["second"], ClusterKey), results["second"]
    assert results["first"] == results["second"]
    assert os.listdir(home / ".pb3a") == ["cluster.key"]        # no temporary file left
    assert stat.S_IMODE((home / ".pb3a" / "cluster.key").stat().st_mode) == 0o600


def test_a_key_file_made_where_hard_links_cannot_be_is_written_in_place(
        tmp_path, monkeypatch) -> None:
    """A file system without hard links (a FAT stick the key is carried on) has the
    key written straight into its file, as before the key was linked into place."""
    def no_link(source, destination) -> None:
        raise PermissionError(errno.EPERM, "Operation not permitted")
    monkeypatch.setattr(os, "link", no_link)
    made = ClusterKey.create(tmp_path / "cluster.key")
    assert ClusterKey.load({"PB3A_KEY_FILE": str(tmp_path / "cluster.key")}) == made
    assert os.listdir(tmp_path) == ["cluster.key"]
    with pytest.raises(FileExistsError):
        ClusterKey.create(tmp_path / "cluster.key")
    assert os.listdir(tmp_path) == ["cluster.key"]


def test_bad_keys_name_where_they_came_from(tmp_path) -> None:
    with pytest.raises(ClusterKeyError, match=r"\$PB3A_KEY is 5 bytes; use at least 32"):
        ClusterKey.load({"PB3A_KEY": "short"})
    missing = tmp_path / "nope.key"
    with pytest.raises(ClusterKeyError, match=f"cannot read the cluster key file {missing}"):
        ClusterKey.load({"PB3A_KEY_FILE": str(missing)})


def _key_file(tmp_path, mode: int):
    path = tmp_path / "cluster.key"
    path.write_text("s" * 64 + "\n")
    path.chmod(mode)
    return path


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660, 0o602, 0o620, 0o610, 0o601])
def test_a_key_file_others_can_read_or_change_is_refused_saying_how_to_fix_it(
        tmp_path, mode) -> None:
    path = _key_file(tmp_path, mode)
    with pytest.raises(ClusterKeyError) as refused:
        ClusterKey.load({"PB3A_KEY_FILE": str(path)})
    assert str(refused.value) == (
        f"the cluster key file {path} has mode {mode:04o}, so other users can read or "
        f"change it; make it private with `chmod 600 {path}`")


def test_the_home_key_file_is_refused_too_once_others_can_read_it(tmp_path) -> None:
    ClusterKey.load({}, home=tmp_path)
    path = tmp_path / ".pb3a" / "cluster.key"
    path.chmod(0o644)
    with pytest.raises(ClusterKeyError, match=f"chmod 600 {path}"):
        ClusterKey.load({}, home=tmp_path)


@pytest.mark.parametrize("mode", [0o600, 0o400])
def test_a_key_file_only_its_owner_can_read_is_accepted(tmp_path, mode) -> None:
    path = _key_file(tmp_path, mode)
    assert ClusterKey.load({"PB3A_KEY_FILE": str(path)}) == ClusterKey.from_material("s" * 64)


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a file to another user needs root")
def test_a_key_file_of_another_user_is_refused_naming_both_users(tmp_path) -> None:
    path = _key_file(tmp_path, 0o600)
    os.chown(path, 65534, -1)
    owner, me = pwd.getpwuid(65534).pw_name, pwd.getpwuid(os.geteuid()).pw_name
    with pytest.raises(ClusterKeyError) as refused:
        ClusterKey.load({"PB3A_KEY_FILE": str(path)})
    assert str(refused.value) == (
        f"the cluster key file {path} (mode 0600) belongs to {owner}, not to {me} who runs "
        f"this; give it to that user with `chown {me} {path}`")


@pytest.mark.skipif(os.geteuid() != 0 or not shutil.which("setpriv"),
                    reason="running as another user needs root and setpriv")
def test_a_key_file_its_user_may_not_read_says_whose_it_is_and_the_chown() -> None:
    """A key root made (the deployment's ``chown`` forgotten) said only "Permission
    denied" to the daemon's user, and the operator copied the key again where it was."""
    where = Path(tempfile.mkdtemp(prefix="pb3a-key-"))     # (not under a private tmp_path)
    try:
        where.chmod(0o755)
        path = _key_file(where, 0o600)                        # root's, as `sudo pb3a key new`
        nobody = pwd.getpwuid(65534).pw_name
        run = subprocess.run(
            ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable,
             "-c", "from pb3a.transport.auth import ClusterKey; ClusterKey.load()"],
            env={**{k: v for k, v in os.environ.items() if k != "PB3A_KEY"},
                 "PB3A_KEY_FILE": str(path), "HOME": str(where)},
            capture_output=True, text=True, timeout=60)
        assert run.returncode != 0
        assert run.stderr.strip().splitlines()[-1] == (
            f"pb3a.transport.auth.ClusterKeyError: cannot read the cluster key file {path} "
            f"named by $PB3A_KEY_FILE: Permission denied: it belongs to root (mode 0600), "
            f"not to {nobody} who runs this; give it to that user with "
            f"`chown {nobody} {path}`")
    finally:
        shutil.rmtree(where)


# -- sealing and opening ------------------------------------------------------------
def test_sealed_messages_open_with_their_frames_intact() -> None:
    sealer, opener = Sealer(KEY, epoch=3), Opener(KEY, epoch=3)
    array = np.arange(1 << 17, dtype=np.float64)               # 1 MiB: the streamed tag
    for frames in ([], [b"small"], [b"a", b"", b"c" * 70_000], [b"meta", array]):
        message = opener.open(sealer.seal(7, frames))
        assert message.kind == 7 and message.epoch == 3 and message.sender == sealer.sender
        assert [bytes(f) for f in message.frames] == [bytes(memoryview(f)) for f in frames]
    assert not opener.rejected


def test_zmq_frames_are_accepted_as_they_arrive() -> None:
    sealer, opener = Sealer(KEY), Opener(KEY)
    frames = [zmq.Frame(bytes(f)) for f in sealer.seal(1, [b"x" * 100_000, b"y"])]
    assert bytes(opener.open(frames).frames[1]) == b"y"


def test_another_key_a_flipped_bit_and_garbage_are_refused() -> None:
    opener = Opener(KEY)
    other = Sealer(ClusterKey.load({"PB3A_KEY": "o" * 40}))
    _rejected(opener, other.seal(1, [b"payload"]), "bad tag")
    sealer = Sealer(KEY)
    (packed,) = sealer.seal(1, [b"payload"])                # a small message: one frame
    for index in (0, 30, 60, len(packed) - 1):              # header, sender, part, tag
        frame = bytearray(packed)
        frame[index] ^= 0x01
        with pytest.raises(Rejected):
            opener.open([frame])
    split = sealer.seal(1, [b"x" * 100_000])                # a large one: header, part, tag
    assert len(split) == 3
    for index in range(3):
        frames = [bytearray(f) for f in split]
        frames[index][-1] ^= 0x01
        with pytest.raises(Rejected):
            opener.open(frames)
    _rejected(opener, [], "frame count")
    _rejected(opener, [b"garbage"], "malformed")
    _rejected(opener, [b"garbage", b"more", b"x" * 16], "malformed")


def test_replays_and_old_counters_are_refused() -> None:
    sealer, opener = Sealer(KEY), Opener(KEY)
    first, second = sealer.seal(1, [b"a"]), sealer.seal(1, [b"b"])
    opener.open(second)
    _rejected(opener, second, "replay")
    _rejected(opener, first, "replay")        # an older counter, though never seen
    opener.open(sealer.seal(1, [b"c"]))


def test_stale_epochs_and_stale_times_are_refused(monkeypatch) -> None:
    opener = Opener(KEY, epoch=5, fresh_s=10.0)
    _rejected(opener, Sealer(KEY, epoch=4).seal(1), "stale epoch")
    opener.open(Sealer(KEY, epoch=6).seal(1))
    old = Sealer(KEY, epoch=5).seal(1)
    now = auth.time.time()
    monkeypatch.setattr(auth.time, "time", lambda: now + 11.0)
    _rejected(opener, old, "not fresh")


def test_a_known_sender_s_message_that_waited_out_the_window_is_taken_in_order(
        monkeypatch) -> None:
    """Freshness is asked of a sender's first message only: its later ones are ordered
    by its counters, so one that spent longer than the window in a slow link's queue is
    taken (a lossless link a minute behind had each refused, and sent again behind the
    rest), while a replay of it is still refused."""
    sealer, opener = Sealer(KEY), Opener(KEY, fresh_s=10.0)
    opener.open(sealer.seal(1, [b"first"]))
    queued = [sealer.seal(1, [bytes([n])]) for n in range(3)]
    now = auth.time.time()
    monkeypatch.setattr(auth.time, "time", lambda: now + 60.0)
    assert [bytes(opener.open(message).frames[0]) for message in queued] == [b"\0", b"\1",
                                                                           b"\2"]
    _rejected(opener, queued[1], "replay")
    stranger = Sealer(KEY)
    monkeypatch.setattr(auth.time, "time", lambda: now)
    recorded = stranger.seal(1, [b"recorded"])
    monkeypatch.setattr(auth.time, "time", lambda: now + 60.0)
    _rejected(opener, recorded, "not fresh")      # a sender not known here: its first


def test_size_and_frame_count_are_bounded_before_anything_else() -> None:
    sealer, opener = Sealer(KEY), Opener(KEY, max_bytes=1000, max_frames=3)
    _rejected(opener, sealer.seal(1, [b"x" * 2000]), "too large")
    _rejected(opener, sealer.seal(1, [b"1", b"2", b"3", b"4"]), "frame count")
    opener.open(sealer.seal(1, [b"1", b"2", b"3"]))


def test_random_corruption_is_always_refused_cleanly() -> None:
    rng = random.Random(1234)
    sealer, opener = Sealer(KEY), Opener(KEY)
    for _ in range(2000):
        payload = b"payload" * (20 if rng.random() < 0.8 else 10_000)   # packed or split
        frames = [bytearray(f) for f in sealer.seal(rng.randrange(256), [payload, b"m"])]
        mutation = rng.randrange(4)
        if mutation == 0:                    # flip a random bit somewhere
            frame = rng.choice([f for f in frames if f])
            frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
        elif mutation == 1:                  # truncate a frame
            frame = rng.choice([f for f in frames if f])
            del frame[rng.randrange(len(frame)):]
        elif mutation == 2:                  # drop or duplicate a frame
            index = rng.randrange(len(frames))
            frames[index:index + 1] = [] if rng.random() < 0.5 else [frames[index]] * 2
        else:                                # replace everything with noise
            frames = [bytearray(rng.randbytes(rng.randrange(80))) for _ in range(3)]
        with pytest.raises(Rejected):
            opener.open(frames)
    assert sum(opener.rejected.values()) == 2000
    opener.open(sealer.seal(1, [b"still fine"]))
