"""A slow link for tests: a TCP proxy on loopback that forwards at a set rate.

``Throttle(down_bps)`` listens for every address it is asked to ``route`` and forwards
each connection to it, each direction through one token bucket shared by all its
connections (as one radio link carries them all): ``down`` is from the address routed
to (a writer's node) to whoever connects (a reader's node), ``up`` the other way. Its
own socket buffers are small, so a sender feels the link's pace through TCP's
backpressure rather than the proxy taking in megabytes at loopback speed. It counts
the connections made to each address (a reconnection is one more) and, for each that
ended, which side ended it.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import socket
import threading
from typing import Any

CHUNK = 4096                   # bytes forwarded at a time
BUFFER = 64 * 1024             # the proxy's socket buffers (the kernel doubles them)
SLACK_S = 0.02                 # how late a chunk may come and still have its turn on time


class _Bucket:
    """A link of ``rate`` bytes per second: each chunk takes its time on it, in turn.
    A chunk that comes a little after the link is free (the proxy's own delay, a sleep
    that overran) takes its time from when the link was free, not from when it came:
    else every chunk lost that delay, and the link carried 10% less than its rate at
    5 Mbit/s (4.47 Mbit/s of a steady stream), 5% at 2. A link idle for longer
    gives no more than ``SLACK_S`` of its time back."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self._free_at = 0.0
        self._lock = asyncio.Lock()

    async def take(self, nbytes: int) -> None:
        async with self._lock:                   # (FIFO: the connections take turns)
            loop = asyncio.get_running_loop()
            start = max(self._free_at, loop.time() - SLACK_S)
            self._free_at = start + nbytes / self.rate
            await asyncio.sleep(self._free_at - loop.time())


class Throttle:
    """A rate-limited TCP proxy on 127.0.0.1, run on a thread of its own."""

    def __init__(self, down_bps: float, up_bps: float | None = None) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="throttle",
                                        daemon=True)
        self._thread.start()
        self._down = self._call(lambda: _Bucket(down_bps / 8))
        self._up = self._call(lambda: _Bucket((up_bps or down_bps) / 8))
        self._routes: dict[str, str] = {}
        self._servers: list[asyncio.AbstractServer] = []
        self.connections: collections.Counter[str] = collections.Counter()  # by address
        self.ended_by: collections.Counter[str] = collections.Counter()     # "reader", "writer"
        self.forwarded = 0                       # bytes, down
        self._open = self._call(asyncio.Event)   # cleared: the link carries nothing
        self._call(self._open.set)

    def set_rate(self, down_bps: float, up_bps: float | None = None) -> None:
        """Carry each direction at another rate from now on (a radio link that got better
        or worse)."""
        def change() -> None:
            self._down.rate, self._up.rate = down_bps / 8, (up_bps or down_bps) / 8
        self._call(change)

    def pause(self) -> None:
        """Carry nothing either way, connections kept (a radio link in a tunnel), until
        ``go_on``."""
        self._call(self._open.clear)

    def go_on(self) -> None:
        """Carry again what was held, and the rest, at the link's rate."""
        self._call(self._open.set)

    def _call(self, fn: Any) -> Any:
        async def run() -> Any:
            return fn()
        return asyncio.run_coroutine_threadsafe(run(), self._loop).result(10)

    def route(self, address: str) -> str:
        """The address (``tcp://127.0.0.1:PORT``) that reaches ``address`` through the link."""
        if address not in self._routes:
            host, port = address.removeprefix("tcp://").rsplit(":", 1)
            listener = socket.create_server(("127.0.0.1", 0))
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BUFFER)
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, BUFFER)

            async def start() -> None:
                server = await asyncio.start_server(
                    lambda r, w: self._serve(r, w, address, host, int(port)), sock=listener)
                self._servers.append(server)
            asyncio.run_coroutine_threadsafe(start(), self._loop).result(10)
            self._routes[address] = f"tcp://127.0.0.1:{listener.getsockname()[1]}"
        return self._routes[address]

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                     address: str, host: str, port: int) -> None:
        self.connections[address] += 1
        upstream = socket.socket()
        upstream.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BUFFER)
        upstream.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, BUFFER)
        upstream.setblocking(False)
        pumps: list[asyncio.Task[None]] = []
        far_writer = None
        try:
            await self._loop.sock_connect(upstream, (host, port))
            far_reader, far_writer = await asyncio.open_connection(sock=upstream)
            for stream in (writer, far_writer):
                stream.transport.set_write_buffer_limits(high=2 * CHUNK)
            pumps = [self._loop.create_task(self._pump(far_reader, writer, self._down, True)),
                     self._loop.create_task(self._pump(reader, far_writer, self._up, False))]
            done, _ = await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
            self.ended_by["writer" if pumps[0] in done else "reader"] += 1
        except OSError:
            pass                                 # (the address routed to is gone)
        except asyncio.CancelledError:
            pass       # closing: ends quietly (asyncio's server reports a cancelled one)
        finally:
            for task in pumps:
                task.cancel()
            await asyncio.gather(*pumps, return_exceptions=True)
            for stream in (writer, far_writer):
                if stream is not None:
                    # (waited for: a transport still closing as the loop closed was
                    # collected later, unclosed, "loop is closed")
                    stream.close()
                    with contextlib.suppress(OSError):
                        await stream.wait_closed()
            if far_writer is None:
                upstream.close()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                    bucket: _Bucket, down: bool) -> None:
        """Forward one direction until its sender ends (EOF, reset)."""
        with contextlib.suppress(OSError):
            while data := await reader.read(CHUNK):
                await self._open.wait()
                await bucket.take(len(data))
                writer.write(data)
                await writer.drain()
                if down:
                    self.forwarded += len(data)

    def close(self) -> None:
        """Cut every connection, stop listening and stop the thread."""
        async def stop() -> None:
            for server in self._servers:
                server.close()
            tasks = [task for task in asyncio.all_tasks() if task is not asyncio.current_task()]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            for server in self._servers:
                await server.wait_closed()
        asyncio.run_coroutine_threadsafe(stop(), self._loop).result(10)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)
        self._loop.close()

    def __enter__(self) -> Throttle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
