"""An ASGI guard on request body size: the multipart parser spools a whole upload to disk
before a route runs, so the upload cap must act on the raw byte stream, not in the route."""

from __future__ import annotations

import asyncio
import json
import time

from farm.config import API_V1
from schemas.common import ErrorCode
from services.deps import INVALID_TOKEN, NOT_AUTHENTICATED, tenant_of_token
from services.uploads import TOO_LARGE

#: multipart framing and form fields around the file
SLACK = 64 * 1024


class BodyLimit:
    """Refuse request bodies above `max_bytes` (+ framing slack) with 413: at once when the
    Content-Length says so, else as soon as the streamed body passes the cap."""

    def __init__(self, app, max_bytes: int):  # noqa: ANN001
        self.app = app
        self.limit = int(max_bytes) + SLACK

    async def __call__(self, scope, receive, send):  # noqa: ANN001
        if scope["type"] != "http" or scope.get("method") not in ("POST", "PUT", "PATCH"):
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        length = headers.get(b"content-length")
        if length is not None and length.isdigit() and int(length) > self.limit:
            return await _too_large(send, self.limit - SLACK)
        seen = 0
        started = False
        refused = False

        async def guarded_receive():
            nonlocal seen, refused
            if refused:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    # answer 413 now; the app sees a disconnect and whatever it then tries to
                    # send (a 400 for a broken body) is dropped
                    refused = True
                    if not started:
                        await _too_large(send, self.limit - SLACK)
                    return {"type": "http.disconnect"}
            return message

        async def tracking_send(message):
            nonlocal started
            if refused:
                return
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, guarded_receive, tracking_send)
        except Exception:
            if not refused:
                raise


async def _too_large(send, cap: int) -> None:  # noqa: ANN001
    body = json.dumps(
        {"detail": f"{TOO_LARGE} {cap} bytes: request body", "code": ErrorCode.UPLOAD_TOO_LARGE.value}
    ).encode()
    await send(
        {
            "type": "http.response.start",
            "status": 413,
            "headers": [(b"content-type", b"application/json"), (b"connection", b"close")],
        }
    )
    await send({"type": "http.response.body", "body": body})


class AuthFirst:
    """A request with a body (POST, PUT, PATCH) under the API is refused 401 from its
    `Authorization` header alone, before a byte of its body is read: an unauthenticated
    upload costs no disk, no parsing, and (with `Expect: 100-continue`) no transfer, since
    the server sends `100 Continue` only when the app first reads the body. The scheme is
    matched case-insensitively, as the routes' own check (`services.deps`) does."""

    def __init__(self, app, state):  # noqa: ANN001
        self.app = app
        self.state = state  # the FastAPI app's state: settings, token cache, loop reads

    async def __call__(self, scope, receive, send):  # noqa: ANN001
        if (scope["type"] != "http" or scope.get("method") not in ("POST", "PUT", "PATCH")
                or not scope["path"].startswith(API_V1 + "/")):  # fmt: skip
            return await self.app(scope, receive, send)
        auth = next((v for k, v in scope["headers"] if k == b"authorization"), b"")
        scheme, _, token = auth.decode("latin-1").partition(" ")
        detail = None
        if scheme.lower() != "bearer" or not token:
            detail = NOT_AUTHENTICATED
        elif await tenant_of_token(self.state, token) is None:
            detail = INVALID_TOKEN
        if detail is None:
            return await self.app(scope, receive, send)
        code = (ErrorCode.NOT_AUTHENTICATED if detail == NOT_AUTHENTICATED
                else ErrorCode.INVALID_TOKEN)  # fmt: skip
        body = json.dumps({"detail": detail, "code": code.value}).encode()
        await send({"type": "http.response.start", "status": 401, "headers": [
            (b"content-type", b"application/json"), (b"www-authenticate", b"Bearer"),
            (b"content-length", str(len(body)).encode()), (b"connection", b"close")]})  # fmt: skip
        await send({"type": "http.response.body", "body": body})
        return None


class ServerTiming:
    """`Server-Timing: app;dur=MS` on every response: the time from the app receiving the
    request to its response headers, so a load test can tell the API's own latency from the
    time a request waited in the client or in the kernel (benchmarks/load.py)."""

    def __init__(self, app):  # noqa: ANN001
        self.app = app

    async def __call__(self, scope, receive, send):  # noqa: ANN001
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()

        async def timed_send(message):
            if message["type"] == "http.response.start":
                ms = (time.perf_counter() - t0) * 1e3
                headers = list(message.get("headers") or [])
                headers.append((b"server-timing", f"app;dur={ms:.2f}".encode()))
                message = {**message, "headers": headers}
            await send(message)

        return await self.app(scope, receive, timed_send)


class CpuSlots:
    """At most `n` requests of this process at once inside (0: no limit), the rest waiting on
    the event loop: a route whose Python work (POST /jobs: the ledger, pydantic) runs in the
    thread pool holds the GIL, and 20 of them at once left the event loop one turn in 21 at the
    GIL, which every status read waited for. They wait holding no thread: waiting in the pool
    took a thread each, and a burst's 20 new threads stalled the loop (a thread's start waits
    until the new thread runs, which it does only when it gets the GIL)."""

    def __init__(self, n: int):
        self.n = n
        self._sem: asyncio.Semaphore | None = None  # made on the loop that first enters

    async def __aenter__(self) -> None:
        if self.n > 0:
            if self._sem is None:
                self._sem = asyncio.Semaphore(self.n)
            await self._sem.acquire()

    async def __aexit__(self, *exc: object) -> None:
        if self._sem is not None:
            self._sem.release()
