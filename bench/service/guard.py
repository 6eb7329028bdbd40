"""The service bounded by construction: request bodies limited per route before anything parses them, connections
limited and idle or slow ones closed, accept errors logged once per interval (numbers in bench/service/limits.py).

- BodyLimitMiddleware (ASGI): a Content-Length over the route's limit is refused with 413 before a byte of the body
  is read; a body without one (chunked) is counted as it arrives and refused when it passes the limit; a body that
  stops arriving for BODY_IDLE_TIMEOUT_S is 408. It sits inside AuthMiddleware, which reads only headers: a request
  without a valid token never has its body read.
- GuardedHttpProtocol (uvicorn's httptools protocol): a connection must send a complete request head within
  HEAD_TIMEOUT_S of connecting or of its last response (uvicorn itself never times out a connection that sends
  nothing), and beyond max_connections the oldest idle connections are closed for the newcomer: idle clients
  cannot lock the API out, and the process never runs out of descriptors for its own work.
"""

from __future__ import annotations

import asyncio
import json
import logging
import resource
import sys
import time
from typing import Any

from starlette.exceptions import HTTPException
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from bench.service.fresh import FreshCache
from bench.service.limits import (BODY_IDLE_TIMEOUT_S, FD_RESERVE, HEAD_TIMEOUT_S, KEEP_ALIVE_S, MAX_CONNECTIONS,
                                  READ_CACHE_ENTRIES, READ_CACHE_S, SWITCH_INTERVAL_S, body_limit)
from drivers.contract.ratelog import RateLimitedLog

log = logging.getLogger("drivebench.serve")


def api_answers() -> FreshCache[tuple[int, list, list[bytes]]]:
    """What ReadCache keeps: (status, headers, body chunks), only whole 200 answers."""
    return FreshCache(READ_CACHE_S, READ_CACHE_ENTRIES, keep=lambda answer: answer[0] == 200 and len(answer[2]) == 1)


async def _reply(send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


class BodyLimitMiddleware:
    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        limit = body_limit(scope["method"], scope["path"])
        declared = next((v for k, v in scope.get("headers", []) if k.lower() == b"content-length"), None)
        if declared is not None:
            try:
                length = int(declared)
            except ValueError:
                return await _reply(send, 400, f"request: Content-Length: not a number: {declared[:20]!r}")
            if length > limit:
                return await _reply(send, 413, f"request: (body): {length} bytes; "
                                               f"{scope['method']} {scope['path']} takes at most {limit}")
        received = 0
        complete = False

        async def bounded_receive():
            nonlocal received, complete
            if complete:                      # after the body: disconnect listeners wait as long as they like
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), BODY_IDLE_TIMEOUT_S)
            except asyncio.TimeoutError:
                raise HTTPException(408, f"request: (body): nothing received for {BODY_IDLE_TIMEOUT_S:g} s") from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                complete = not message.get("more_body", False)
                if received > limit:
                    raise HTTPException(413, f"request: (body): over {limit} bytes; "
                                             f"{scope['method']} {scope['path']} takes at most {limit}")
            else:
                complete = True
            return message

        return await self.app(scope, bounded_receive, send)


def _reader(scope) -> int | None:
    """Who asks: the token's id (a websocket event sent to that token raises the oldest answer it may get)."""
    principal = scope.get("state", {}).get("principal")
    return principal.token_id if principal is not None else None


def _no_cache(scope) -> bool:
    """Cache-Control: no-cache (or max-age=0): the client wants the state as of its request, not the previous one."""
    for name, value in scope.get("headers", []):
        if name.lower() == b"cache-control":
            directives = value.lower().replace(b" ", b"").split(b",")
            return b"no-cache" in directives or b"max-age=0" in directives
    return False


