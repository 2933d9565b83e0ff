"""Authenticated frames: every control and replication message carries a tag made
with the cluster key, and is checked before any byte of it is interpreted.

A message is a kind and a list of parts. ``Sealer.seal`` puts a fixed header in
front (magic, version, kind, flags, epoch, sender, counter, send time) and a 16-byte
tag behind. A small message travels as one ZeroMQ frame (pyzmq costs microseconds
per frame); a large one as ``[header, *parts, tag]``, so that big parts go without a
copy. The tag is GMAC (AES-256-GCM over the header and the length-prefixed parts as
associated data): OpenSSL runs it at about 15-30 GB/s here, where HMAC-SHA256 would
cost over a millisecond per MiB. Each sender draws a random 16-byte id per
incarnation and signs with its own key, derived from the cluster key and that id
(HKDF), so its 96-bit counter nonces can never collide with another sender's.

A message may carry one more frame behind it, a payload sealed on its own
(``Payloads``, flag ``_ATTACHED``; wire version 2): a remote link's large value,
encrypted with AES-GCM at write time, straight from the writer's memory into the
buffer that is sent, so that one pass is both the copy value semantics need and the
authentication (a copy, then GMAC over it, took two: ~110 us per cold MiB against
~65 here), and decrypted straight into the reader's ring slot at the other end.
The message's tag does not cover that frame; its parts carry the payload's nonce
and tag, which it does cover, and the payload's associated data names what it is
(topic, incarnation, sequence number), so it cannot be moved to another message as
another value. Payload keys use an HKDF label of their own: never a message key.

``Opener.open`` refuses, counts and never decodes: wrong frame count or size, a
malformed header, an unknown version, a stale epoch, a first message from a sender
whose send time is outside the freshness window, a counter not above the last one
from that sender (replay), and any tag that does not verify. Only then does a caller
unpickle anything (or open the attached payload: ``Payloads.open_into``).
"""

from __future__ import annotations

import collections
import contextlib
import errno
import hashlib
import itertools
import os
import pwd
import secrets
import stat
import struct
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes
from cryptography.hazmat.primitives.ciphers.aead import AESGCM
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from pb3a.errors import PB3AError

if TYPE_CHECKING:
    from collections.abc import Sequence

KEY_ENV, KEY_FILE_ENV = "PB3A_KEY", "PB3A_KEY_FILE"
DEFAULT_KEY_FILE = Path("~/.pb3a/cluster.key")

_MAGIC = b"PB3A"
_VERSION = 2                     # 2: a message may carry a sealed payload (see above)
# magic, version, kind, flags, (reserved), part count, epoch, sender id, counter,
# send time (unix s)
_HEADER = struct.Struct("<4sBBBxHQ16sQd")
_PACKED = 0x01                   # flag: header, parts and tag travel as one frame
_ATTACHED = 0x02                 # flag: a sealed payload frame follows the message
_TAG = 16
_LEN = struct.Struct("<Q")
_PACK_MAX = 64 * 1024            # messages up to this size travel as one frame
MAX_BYTES = 256 * 1024 * 1024    # default bound on one message (all its frames)
MAX_FRAMES = 64
FRESH_S = 60.0                   # a message older (or newer) than this is refused
_SENDERS = 4096                  # senders remembered (their derived keys and counters)
# what link() says on a file system without hard links (FAT, some FUSE ones)
_NO_HARD_LINKS = {errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS}


class ClusterKeyError(PB3AError, ValueError):
    """The cluster key is missing, unreadable or too short."""


class ClusterKeyMissing(ClusterKeyError):
    """No cluster key is set and none is at ``~/.pb3a/cluster.key``, where it may not be
    created (a daemon's: a key nobody else has would refuse every launcher)."""


