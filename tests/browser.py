"""A real headless browser for the manager's page tests: Debian's chromium driven by
Playwright for Python (its own browser download is not reachable from every machine,
so the tests use the system's, as ``executable_path``).

``chromium()`` starts the browser, once for a test file (its start, with Playwright's
own, is most of what opening a page costs), and closes it (all its processes) at the
end; ``chromium_page(browser)`` gives a page in a fresh context of that browser (a
profile of its own: no cookie, storage or cache of another test's), with every wait
bounded, and closes it when the test ends. ``skip_reason()`` says why the tests cannot
run here (no chromium, no playwright) so they skip with that reason.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "/usr/bin/chromium-browser")

# Flags for a headless Chromium in a sandboxed CI as root, on a machine with no network
# beyond loopback: no sandbox (root), no GPU, and none of the background connections
# (updates, sync, QUIC probes) that a closed network refuses, many at a time.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--disable-dev-shm-usage"]

LAUNCH_TIMEOUT_MS = 30_000      # starting the browser
ACTION_TIMEOUT_MS = 10_000      # one click, fill or wait for an element
VIEWPORT = {"width": 1440, "height": 860}


def chromium_path() -> str | None:
    """Debian's chromium (or ``PB3A_CHROMIUM``), None when there is none."""
    chosen = os.environ.get("PB3A_CHROMIUM")
    if chosen:
        return chosen if os.access(chosen, os.X_OK) else None
    for candidate in CHROMIUM_CANDIDATES:
        if os.access(candidate, os.X_OK):
            return candidate
    return shutil.which("chromium")


def skip_reason() -> str | None:
    """Why the browser tests cannot run here, or None when they can."""
    if importlib.util.find_spec("playwright") is None:
        return ("Playwright for Python is not installed: `pip install -e '.[test]'` "
                "(make test does it)")
    if chromium_path() is None:
        return ("no chromium: `apt-get install chromium` as root (make test does it), "
                "or point PB3A_CHROMIUM at a Chromium binary")
    return None


@dataclass
class Tab:
    """A Playwright page and the uncaught errors its scripts threw."""

    page: Any
    errors: list[str] = field(default_factory=list)


@contextlib.contextmanager
def chromium() -> Iterator[Any]:
    """A headless Chromium (Playwright's ``Browser``) to open pages in; closed, with all
    its processes, on the way out, also when a test failed."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=chromium_path(), headless=True, args=CHROMIUM_ARGS,
            timeout=LAUNCH_TIMEOUT_MS)
        try:
            yield browser
        finally:
            browser.close()


@contextlib.contextmanager
def chromium_page(browser: Any) -> Iterator[Tab]:
    """A Playwright page in a fresh context of ``browser`` (``chromium()``): nothing of
    another page's (cookies, storage, cache) is there; the context is closed on the way
    out, also when the test fails."""
    context = browser.new_context(viewport=VIEWPORT, device_scale_factor=1)
    try:
        context.set_default_timeout(ACTION_TIMEOUT_MS)
        tab = Tab(context.new_page())
        tab.page.on("pageerror", lambda error: tab.errors.append(str(error)))
        yield tab
    finally:
        context.close()
