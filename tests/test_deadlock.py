"""No deadlock between agents and the API, by design: agents reading, editing, swapping
and moving each other while the program does the same to them."""

from __future__ import annotations

import itertools
import time

import pytest
from sample_modules import Busybody, Locator

from pb3a import System

pytestmark = pytest.mark.timeout(120)

AGENTS = ("a0", "a1", "a2")


@pytest.mark.parametrize("workers", [0, 1], ids=["one-process-each", "packed"])
def test_agents_and_the_program_act_on_each_other_without_deadlock(workers: int) -> None:
    system = System("busy")
    for node in ("n1", "n2"):
        system.node(node, workers=workers)
    for name in AGENTS:
        system.add(name, Busybody, node="n1",
                   state={"peers": [p for p in AGENTS if p != name], "nodes": ["n1", "n2"]})
    program = 0
    deadline = time.monotonic() + 90
    with system.launch() as run:
        for i in itertools.count():
            agent = AGENTS[i % len(AGENTS)]
            match i % 5:
                case 0:
                    run.state(agent)
                case 1:
                    run.stats()
                case 2:
                    run.set_state(agent, poked=-i)
                case 3:
                    run.swap(agent, Busybody)
                case _:
                    run.migrate(agent, to="n2" if i % 2 else "n1")
            program += 1
            states = [run.state(name) for name in AGENTS]
            answered = sum(s["asked"] - s["refused"] for s in states)
            if (program >= 500 and answered >= 1000) or time.monotonic() > deadline:
                break
    # every request of the program was answered (else it raised); the agents' were too,
    # except those cut short because their agent had to be paused (to move or swap it):
    # never a time-out, never another error
    assert [s["unexpected"] for s in states] == ["", "", ""]
    assert program >= 500 and answered >= 1000, (program, answered)


def test_an_agent_may_ask_the_runtime_from_setup_as_the_system_starts() -> None:
    system = System("locating").node("a").node("b")
    system.add("src", Busybody, node="b", period=1.0, state={"peers": ["src"]})
    system.add("locator", Locator, node="a")
    with system.launch(timeout=10) as run:
        assert run.state("locator")["found"] == "b"
