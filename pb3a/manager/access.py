"""Who may use the manager: a one-time token, the right ``Host``, the right ``Origin``.

The manager changes a running system, so it is a control surface: every request
and websocket carries the token printed at start, as ``Authorization: Bearer TOKEN``
or as the cookie ``pb3a_token_PORT``, which ``GET /?token=TOKEN`` sets (HttpOnly,
SameSite=Strict) before redirecting to ``/``, so the token leaves the address bar
and the page's own requests carry it without script access. Cookies are not kept
apart by port: named by its port, one manager's does not overwrite another's on the
same host. A token in the query
of any other request is refused: it would end up in logs and histories.

The ``Host`` header must name the address served (DNS rebinding: a page of another
site whose name resolves to 127.0.0.1 sends its own host name), and a request's or
websocket's ``Origin``, when a browser sends one, must be that address too: a
websocket is not bound by the same-origin policy, and a page served from another
port of this host is the same *site*, so its form posts and no-cors fetches carry
the SameSite=Strict cookie.
"""

from __future__ import annotations

import hmac
import json
import secrets
from collections.abc import Awaitable, Callable, MutableMapping
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs

COOKIE = "pb3a_token"
TOKEN_BYTES = 32

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

_SIGN_IN_PAGE = b"""<!doctype html><meta charset="utf-8"><title>PB3A manager</title>
<p>This page needs the token <code>pb3a manager</code> printed when it started:
open the whole URL it printed (<code>http://HOST:PORT/?token=...</code>).</p>
"""


def new_token() -> str:
    """A fresh token: 32 random bytes, URL-safe base64."""
    return secrets.token_urlsafe(TOKEN_BYTES)


class Access:
    """The token and the host names the manager answers to."""

    def __init__(self, token: str, hosts: set[str] | None = None) -> None:
        self.token = token
        self.hosts: set[str] = {h.lower() for h in hosts or ()}   # Host header values allowed
        self.cookie = COOKIE

    def serve_at(self, host: str, port: int) -> None:
        """Answer to ``host:port``, and to localhost and 127.0.0.1 with that port (on
        port 80 also without it, as browsers send it); the cookie is the port's."""
        for name in {host.lower(), "localhost", "127.0.0.1"}:
            shown = f"[{name}]" if ":" in name else name
            self.hosts.add(f"{shown}:{port}")
            if port == 80:
                self.hosts.add(shown)
        self.cookie = f"{COOKIE}_{port}"

    def host_allowed(self, host: str | None) -> bool:
        return host is not None and host.lower() in self.hosts

    def origin_allowed(self, origin: str | None) -> bool:
        """No ``Origin`` (not a browser) or one of the served addresses over http."""
        if origin is None:
            return True
        scheme, _, host = origin.partition("://")
        return scheme == "http" and self.host_allowed(host)

    def is_token(self, candidate: str | None) -> bool:
        """Whether ``candidate`` is the token (compared in constant time)."""
        return candidate is not None and hmac.compare_digest(candidate.encode(),
                                                             self.token.encode())

    def authenticated(self, headers: dict[str, str]) -> bool:
        """Whether the request's ``Authorization`` header or cookie carries the token."""
        scheme, _, credential = headers.get("authorization", "").partition(" ")
        if scheme.lower() == "bearer" and self.is_token(credential.strip()):
            return True
        cookie = SimpleCookie()
        try:
            cookie.load(headers.get("cookie", ""))
        except Exception:                   # a malformed cookie header: no token in it
            return False
        return self.cookie in cookie and self.is_token(cookie[self.cookie].value)


class AccessMiddleware:
    """Refuses, before any route runs, a request with the wrong ``Host`` (403), a
    request or websocket with the wrong ``Origin`` (403), and one without the token (401);
    turns ``GET /?token=TOKEN`` into the cookie and a redirect to ``/``."""

    def __init__(self, app: ASGIApp, access: Access) -> None:
        self.app = app
        self.access = access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {key.decode("latin-1").lower(): value.decode("latin-1")
                   for key, value in scope["headers"]}
        path = scope["path"]
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        access = self.access
        if not access.host_allowed(headers.get("host")):
            await _refuse(scope, send, 403, f"this manager does not serve the host "
                          f"{headers.get('host')!r}: open the URL pb3a manager printed")
            return
        if not access.origin_allowed(headers.get("origin")):
            what = "websocket" if scope["type"] == "websocket" else "request"
            await _refuse(scope, send, 403, f"{what} from origin {headers.get('origin')!r} "
                          "refused: only the manager's own page may send it")
            return
        if "token" in query:
            if path == "/" and scope["type"] == "http" and access.is_token(query["token"][0]):
                await _sign_in(send, access.cookie, access.token)
                return
            await _refuse(scope, send, 401, "the token goes in the header 'Authorization: "
                          "Bearer TOKEN' (or the cookie the page sets), never in the URL of "
                          "a request other than the first page's")
            return
        if not access.authenticated(headers):
            await _refuse(scope, send, 401, "missing or wrong token: send 'Authorization: "
                          "Bearer TOKEN' with the token pb3a manager printed")
            return
        await self.app(scope, receive, send)


async def _sign_in(send: Send, name: str, token: str) -> None:
    """Set the cookie ``name`` and send the browser to ``/`` (so the token leaves its
    address bar)."""
    cookie = f"{name}={token}; HttpOnly; SameSite=Strict; Path=/"
    await send({"type": "http.response.start", "status": 303,
                "headers": [(b"location", b"/"), (b"set-cookie", cookie.encode()),
                            (b"cache-control", b"no-store"), (b"content-length", b"0")]})
    await send({"type": "http.response.body", "body": b""})


async def _refuse(scope: Scope, send: Send, status: int, message: str) -> None:
    """A JSON error for the API, a short page for the rest; a websocket is closed
    before it is accepted (the client sees the HTTP status 403)."""
    if scope["type"] == "websocket":
        await send({"type": "websocket.close", "code": 4000 + status, "reason": message[:120]})
        return
    if scope["path"].startswith("/api/"):
        body, kind = json.dumps({"error": message, "problems": []}).encode(), b"application/json"
    elif status == 401:
        body, kind = _SIGN_IN_PAGE, b"text/html; charset=utf-8"
    else:
        body, kind = message.encode(), b"text/plain; charset=utf-8"
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", kind), (b"content-length", str(len(body)).encode()),
                            (b"cache-control", b"no-store")]})
    await send({"type": "http.response.body", "body": body})