class ReadCache:
    """GET answers of the viewer-level JSON API (rigs, runs, leases, trend) from memory (bench.service.fresh): at most
    READ_CACHE_S old, read again in the background before then and at once after a change, and while a change is
    read the previous answer, except after a write through the API (seen by every read after it), to a token that
    was sent a websocket event of the change, and to a request with Cache-Control: no-cache. Fifty clients reading
    the same lists cost one database read, not fifty (1.5-1.8 ms of CPU each), and seldom wait for one: with a
    read on the request path, every expiry and every change made the fifty wait 20-130 ms while the event loop
    served the others (the p99 of benchmarks/service_abuse.py and benchmarks/service.py). It sits inside the auth
    middleware: only a valid token gets an answer, and the answers are the same for every role that may read them."""

    PREFIXES = ("/api/rigs", "/api/runs", "/api/leases", "/api/trend")

    def __init__(self, app, generation, changed, answers: FreshCache):
        self.app = app
        self.generation = generation          # () -> int; changes invalidate
        self.changed = changed                # () -> int, the new generation: an API write is a change
        self.answers = answers

    def _cacheable(self, scope) -> bool:
        path = scope["path"]
        return (scope["method"] == "GET" and path.startswith(self.PREFIXES) and "/files/" not in path
                and "/export/" not in path and not path.endswith("/lease"))

    async def _read(self, scope) -> tuple[int, list, list[bytes]]:
        """The route's answer, whole, without a client (the background reads have none)."""
        start: dict = {}
        chunks: list[bytes] = []

        async def receive():
            return {"type": "http.request", "body": b"", "more_body": False}

        async def capture(message):
            if message["type"] == "http.response.start":
                start.update(message)
            elif message["type"] == "http.response.body":
                chunks.append(message.get("body", b""))

        await self.app(dict(scope), receive, capture)
        return start.get("status", 500), list(start.get("headers", [])), chunks

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        if not self._cacheable(scope):
            try:
                return await self.app(scope, receive, send)
            finally:
                if scope["method"] not in ("GET", "HEAD", "OPTIONS"):
                    self.answers.show(self.changed())      # an API write is seen by every read after it
        key = scope["path"] + "?" + scope.get("query_string", b"").decode("latin-1")
        status, headers, chunks = await self.answers.get(key, self.generation(), lambda: self._read(scope),
                                                         _reader(scope), fresh=_no_cache(scope))
        await send({"type": "http.response.start", "status": status, "headers": headers})
        for i, chunk in enumerate(chunks):
            await send({"type": "http.response.body", "body": chunk, "more_body": i < len(chunks) - 1})
        if not chunks:
            await send({"type": "http.response.body", "body": b""})


class GuardedHttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol (its C parser and byte-joined response heads: 0.13-0.25 ms of the service's CPU
    per cached API answer against 0.26-0.43 with the pure-Python h11, same sitting), guarded."""

    max_connections = MAX_CONNECTIONS

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.born_s = time.monotonic()
        self._head_timer: asyncio.TimerHandle | None = None
        self._arm_head_timer()
        if len(self.connections) > self.max_connections:
            self._make_room()

    def _idle(self) -> bool:
        return self.cycle is None or self.cycle.response_complete

    def _arm_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
        self._head_timer = self.loop.call_later(HEAD_TIMEOUT_S, self._head_timeout)

    def _head_timeout(self) -> None:
        self._head_timer = None
        if self._idle() and not self.transport.is_closing():
            self.transport.close()

    def _make_room(self) -> None:
        """Close the oldest idle connections so that this one fits; if every one is busy, this one goes."""
        excess = len(self.connections) - self.max_connections
        idle = sorted((c for c in self.connections if c is not self and isinstance(c, GuardedHttpProtocol)
                       and c._idle() and not c.transport.is_closing()), key=lambda c: c.born_s)
        for conn in idle[:excess]:
            conn.transport.close()
        if len(idle) < excess:
            self.transport.close()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_head_timer()

    def handle_websocket_upgrade(self) -> None:
        if self._head_timer is not None:       # the websocket protocol owns the transport from here
            self._head_timer.cancel()
            self._head_timer = None
        super().handle_websocket_upgrade()

    def connection_lost(self, exc) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None
        super().connection_lost(exc)


def raise_fd_limit() -> int:
    """The soft descriptor limit up to the hard one (many distributions start services at 1,024); returns it."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = hard if hard != resource.RLIM_INFINITY else max(soft, 65536)
    if soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    return soft


def rate_limited_accept_errors(loop: asyncio.AbstractEventLoop) -> None:
    """asyncio logs a traceback per failed accept (EMFILE: out of descriptors), thousands a second under a connection
    flood: one line per interval with a count instead."""
    accept_log = RateLimitedLog(log, "accept failed")

    def handler(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        if "accept" in str(context.get("message", "")) and isinstance(context.get("exception"), OSError):
            accept_log.note(context["exception"])
        elif "_start_serving" in repr(context.get("handle")) and isinstance(context.get("exception"), ValueError):
            pass      # an accept paused by EMFILE resuming on the listener that shutdown closed: nothing to report
        else:
            loop.default_exception_handler(context)

    loop.set_exception_handler(handler)


ACCEPT_BATCH = 128    # listen backlog, which is also how many connections asyncio accepts in one go: less than
                      # FD_RESERVE, so the oldest idle connections are closed before descriptors run out


def run_server(app, host: str, port: int, ssl_keyfile: str | None, ssl_certfile: str | None) -> None:
    import uvicorn

    soft = raise_fd_limit()
    # the event loop, the request threads, the runner and each run's readers share one interpreter lock: a thread
    # that wants it waits up to the switch interval behind a busy one, several times per request (5 ms by default;
    # API p99 under benchmarks/service.py 88.9/61.3 -> 68.8/40.3 ms with 1 ms, back to back)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    GuardedHttpProtocol.max_connections = max(32, min(MAX_CONNECTIONS, soft - FD_RESERVE))
    uvicorn.run(app, host=host, port=port, log_level="warning", ssl_keyfile=ssl_keyfile, ssl_certfile=ssl_certfile,
                timeout_graceful_shutdown=5, http=GuardedHttpProtocol, timeout_keep_alive=KEEP_ALIVE_S,
                backlog=ACCEPT_BATCH)
