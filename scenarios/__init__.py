"""PB3A applications: each runnable as a script and with ``pb3a scenario NAME``."""

from __future__ import annotations

import tempfile
from pathlib import Path

from pb3a.cli.arguments import seed


def summary(doc: str | None) -> str:
    """A scenario's ``--help`` description: its docstring's first paragraph (its first
    line ended mid-sentence)."""
    return " ".join((doc or "").split("\n\n")[0].split())


SUMO_SEED_MAX = 2**31 - 1       # SUMO reads its --seed as a C int


def sumo_seed(text: str) -> int:
    """``--seed`` of a run on SUMO, which takes none above ``SUMO_SEED_MAX``: 2147483648
    passed, and the traffic scenario ended in libsumo's traceback ("Could not parse
    commandline options")."""
    return seed(text, SUMO_SEED_MAX)


def output_directory(text: str) -> Path:
    """The directory ``--out`` names, made if need be. ``ValueError`` saying what to fix
    when it is a file or cannot be written in: found before the run, not after it (an
    unwritable one failed once the run was over, its figures lost)."""
    out = Path(text)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {text}: it is a file; give a directory for the report")
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        raise ValueError(f"--out {text}: the report cannot be written there "
                         f"({exc.strerror or exc}); give a directory you can write in"
                         ) from None
    return out
