"""The manager's web app (``create_app``) and its server (``serve``, with uvicorn).

Starlette was chosen for the app: small, pure Python, ASGI with websockets and a
test client, well kept; uvicorn (with the ``websockets`` package) serves it. The
page is plain files in ``static/`` (no build step, nothing from the internet).
Everything, the page included, is behind ``AccessMiddleware``.
"""

from __future__ import annotations

import contextlib
import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import uvicorn
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import FileResponse, HTMLResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket

from pb3a.manager.access import Access, AccessMiddleware
from pb3a.manager.api import routes
from pb3a.manager.live import REFRESH_S, Feed
from pb3a.manager.session import Session

STATIC = Path(__file__).resolve().parent / "static"
_NO_PAGE = """<!doctype html><meta charset="utf-8"><title>PB3A manager</title>
<p>The manager's page is missing from this installation (pb3a/manager/static/index.html);
the HTTP API at <code>/api/...</code> works without it.</p>"""


def create_app(session: Session, access: Access, refresh: float = REFRESH_S) -> Starlette:
    """The app serving ``session``: the page, the API and the websocket feed, all behind
    ``access``. Its lifespan runs the feed and closes the session at the end."""
    feed = Feed(session, refresh)

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        feed.start()
        try:
            yield
        finally:
            await feed.stop()
            session.close()
            await feed.settle()             # (calls the close has ended)

    async def index(request: Request) -> Response:
        page = STATIC / "index.html"
        if page.is_file():
            return FileResponse(page, headers={"cache-control": "no-store"})
        return HTMLResponse(_NO_PAGE)

    async def live(websocket: WebSocket) -> None:
        await feed.serve(websocket)

    async def unknown(request: Request) -> Response:
        return JSONResponse({"error": f"no API route {request.method} {request.url.path}; "
                             "see docs/manager.md for the routes", "problems": []},
                            status_code=404)

    app = Starlette(
        routes=[Route("/", index), *routes(session), WebSocketRoute("/api/live", live),
                Route("/api/{rest:path}", unknown,
                      methods=["GET", "POST", "PUT", "DELETE", "PATCH"]),
                Mount("/static", StaticFiles(directory=STATIC, check_dir=False),
                      name="static")],
        middleware=[Middleware(AccessMiddleware, access=access)],
        lifespan=lifespan)
    app.state.feed = feed
    app.state.session = session
    return app


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket at ``host:port`` (port 0: any free one); OSError if taken."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(128)
    except OSError:
        sock.close()
        raise
    return sock


def serve(app: Any, sock: socket.socket) -> None:
    """Serve ``app`` on ``sock`` until SIGINT or SIGTERM (uvicorn's own handling: the
    lifespan ends, so the session closes, then the signal is raised again)."""
    # log_config=None: uvicorn's records go to the root logger, in the format every PB3A
    # process writes (pb3a.log_format), not in a format of its own
    config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="on",
                            ws="auto", timeout_graceful_shutdown=5, log_config=None)
    try:
        uvicorn.Server(config).run(sockets=[sock])
    finally:
        sock.close()
