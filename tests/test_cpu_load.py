"""CPULoad holds CPUs at the level asked, as psutil reads it, and leaves nothing running."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import psutil
import pytest
from conftest import alive, eventually

from pb3a.cli.stress_options import parse_levels
from pb3a.cpu_load import CPULoad

pytestmark = pytest.mark.timeout(60)

TOLERANCE = 10.0       # percent: the machine is shared, and its other load comes and goes


@pytest.mark.serial     # alone: it loads a CPU and reads its load (the Makefile's test target)
def test_psutil_reads_the_level_asked_and_the_burners_end_with_the_block() -> None:
    cpu = max(os.sched_getaffinity(0))
    with CPULoad({cpu: 60.0}) as load:
        pids = load.pids
        time.sleep(2.0)                       # the controller settles (4 adjustments)
        psutil.cpu_percent(percpu=True)
        time.sleep(3.0)                       # (measuring a span of time, not waiting)
        reading = psutil.cpu_percent(percpu=True)[cpu]
        assert all(psutil.Process(pid).cpu_affinity() == [cpu] for pid in pids)
    assert abs(reading - 60.0) < TOLERANCE, reading
    assert not [pid for pid in pids if alive(pid)]


@pytest.mark.parametrize(("levels", "said"), [
    ({9999: 50.0}, "cannot load CPU 9999"), ({0: 150.0}, "give a percent from 0 to 100")])
def test_a_wrong_level_names_the_cpu(levels: dict[int, float], said: str) -> None:
    with pytest.raises(ValueError, match=said):
        CPULoad(levels)


def test_levels_parse_from_the_command_line_form() -> None:
    assert parse_levels("0,1:80") == {0: 80.0, 1: 80.0}
    for wrong in ("80", "a:80", "0:lots"):
        with pytest.raises(ValueError, match="is not CPUS:PERCENT"):
            parse_levels(wrong)


_KILLED_OWNER = textwrap.dedent("""
    import sys, time
    from multiprocessing import util
    from pb3a.cpu_load import CPULoad
    from pb3a.node import forkserver_owner

    with CPULoad({int(sys.argv[1]): 20.0}) as load:
        print(forkserver_owner.running(), *load.pids, flush=True)
        print(util.get_temp_dir(), flush=True)      # (where its forkserver's socket is)
        time.sleep(120)
""")


def test_burners_started_first_leave_nothing_behind_an_owner_killed_with_sigkill(
        tmp_path: Path) -> None:
    """The burners come from the forkserver the workers use. Started first, by a
    ``CPULoad``, it was multiprocessing's plain one: it ended with a killed owner, but
    left its socket in /tmp (and every worker started after it in that process came
    from a forkserver that did not watch its owner). It is PB3A's now, whoever starts
    it, and removes its socket as its owner dies."""
    script = tmp_path / "load.py"
    script.write_text(_KILLED_OWNER)
    cpu = max(os.sched_getaffinity(0))
    proc = subprocess.Popen([sys.executable, str(script), str(cpu)],
                            stdout=subprocess.PIPE, text=True)
    try:
        forkserver, *burners = map(int, proc.stdout.readline().split())
        sockets = Path(proc.stdout.readline().strip())
        assert burners and [entry for entry in sockets.iterdir() if entry.is_socket()]
        proc.kill()
        proc.wait(10)
        eventually(lambda: not any(alive(pid) for pid in (forkserver, *burners)),
                   what="the forkserver and the burners to end")
        eventually(lambda: not sockets.exists(), what=f"{sockets} removed")
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()
