"""Starting PB3A's own processes (workers, node executors) from any script."""

from __future__ import annotations

import threading
from multiprocessing import spawn as mp_spawn
from typing import Any

_start_lock = threading.Lock()


def start_without_main(process: Any) -> None:
    """Start a worker without re-running the user's ``__main__`` in it.

    multiprocessing re-imports the main script in every child, which breaks
    scripts without an ``if __name__ == "__main__"`` guard. Workers never need
    it: module classes travel with cloudpickle (by value when defined in main).
    """
    original = mp_spawn.get_preparation_data

    def preparation(name: str) -> dict[str, Any]:
        data = original(name)
        data.pop("init_main_from_path", None)
        data.pop("init_main_from_name", None)
        return data

    with _start_lock:
        mp_spawn.get_preparation_data = preparation
        try:
            process.start()
        finally:
            mp_spawn.get_preparation_data = original
