"""The manager's HTTP API: one route per operation, JSON in and out, errors that say
what to do.

Each route reads its request, then runs the session's blocking method in a worker
thread (``run_in_threadpool``: never on the event loop, so the websocket feed and
other requests go on meanwhile), each call to the system bounded by the session's
timeout. Errors become ``{"error": ..., "problems": [...]}`` with the status that
fits (see ``STATUS``); the session checks before it changes anything, so a refused
request changes nothing.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect, Request
from starlette.responses import JSONResponse, PlainTextResponse, Response
from starlette.routing import Route

from pb3a.errors import ConfigError, ModuleNotFound, RuntimeFailure, RuntimeTimeout
from pb3a.manager.document import ChangedOnDisk, Document, Stale, float_of_json
from pb3a.manager.session import Malformed, NotFound, Session, Unfit

log = logging.getLogger("pb3a.manager")

# exception -> status, most specific first
STATUS: list[tuple[type[BaseException], int]] = [
    (Malformed, 400), (ModuleNotFound, 404), (NotFound, 404), (Stale, 412), (Unfit, 422),
    (ConfigError, 409), (ChangedOnDisk, 409), (RuntimeTimeout, 504), (RuntimeFailure, 502),
]
FLAGS = {"1": True, "true": True, "0": False, "false": False}   # a query's yes or no
MOST_BODY_BYTES = 8_000_000          # a request body larger than this is refused
_LONGEST_NAME = 255                  # bytes in a file's name (Linux's NAME_MAX)


def encode(content: Any) -> str:
    """JSON text in ASCII, as the API answers and the live feed sends: a string that is
    not text (a lone surrogate, as a file name that is not UTF-8 decodes to) is
    escaped, and a float JSON has no word for is an error."""
    return json.dumps(content, allow_nan=False, separators=(",", ":"))


class JSONAnswer(JSONResponse):
    """An answer in ``encode``'s JSON. Starlette's UTF-8 could not encode a string that
    is not text, and answered a bare 500 after the change was made."""

    def render(self, content: Any) -> bytes:
        return encode(content).encode("ascii")


def error_response(exc: BaseException) -> JSONResponse:
    """The JSON error for ``exc``, with its status; an unexpected error is a 500 and logged."""
    for kind, status in STATUS:
        if isinstance(exc, kind):
            problems = list(getattr(exc, "problems", []) or [])
            message = "; ".join(problems) if problems else str(exc)
            return JSONAnswer({"error": message, "problems": problems}, status_code=status)
    log.exception("the manager failed on a request", exc_info=exc)
    return JSONAnswer({"error": f"the manager failed: {type(exc).__name__}: {exc}",
                       "problems": []}, status_code=500)


async def body_of(request: Request, *, optional: bool = False) -> Any:
    """The request's JSON body (``optional``: None when there is none); Malformed when
    it is too large (refused as it comes,
    not once it is all in memory), is not JSON, nests deeper than Python can read, or
    holds a string that is not Unicode text (a lone surrogate, which JSON allows:
    taken, it made every later answer that carried it fail). ``{"$float": "inf"}``
    ("-inf", "nan") is that float, which JSON cannot write."""
    too_large = Malformed(f"the request body has more than {MOST_BODY_BYTES} bytes")
    declared = request.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > MOST_BODY_BYTES:
        raise too_large
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > MOST_BODY_BYTES:
            raise too_large
        chunks.append(chunk)
    raw = b"".join(chunks)
    if not raw:
        if optional:
            return None
        raise Malformed("the request needs a JSON body")
    try:
        body = json.loads(raw, object_pairs_hook=float_of_json, parse_float=_float,
                          parse_constant=_NotJSON)
        json.dumps(body, ensure_ascii=False, default=repr).encode()
        found = _refused_in(body)
    except RecursionError:
        raise Malformed("the request body nests too deeply") from None
    except UnicodeEncodeError as exc:
        raise Malformed(f"the request body has a string that is not text: {exc}") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise Malformed(f"the request body is not JSON: {exc}") from None
    if found is not None:
        where, refused = found
        where = f"{where!r}: " if where else ""
        if isinstance(refused, _NotJSON):
            raise Malformed(f"the request body is not JSON: {where}{refused.text} is no JSON "
                            f"number; a float that is not finite is written "
                            f"{{\"$float\": \"{refused.word}\"}}")
        raise Unfit([f"{where}{refused.text} is a number no float holds (at most "
                     f"{sys.float_info.max:.4g}); an infinity is written "
                     f"{{\"$float\": \"inf\"}}"])
    return body


class _NotJSON:
    """NaN, Infinity or -Infinity in a body: Python's JSON reads them, JSON has none (they
    were set as floats, where the API says a float that is not finite travels as
    ``{"$float": "inf"}``)."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.word = {"NaN": "nan", "Infinity": "inf", "-Infinity": "-inf"}.get(text, text)


