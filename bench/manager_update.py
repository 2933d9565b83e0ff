"""The ModuleManager's cost of one live update for a system of 200 modules.

What is measured, on 200 small modules on one embedded node (packed into 4 worker
processes; chains of 10: a threaded ``Clock``, period 0.1 s, feeding 9 event-driven
``Gain`` modules; 180 links):

- ``stats_message_ms``: building one websocket ``stats`` message on the server
  (``live.stats_message``: ``run.stats()`` asked of every worker, the figures as JSON
  text), what the feed does every 0.5 s however many pages are open;
- ``get_stats_ms``: ``GET /api/stats`` through the app (Starlette's test client: the
  request, the token check, the thread pool, the JSON response);
- ``stats_bytes``: the size of one message;
- ``system_ms``, ``layout_ms``: the structure as JSON and its first Graphviz layout
  (sent at start and after each structural change, not at each update).

Each figure is the median (min, max) of ``REPEATS`` updates, one every 0.1 s. This is
the server's share; the page's (drawing one update of 200 modules in headless
Chromium) is measured by ``tests/test_manager_browser.py``
(``test_the_page_keeps_up_with_200_modules``); docs/manager.md gives both.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, main_guard, summary
from _modules import Clock, Gain

from pb3a import System
from pb3a.manager.access import Access, new_token
from pb3a.manager.app import create_app
from pb3a.manager.catalog import Catalog
from pb3a.manager.document import Document
from pb3a.manager.live import stats_message
from pb3a.manager.session import Session

MODULES = 200
CHAIN = 10
WORKERS = 4
REPEATS = 30
PAUSE_S = 0.1


def big_system() -> System:
    system = System("manager-bench", workers=WORKERS)
    for chain in range(MODULES // CHAIN):
        system.add(f"c{chain}-clock", Clock, period=0.1)
        for step in range(1, CHAIN):
            system.add(f"c{chain}-gain{step}", Gain)
            previous = "clock.out" if step == 1 else f"gain{step - 1}.y"
            system.link(f"c{chain}-{previous}", f"c{chain}-gain{step}.x")
    return system


def timed(work: Any) -> tuple[float, Any]:
    started = time.perf_counter()
    value = work()
    return (time.perf_counter() - started) * 1e3, value


def body(result: dict[str, Any]) -> None:
    from starlette.testclient import TestClient

    result.update(benchmark="manager_update", machine=machine(), modules=MODULES,
                  workers=WORKERS, repeats=REPEATS)
    with big_system().launch() as run:
        document = Document.empty()
        session = Session(document, run, catalog=Catalog(document, roots=[]))
        token = new_token()
        app = create_app(session, Access(token, {"testserver"}))
        with TestClient(app, headers={"Authorization": f"Bearer {token}"}) as client:
            time.sleep(1.0)                                # values flowing everywhere
            result["system_ms"] = round(timed(session.system)[0], 2)
            result["layout_ms"] = round(timed(session.layout)[0], 2)
            built, fetched, sizes = [], [], []
            for _ in range(REPEATS):
                cost, message = timed(lambda: stats_message(session))
                built.append(cost)
                sizes.append(len(message.text))
                cost, answer = timed(lambda: client.get("/api/stats"))
                if answer.status_code != 200:
                    raise RuntimeError(f"GET /api/stats: {answer.status_code} {answer.text}")
                fetched.append(cost)
                time.sleep(PAUSE_S)
    result["stats_message_ms"] = summary(built, 2)
    result["get_stats_ms"] = summary(fetched, 2)
    result["stats_bytes"] = summary(sizes, 0)
    result["share_of_refresh"] = round(result["stats_message_ms"]["median"] / 500.0, 3)


if __name__ == "__main__":
    main_guard(body, {})
