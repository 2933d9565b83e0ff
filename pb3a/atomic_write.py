"""``write_text_atomically``: a file replaced whole, or not at all.

The text is written beside the file's final name, flushed to the disk, then renamed
over it, so a reader, a crash or a full disk finds the old file or the new one,
never part of either (a save that failed half-way left a user's configuration cut
off and no longer TOML).
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from pathlib import Path


def write_text_atomically(path: str | Path, text: str, *, newline: str | None = None) -> None:
    """Write ``text`` (UTF-8, each "\\n" written as ``newline`` if given) to ``path``
    whole or not at all, keeping an existing file's permissions (a new one gets the
    process's usual ones). ``OSError`` if it cannot be written: the file as it was, and
    nothing left beside it."""
    target = Path(path)
    partial = target.with_name(f".{target.name}.{secrets.token_hex(4)}.partial")
    try:
        # (the umask's permissions)
        with partial.open("x", encoding="utf-8", newline=newline) as out:
            out.write(text)
            out.flush()
            os.fsync(out.fileno())
        with contextlib.suppress(FileNotFoundError):
            shutil.copymode(target, partial)
        os.replace(partial, target)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
