"""``SignalHead`` on its own: minimum green, yellow and all-red before a new green,
and legal lights whatever a controller asks, and when."""

from __future__ import annotations

import random

import pytest
from traffic_legality import illegal_steps

from agents.traffic.signals import SignalHead, SignalPlan

# netconvert's program for a crossing of two two-way streets (one lane each way)
CROSSING = [("GGgrrrGGgrrr", 42.0), ("yyyrrryyyrrr", 3.0),
            ("rrrGGgrrrGGg", 42.0), ("rrryyyrrryyy", 3.0)]


def test_the_plan_is_read_from_the_program() -> None:
    plan = SignalPlan.from_program(CROSSING)
    assert plan.greens == ("GGgrrrGGgrrr", "rrrGGgrrrGGg")
    assert (plan.yellow_s, plan.all_red_s) == (3.0, 0.0)
    with_red = SignalPlan.from_program([*CROSSING[:2], ("rrrrrrrrrrrr", 2.0), *CROSSING[2:]])
    assert with_red.all_red_s == 2.0
    assert plan.yellow(0, 1) == "yyyrrryyyrrr"
    with pytest.raises(ValueError, match="no green phase"):
        SignalPlan.from_program([("rrrr", 3.0), ("yyyy", 3.0)])


def test_a_new_green_comes_after_the_minimum_green_and_a_yellow() -> None:
    head = SignalHead(SignalPlan.from_program(CROSSING), min_green_s=5.0)
    head.request(1)                                   # at once: too soon
    states = [head.show(1.0) for _ in range(10)]
    assert states == ["GGgrrrGGgrrr"] * 5 + ["yyyrrryyyrrr"] * 3 + ["rrrGGgrrrGGg"] * 2
    assert (head.green, head.stage, head.elapsed) == (1, "green", 2.0)


def test_all_red_follows_yellow_when_the_program_has_it() -> None:
    plan = SignalPlan.from_program([*CROSSING[:2], ("rrrrrrrrrrrr", 2.0), *CROSSING[2:]])
    head = SignalHead(plan, min_green_s=1.0)
    head.request(1)
    states = [head.show(1.0) for _ in range(7)]
    assert states == (["GGgrrrGGgrrr"] + ["yyyrrryyyrrr"] * 3 + ["rrrrrrrrrrrr"] * 2
                      + ["rrrGGgrrrGGg"])


def test_a_transition_once_begun_finishes_whatever_is_asked_meanwhile() -> None:
    head = SignalHead(SignalPlan.from_program(CROSSING), min_green_s=2.0)
    head.request(1)
    head.show(1.0), head.show(1.0)
    assert head.show(1.0) == "yyyrrryyyrrr"
    head.request(0)                                   # changes its mind mid-yellow
    assert [head.show(1.0) for _ in range(4)] == ["yyyrrryyyrrr"] * 2 + ["rrrGGgrrrGGg"] * 2
    assert head.target == 1                           # then it goes back, legally
    assert [head.show(1.0) for _ in range(3)] == ["rrryyyrrryyy"] * 3


def test_requests_it_cannot_show_are_refused_by_name() -> None:
    head = SignalHead(SignalPlan.from_program(CROSSING), min_green_s=5.0)
    with pytest.raises(ValueError, match=r"no green phase 2: this junction has 2 \(0..1\)"):
        head.request(2)
    assert head.requested == 0


def test_the_legality_check_finds_each_fault() -> None:
    greens = ("GGgrrrGGgrrr", "rrrGGgrrrGGg")
    assert illegal_steps(["GGgrrrGGgrrr", "rrrGGgrrrGGg"], greens, 3) != []   # no yellow
    assert illegal_steps(["GGgrrrGGgrrr", "yyyrrryyyrrr", "rrrGGgrrrGGg"], greens, 3) != []
    assert illegal_steps(["GGgGGgrrrrrr"], greens, 3) != []                 # conflicting
    assert illegal_steps(["GGgrrrGGgrrr", *["yyyrrryyyrrr"] * 3, "rrrGGgrrrGGg"],
                         greens, 3) == []


@pytest.mark.parametrize("seed", range(5))
def test_any_sequence_of_requests_gives_legal_lights(seed: int) -> None:
    """Controllers swapped at random moments, each asking what it likes every second
    (also for the phase shown, also twice in a row), never make the lights illegal."""
    rng = random.Random(seed)
    plan = SignalPlan.from_program([*CROSSING[:2], ("rrrrrrrrrrrr", 1.0), *CROSSING[2:]])
    head = SignalHead(plan, min_green_s=rng.choice([0.0, 1.0, 5.0]))
    states = []
    for _ in range(400):
        if rng.random() < 0.4:
            head.request(rng.randrange(2))
        states.append(head.show(1.0))
    assert illegal_steps(states, plan.greens, yellow_s=3) == []
    assert len(set(states)) == 5                      # both greens, both yellows, all-red
