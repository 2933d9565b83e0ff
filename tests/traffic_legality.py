"""What legal lights are, checked over a sequence of signal states, one per second:
the traffic tests of the signal head and of the driver share it."""

from __future__ import annotations

from collections.abc import Sequence

GREEN = "Gg"


def conflicting_greens(state: str, greens: Sequence[str]) -> bool:
    """True when the movements green in ``state`` are not all green together in one
    of the program's green phases (netconvert builds those free of conflicts)."""
    shown = {i for i, c in enumerate(state) if c in GREEN}
    return not any(shown <= {i for i, c in enumerate(g) if c in GREEN} for g in greens)


def illegal_steps(states: Sequence[str], greens: Sequence[str], yellow_s: int) -> list[str]:
    """Every fault in ``states`` (one per simulated second): conflicting greens, a
    green that turns red without yellow, a yellow shorter than ``yellow_s``."""
    faults = []
    for t, state in enumerate(states):
        if conflicting_greens(state, greens):
            faults.append(f"t={t}: conflicting greens {state}")
        if t == 0:
            continue
        for link, (before, now) in enumerate(zip(states[t - 1], state, strict=True)):
            if before in GREEN and now == "r":
                faults.append(f"t={t}: link {link} went from green to red without yellow")
            if before == "y" and now != "y":
                run = 0
                while t - 1 - run >= 0 and states[t - 1 - run][link] == "y":
                    run += 1
                if run < yellow_s:
                    faults.append(f"t={t}: link {link} was yellow for {run} s only")
            if before == "y" and now in GREEN:
                faults.append(f"t={t}: link {link} went from yellow back to green")
    return faults
