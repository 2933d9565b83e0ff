"""``pb3a key new PATH``: make a cluster key file the way every command accepts it (new
random material, mode 0600, owned by the user who runs this), to copy to each host."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pb3a.transport.auth import KEY_FILE_ENV, ClusterKey


def key_new_command(args: argparse.Namespace) -> int:
    """``pb3a key new PATH``: a new key file, never over an existing one."""
    path = Path(args.path).expanduser()
    if not args.path.strip() or path.is_dir():
        print(f"pb3a key new: {args.path!r} is {'a directory' if args.path.strip() else 'empty'}"
              "; give the path of the key file to create, e.g. ~/.pb3a/cluster.key",
              file=sys.stderr)
        return 1
    try:
        ClusterKey.create(path)
    except FileExistsError:
        print(f"pb3a key new: {path} exists; a cluster's key is made once and copied to "
              "each host (remove the file first to replace the key on every host)",
              file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"pb3a key new: cannot create {path}: {exc.strerror}", file=sys.stderr)
        return 1
    print(f"wrote a new cluster key to {path} (mode 0600); copy it to each host, readable "
          f"only by the user who runs pb3a there, and set {KEY_FILE_ENV}={path.resolve()}")
    return 0