class _Beyond:
    """A JSON number no float holds (1e400, read as inf: it was set as an infinity)."""

    def __init__(self, text: str) -> None:
        self.text = text if len(text) <= 40 else f"{text[:20]}...{text[-8:]}"


def _float(text: str) -> float | _Beyond:
    number = float(text)
    return number if math.isfinite(number) else _Beyond(text)


def _refused_in(value: Any, path: str = "") -> tuple[str, _NotJSON | _Beyond] | None:
    """The first number of a body that is refused (``_NotJSON``, ``_Beyond``), with
    where it is (``kp``, ``cal.offset``, ``grid.0.1``); None if there is none."""
    if isinstance(value, (_NotJSON, _Beyond)):
        return path, value
    items = value.items() if isinstance(value, dict) else enumerate(value) \
        if isinstance(value, list) else ()
    for key, item in items:
        found = _refused_in(item, f"{path}.{key}" if path else str(key))
        if found is not None:
            return found
    return None


def routes(session: Session) -> list[Route]:
    """Every API route, bound to ``session``."""

    def answer(work: Callable[[Request], Awaitable[Any]], status: int = 200
               ) -> Callable[[Request], Awaitable[Response]]:
        async def endpoint(request: Request) -> Response:
            try:
                result = await work(request)
                if isinstance(result, Response):
                    return result
                # (encoded here: an answer JSON cannot say is an error of its own, not a
                # bare 500 after the change was made)
                return JSONAnswer(result, status_code=status)
            except ClientDisconnect:
                # gone before its body was in (a page closed or reloaded as it sent):
                # nothing was done, and there is no one to answer; no bug, no traceback
                log.info("manager: %s %s: the client went before its request was read "
                         "whole; nothing done", request.method, request.url.path)
                return Response(status_code=400)
            except Exception as exc:
                return error_response(exc)
        return endpoint

    def call(method: Callable[..., Any], *args: Any) -> Awaitable[Any]:
        return run_in_threadpool(method, *args)

    def name(request: Request) -> str:
        # (a route's pattern ends in "$", which also matches before a final newline:
        # DELETE /api/modules/probe%0A removed the module probe)
        if "\n" in request.scope["path"]:
            raise Malformed(f"no module name holds a line break: {request.scope['path']!r}")
        return request.path_params["name"]

    async def system(request: Request) -> Any:
        return await call(session.system)

    async def system_toml(request: Request) -> Any:
        return PlainTextResponse(await call(session.system_toml),
                                 media_type="application/toml; charset=utf-8")

    async def layout(request: Request) -> Any:
        return await call(session.layout)

    async def stats(request: Request) -> Any:
        return await call(session.stats)

    async def get_state(request: Request) -> Any:
        return await call(session.state, name(request), request.query_params.get("path", ""))

    async def set_state(request: Request) -> Any:
        values = await body_of(request)
        return await call(session.set_state, name(request), values)

    async def keep_offer(request: Request) -> Any:
        return await call(session.keep_offer, name(request))

    async def keep(request: Request) -> Any:
        body = await body_of(request, optional=True)
        return await call(session.keep, name(request), body)

    async def image(request: Request) -> Any:
        png = await call(session.image, name(request), request.query_params.get("path", ""))
        return Response(png, media_type="image/png", headers={"cache-control": "no-store"})

    async def migrate(request: Request) -> Any:
        body = await body_of(request)
        return await call(session.migrate, name(request),
                          body.get("to") if isinstance(body, dict) else None)

    async def swap(request: Request) -> Any:
        body = await body_of(request)
        return await call(session.swap, name(request),
                          body.get("class") if isinstance(body, dict) else None)

    async def swaps(request: Request) -> Any:
        return await call(session.swaps, name(request))

    async def add(request: Request) -> Any:
        return await call(session.add, await body_of(request))

    async def remove(request: Request) -> Any:
        force = request.query_params.get("force", "0")
        if force not in FLAGS:
            raise Malformed(f"'force' must be 1 or 0 (true or false), got {force!r}")
        return await call(session.remove, name(request), FLAGS[force])

    async def restart(request: Request) -> Any:
        return await call(session.restart, name(request))

    async def link(request: Request) -> Any:
        return await call(session.link, await body_of(request))

    async def reload(request: Request) -> Any:
        return await call(session.reload, await body_of(request))

    async def classes(request: Request) -> Any:
        return await call(session.classes)

    document = session.document

    async def get_document(request: Request) -> Any:
        return await call(document.to_json)

    async def put_document(request: Request) -> Any:
        body = await body_of(request)
        revision = body.get("revision") if isinstance(body, dict) else None
        if not isinstance(body, dict) or not isinstance(body.get("system"), dict) or not (
                revision is None or (isinstance(revision, int) and not isinstance(revision, bool))):
            raise Malformed("send {\"system\": {...the tables of the TOML as JSON...}, "
                            "\"revision\": the revision of the document it was made on}")
        try:
            await call(document.replace, body["system"], revision)
        except ValueError as exc:                # TOML cannot hold it: nothing changed
            raise Malformed(str(exc)) from None
        return await call(document.to_json)

    async def open_document(request: Request) -> Any:
        body = await body_of(request)
        if not isinstance(body, dict) or not isinstance(body.get("toml"), str) \
                or not isinstance(body.get("name", "opened.toml"), str):
            raise Malformed("send {\"name\": \"system.toml\", \"toml\": \"...the file's "
                            "text...\"}")
        name = Path(body.get("name") or "opened.toml").name or "opened.toml"
        if len(os.fsencode(name)) > _LONGEST_NAME:        # (no file may have it: a 500)
            raise Malformed(f"'name' must be a file name of at most {_LONGEST_NAME} bytes, "
                            f"got one of {len(os.fsencode(name))}")
        await call(document.open_text, body["toml"], name)
        return await call(document.to_json)

    async def check_link(request: Request) -> Any:
        body = await body_of(request)
        if not isinstance(body, dict) or not all(isinstance(body.get(k), str)
                                                 for k in ("src", "dst")):
            raise Malformed("send {\"src\": \"module.output\", \"dst\": \"module.input\"}")
        ok, message = await call(document.check_link, body["src"], body["dst"])
        return {"ok": ok, "message": message}

    async def toml(request: Request) -> Any:
        return PlainTextResponse(await call(document.toml),
                                 media_type="application/toml; charset=utf-8")

    async def save(request: Request) -> Any:
        body = await body_of(request, optional=True)
        body = {} if body is None else body
        if not isinstance(body, dict):
            raise Malformed(f"send {{\"path\"?: \"system.toml\", \"overwrite\"?: false}} or "
                            f"nothing, got {body!r}")
        path = body.get("path")
        if path is not None and not (isinstance(path, str) and path.strip()):
            raise Malformed(f"'path' must be a file name, got {path!r}")
        overwrite = body.get("overwrite", False)
        if not isinstance(overwrite, bool):
            raise Malformed(f"'overwrite' must be true or false, got {overwrite!r}")
        try:
            written = await call(_save, document, path, overwrite)
        except ValueError as exc:
            raise Malformed(str(exc)) from None
        return {"path": str(written)}

    async def launch(request: Request) -> Any:
        return await call(session.launch)

    async def stop(request: Request) -> Any:
        return await call(session.stop)

    return [
        Route("/api/system", answer(system)),
        Route("/api/system/toml", answer(system_toml)),
        Route("/api/layout", answer(layout)),
        Route("/api/stats", answer(stats)),
        Route("/api/classes", answer(classes)),
        Route("/api/modules", answer(add, 201), methods=["POST"]),
        Route("/api/modules/{name:path}/state", answer(get_state), methods=["GET"]),
        Route("/api/modules/{name:path}/state", answer(set_state), methods=["POST"]),
        Route("/api/modules/{name:path}/keep", answer(keep_offer), methods=["GET"]),
        Route("/api/modules/{name:path}/keep", answer(keep), methods=["POST"]),
        Route("/api/modules/{name:path}/image", answer(image)),
        Route("/api/modules/{name:path}/migrate", answer(migrate), methods=["POST"]),
        Route("/api/modules/{name:path}/swap", answer(swap), methods=["POST"]),
        Route("/api/modules/{name:path}/swaps", answer(swaps)),
        Route("/api/modules/{name:path}/restart", answer(restart), methods=["POST"]),
        Route("/api/modules/{name:path}", answer(remove), methods=["DELETE"]),
        Route("/api/links", answer(link), methods=["POST"]),
        Route("/api/reload", answer(reload), methods=["POST"]),
        Route("/api/document", answer(get_document), methods=["GET"]),
        Route("/api/document", answer(put_document), methods=["PUT"]),
        Route("/api/document/open", answer(open_document), methods=["POST"]),
        Route("/api/document/check-link", answer(check_link), methods=["POST"]),
        Route("/api/document/toml", answer(toml)),
        Route("/api/document/save", answer(save), methods=["POST"]),
        Route("/api/document/launch", answer(launch), methods=["POST"]),
        Route("/api/system/stop", answer(stop), methods=["POST"]),
    ]


def _save(document: Document, path: str | None, overwrite: bool) -> Any:
    try:
        return document.save(path, overwrite=overwrite)
    except OSError as exc:
        where = path if path is not None else document.path
        raise Malformed(f"cannot write {where}: {exc.strerror or exc}") from None