class Rejected(PB3AError):
    """A message failed authentication or validation; ``reason`` says which check."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class ClusterKey:
    """The shared secret of one PB3A cluster (at least 32 bytes of key material)."""

    secret: bytes

    @classmethod
    def load(cls, environ: dict[str, str] | None = None, home: Path | None = None,
             create: bool = True) -> ClusterKey:
        """From ``PB3A_KEY``, else the file named by ``PB3A_KEY_FILE``, else
        ``~/.pb3a/cluster.key``, which is created (mode 0600) on first use unless
        ``create`` is false (``ClusterKeyMissing``: a daemon serves other machines, which
        cannot have a key it made up). A key file another user could read or change is
        refused (``ClusterKeyError``)."""
        env = os.environ if environ is None else environ
        if env.get(KEY_ENV):
            return cls._checked(env[KEY_ENV].encode(), f"${KEY_ENV}")
        if env.get(KEY_FILE_ENV):
            return cls._read(Path(env[KEY_FILE_ENV]).expanduser(), f" named by ${KEY_FILE_ENV}")
        path = (home / ".pb3a" / "cluster.key") if home else DEFAULT_KEY_FILE.expanduser()
        if not path.exists():
            if not create:
                raise ClusterKeyMissing(
                    f"no cluster key: ${KEY_ENV} and ${KEY_FILE_ENV} are not set, and "
                    f"{path} does not exist; a daemon makes no key of its own, which no "
                    f"other machine would have: copy the cluster's key file here "
                    f"(`pb3a key new PATH` makes the first one), then set "
                    f"{KEY_FILE_ENV}=PATH or put it at {path} (mode 0600)")
            path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            with contextlib.suppress(FileExistsError):   # two processes starting at once
                cls.create(path)                         # agree on one key
        return cls._read(path)

    @classmethod
    def create(cls, path: Path) -> ClusterKey:
        """New key material written to ``path``, which must not exist yet
        (``FileExistsError``), as a file only its owner can read (mode 0600). The file
        is there whole or not at all: the key is written to a temporary file beside
        it, synced, then linked to ``path`` (made in place and written after, a process
        loading the key meanwhile read it empty: "the cluster key ... is 0 bytes"). A
        file system without hard links has it written in place, as it was."""
        material = secrets.token_hex(32).encode()
        fd, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)  # (0600)
        try:
            with os.fdopen(fd, "wb") as out:
                out.write(material + b"\n")
                out.flush()
                os.fsync(out.fileno())
            try:
                os.link(temporary, path)        # FileExistsError: another made it first
            except OSError as exc:
                if exc.errno not in _NO_HARD_LINKS:
                    raise
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
                with os.fdopen(fd, "wb") as out:
                    out.write(material + b"\n")
        finally:
            os.unlink(temporary)
        return cls._checked(material, str(path))

    @classmethod
    def _read(cls, path: Path, named: str = "") -> ClusterKey:
        """The key in the file at ``path``, which must belong to the user running this
        and be readable by nobody else (the key is the cluster's root of trust)."""
        try:
            with path.open("rb") as file:
                _check_private(path, os.fstat(file.fileno()))
                material = file.read().strip()
        except PermissionError:
            raise ClusterKeyError(f"cannot read the cluster key file {path}{named}: "
                                  f"{_why_not_readable(path)}") from None
        except OSError as exc:
            raise ClusterKeyError(f"cannot read the cluster key file {path}{named}: "
                                  f"{exc.strerror}") from None
        return cls._checked(material, str(path))

    @classmethod
    def from_material(cls, material: bytes | str, where: str = "the key given") -> ClusterKey:
        """The key of this key material (what ``PB3A_KEY`` or a key file holds)."""
        return cls._checked(material.encode() if isinstance(material, str) else material, where)

    @classmethod
    def _checked(cls, material: bytes, where: str) -> ClusterKey:
        if len(material) < 32:
            raise ClusterKeyError(f"the cluster key from {where} is {len(material)} bytes; "
                            "use at least 32 (e.g. `python -c 'import secrets; "
                            "print(secrets.token_hex(32))'`)")
        return cls(hashlib.sha256(b"pb3a cluster key\0" + material).digest())

    def derive(self, sender: bytes, payload: bool = False) -> bytes:
        """The signing key of one sender incarnation (HKDF-SHA256), or with ``payload``
        the key of its sealed payloads (another label: never the same key)."""
        label = b"pb3a payload\0" if payload else b"pb3a sender\0"
        return HKDF(hashes.SHA256(), 32, salt=None, info=label + sender).derive(self.secret)


def _check_private(path: Path, status: os.stat_result) -> None:
    """Refuse a key file that another user could read or change, or that belongs to
    another user (as ssh refuses such private keys): one sentence with the fix."""
    mode, me = stat.S_IMODE(status.st_mode), os.geteuid()
    if mode & 0o077:
        raise ClusterKeyError(f"the cluster key file {path} has mode {mode:04o}, so other "
                              f"users can read or change it; make it private with "
                              f"`chmod 600 {path}`")
    if status.st_uid != me:
        raise ClusterKeyError(f"the cluster key file {path} (mode {mode:04o}) belongs to "
                              f"{_user(status.st_uid)}, {_not_mine(path)}")


def _why_not_readable(path: Path) -> str:
    """Why the user running this may not read the key file at ``path``, and the fix: its
    owner and the ``chown`` to run (a key root made, the ``chown`` of the deployment
    forgotten, said only "Permission denied", and the file was copied again in vain)."""
    me = _user(os.geteuid())
    try:
        status = path.stat()
    except OSError:              # (a directory on its way is closed to this user)
        return (f"Permission denied: {me}, who runs this, may not open a directory on "
                f"its way; let {me} into that directory, or put the key elsewhere")
    mode = stat.S_IMODE(status.st_mode)
    if status.st_uid != os.geteuid():
        return (f"Permission denied: it belongs to {_user(status.st_uid)} (mode "
                f"{mode:04o}), {_not_mine(path)}")
    return (f"Permission denied: its mode {mode:04o} lets not even its owner read it; "
            f"make it readable by its owner only with `chmod 600 {path}`")


def _not_mine(path: Path) -> str:
    """The end of a sentence about a key file another user owns: who should, and how."""
    me = _user(os.geteuid())
    return f"not to {me} who runs this; give it to that user with `chown {me} {path}`"


def _user(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return f"uid {uid}"


def _flat(part: Any) -> Any:
    """A part as plain bytes, or a byte view of it (an array's raw memory)."""
    return part if type(part) is bytes else memoryview(part).cast("B")


def _prefixed(views: list[Any]) -> bytes:
    parts = []
    for view in views:
        parts += (_LEN.pack(len(view)), view)
    return b"".join(parts)


def _streamed_tag(raw: bytes, nonce: bytes, header: Any, views: list[Any]) -> bytes:
    """GMAC over the header and the length-prefixed parts, without joining them."""
    encryptor = Cipher(algorithms.AES(raw), modes.GCM(nonce)).encryptor()
    encryptor.authenticate_additional_data(header)
    for view in views:
        encryptor.authenticate_additional_data(_LEN.pack(len(view)))
        encryptor.authenticate_additional_data(view)
    encryptor.finalize()
    return encryptor.tag


def _nonce(counter: int) -> bytes:
    return counter.to_bytes(12, "little")


class Sealer:
    """Signs the messages of one sender (one socket: counters must arrive in order)."""

    def __init__(self, key: ClusterKey, epoch: int = 0) -> None:
        self.epoch = epoch
        self.sender = secrets.token_bytes(16)
        self._raw = key.derive(self.sender)
        self._key = AESGCM(self._raw)
        self._counter = 0

    def seal(self, kind: int, parts: Sequence[Any] = (), payload: Any = None) -> list[Any]:
        """The frames to send: ``[packed]`` or ``[header, *parts, tag]``, and then
        ``payload`` if given: a frame sealed on its own (``PayloadSealer``), which this
        tag does not cover (its parts must carry what checks it: its nonce and tag)."""
        self._counter += 1
        views = [_flat(part) for part in parts]
        packed = sum(map(len, views)) <= _PACK_MAX
        flags = (_PACKED if packed else 0) | (_ATTACHED if payload is not None else 0)
        header = _HEADER.pack(_MAGIC, _VERSION, kind, flags, len(parts),
                              self.epoch, self.sender, self._counter, time.time())
        nonce = _nonce(self._counter)
        if packed:
            signed = header + _prefixed(views)
            frames = [signed + self._key.encrypt(nonce, b"", signed)]
        else:
            frames = [header, *parts, _streamed_tag(self._raw, nonce, header, views)]
        if payload is not None:
            frames.append(payload)
        return frames


@dataclass(frozen=True)
class Message:
    """An authenticated message: who sent it, and its frames (not yet decoded)."""

    kind: int
    epoch: int
    sender: bytes
    counter: int
    frames: list[Any]
    payload: Any = None               # a sealed payload frame, not checked yet (see Payloads)


class Opener:
    """Checks messages from any number of senders; counts what it refuses by reason."""

    def __init__(self, key: ClusterKey, *, epoch: int = 0, max_bytes: int = MAX_BYTES,
                 max_frames: int = MAX_FRAMES, fresh_s: float = FRESH_S) -> None:
        self._key = key
        self.epoch = epoch                    # messages of older epochs are stale
        self.max_bytes = max_bytes
        self.max_frames = max_frames
        self.fresh_s = fresh_s
        self.rejected: collections.Counter[str] = collections.Counter()
        # sender id -> [raw key, AESGCM, last counter], least recently used first. A
        # sender evicted from this bounded table could replay within ``fresh_s``.
        self._senders: collections.OrderedDict[bytes, list[Any]] = collections.OrderedDict()

    def open(self, frames: Sequence[Any]) -> Message:
        """The authenticated message, or ``Rejected`` (counted) with the failed check."""
        try:
            return self._open(frames)
        except Rejected as exc:
            self.rejected[exc.reason] += 1
            raise

    def _open(self, frames: Sequence[Any]) -> Message:
        if not 1 <= len(frames) <= self.max_frames + 3:
            raise Rejected("frame count")
        views = [memoryview(_flat(frame)) for frame in frames]
        if sum(view.nbytes for view in views) > self.max_bytes:
            raise Rejected("too large")
        if views[0].nbytes < _HEADER.size:
            raise Rejected("malformed")
        magic, version, kind, flags, count, epoch, sender, counter, sent = _HEADER.unpack(
            views[0][:_HEADER.size])
        if magic != _MAGIC:
            raise Rejected("malformed")
        if version != _VERSION:
            raise Rejected("version")
        payload = None
        if flags & _ATTACHED:                 # (checked by its own tag: see Payloads)
            if len(views) < 2:
                raise Rejected("frame count")
            payload, views = frames[-1], views[:-1]
        packed = len(views) == 1
        if bool(flags & _PACKED) != packed:
            raise Rejected("malformed")
        if packed:                            # header + prefixed parts + tag in one frame
            if views[0].nbytes < _HEADER.size + _TAG:
                raise Rejected("malformed")
            header, tag = views[0][:_HEADER.size], views[0][-_TAG:]
        else:
            header, tag = views[0], views[-1]
            if header.nbytes != _HEADER.size or tag.nbytes != _TAG:
                raise Rejected("malformed")
        if count > self.max_frames or (not packed and count != len(views) - 2):
            raise Rejected("frame count")
        if epoch < self.epoch:
            raise Rejected("stale epoch")
        known = self._senders.get(sender)
        # Freshness is asked of a sender's first message (or its first after it was
        # forgotten): it keeps out a message recorded from a sender not known here.
        # Afterwards the sender's counters refuse any replay, and a message that waited
        # out the window in a slow link's queue (a lossless link a minute behind) is
        # its, in order, not a replay: refused, it was sent again, behind the rest.
        if known is None and not abs(time.time() - sent) <= self.fresh_s:
            raise Rejected("not fresh")
        if known is not None and counter <= known[2]:
            raise Rejected("replay")
        if known is None:
            raw = self._key.derive(sender)
            known = [raw, AESGCM(raw), 0]
        if packed:
            expected = known[1].encrypt(_nonce(counter), b"", views[0][:-_TAG])
        else:
            expected = _streamed_tag(known[0], _nonce(counter), header, views[1:-1])
        if not secrets.compare_digest(expected, bytes(tag)):
            raise Rejected("bad tag")
        parts = (_split(views[0][_HEADER.size:-_TAG], count) if packed
                 else list(frames[1:len(views) - 1]))
        known[2] = counter                    # only an authentic message moves the counter
        self._senders[sender] = known
        self._senders.move_to_end(sender)
        if len(self._senders) > _SENDERS:
            self._senders.popitem(last=False)
        return Message(kind, epoch, sender, counter, parts, payload)


def _split(body: memoryview, count: int) -> list[memoryview]:
    """The parts of a packed message (authentic, but checked all the same)."""
    parts, at = [], 0
    for _ in range(count):
        if at + _LEN.size > body.nbytes:
            raise Rejected("malformed")
        (size,) = _LEN.unpack_from(body, at)
        at += _LEN.size
        if size > body.nbytes - at:
            raise Rejected("malformed")
        parts.append(body[at:at + size])
        at += size
    if at != body.nbytes:
        raise Rejected("malformed")
    return parts


# -- sealed payloads -----------------------------------------------------------------
PAYLOAD_TAG = _TAG                    # bytes of tag at the end of a sealed payload frame


class Payloads:
    """Seals and opens the large payloads of remote links: AES-256-GCM, so that one
    pass over the bytes both copies them and authenticates them.

    A writer's large value is encrypted at write time straight from its memory into
    the buffer that goes on the wire (``seal``): that pass is the copy value semantics
    need (the writer may change its array right after) and the authentication at
    once, where a copy and then GMAC over the copy took two. The receiver decrypts
    straight into where the value lands (``open_into``: the reader's ring slot), so
    checking and landing are one pass too; what it wrote there before the tag failed
    must be discarded by the caller, never delivered.

    Keys: one per owner (a sender incarnation: 16 random bytes), derived from the
    cluster key with an HKDF label of its own (``pb3a payload``), so that no payload
    key is ever a message key and the payload counter (the nonce) cannot collide
    with a message counter; a new incarnation draws a new owner id, hence a new key,
    so nonces never repeat across restarts. The associated data (``bound``) names
    what the payload is (topic, incarnation, sequence number, its kind and meta): a
    payload moved into another message, as another value, fails its tag. The message
    that carries a payload authenticates its nonce and its tag; replay and ordering
    stay the message's business (and a re-sent value is dropped by sequence number).
    """

    def __init__(self, key: ClusterKey, owner: bytes | None = None) -> None:
        self._key = key
        self.owner = owner
        self._own = AESGCM(key.derive(owner, payload=True)) if owner is not None else None
        self._counter = itertools.count(1)    # (next() is atomic under the GIL)
        # owner -> AESGCM of the owners heard from, least recently used first
        self._owners: collections.OrderedDict[bytes, AESGCM] = collections.OrderedDict()

    def seal(self, data: Any, bound: bytes) -> tuple[int, Any]:
        """``(nonce counter, frame)``: ``data`` encrypted into a new buffer of
        ``len(data) + PAYLOAD_TAG`` bytes (ciphertext, then the tag)."""
        if self._own is None:
            raise ValueError("this Payloads has no owner id: it can only open")
        view = _flat(data)                     # (bytes too: a long text, a pickle)
        frame = np.empty(len(view) + _TAG, np.uint8)
        counter = next(self._counter)
        self._own.encrypt_into(_nonce(counter), view, bound, memoryview(frame))
        return counter, frame

    def open_into(self, owner: bytes, counter: int, bound: bytes, frame: Any,
                  out: Any) -> None:
        """Decrypt ``frame`` into ``out`` (``frame``'s size less the tag), or
        ``Rejected("bad payload tag")``: then ``out`` holds garbage."""
        aead = self._owners.get(owner)
        if aead is None:
            aead = AESGCM(self._key.derive(owner, payload=True))
            self._owners[owner] = aead
            if len(self._owners) > _SENDERS:
                self._owners.popitem(last=False)
        else:
            self._owners.move_to_end(owner)
        try:
            aead.decrypt_into(_nonce(counter), _flat(frame), bound, out)
        except (InvalidTag, ValueError):
            raise Rejected("bad payload tag") from None
