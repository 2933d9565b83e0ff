"""``python -m pb3a``: the same as the ``pb3a`` command."""

from __future__ import annotations

from pb3a.cli.main import main

raise SystemExit(main())
