"""``pb3a scenario NAME [ARGS]``: the bundled applications, found by entry point.

A scenario registers itself in the ``pb3a.scenarios`` entry-point group (``name =
package.module:main`` in its distribution's metadata); ``main(argv)`` takes the
scenario's own options and returns its exit code. Other packages can add theirs.
"""

from __future__ import annotations

import argparse
import sys
from importlib.metadata import EntryPoint, entry_points

GROUP = "pb3a.scenarios"


def scenarios() -> dict[str, EntryPoint]:
    """The scenarios installed, by name."""
    return {point.name: point for point in entry_points(group=GROUP)}


def scenario_command(args: argparse.Namespace) -> int:
    """Hand over to the scenario's own ``main``."""
    found = scenarios()
    point = found.get(args.name)
    if point is None:
        print(f"pb3a scenario: no scenario {args.name!r}; the scenarios: "
              f"{', '.join(sorted(found)) or '(none installed)'}", file=sys.stderr)
        return 2
    from pb3a.cli.status import sigterm_interrupts

    main = point.load()
    with sigterm_interrupts():          # (SIGTERM, or the terminal closing: as Ctrl-C)
        return int(main(args.args) or 0)
