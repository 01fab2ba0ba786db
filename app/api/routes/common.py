"""What every router needs: the context, the writer check, bounded body reading, bounded computing."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Callable

from fastapi import BackgroundTasks, Depends, Request
from fastapi.responses import PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.requests import ClientDisconnect

from app.api.errors import ApiError
from app.api.schemas import MAX_ID
from app.workflow import AppContext, queue
from app.workflow.compute import INTERACTIVE, WARM_UP_TIMEOUT_S, JobExpired, JobKilled
from app.workflow.documents import UploadDocument

#: An oversized body is read and thrown away up to this many bytes, so that a client that sends its
#: whole body before reading the answer (Python's urllib, our `upload` command) reads the 413
#: instead of "connection reset by peer"; beyond it the connection is closed (the client may then
#: see the reset, but nobody makes the server read gigabytes).  It bounds the draining of a refused
#: body only: an endpoint whose own limit is larger (frames, 128 MiB) reads bodies up to that limit.
DRAIN_LIMIT_BYTES = 64 * 1024 * 1024
#: How long a body may take to arrive, and how long an oversized one is drained, seconds.
BODY_READ_TIMEOUT_S = 60.0
DRAIN_TIMEOUT_S = 10.0
#: Part of the time-out kept for what follows the computation (storing the result), at most this
#: many seconds and this fraction of the time-out.
STORE_RESERVE_S = 1.0
STORE_RESERVE_FRACTION = 0.2
#: A job is not started later than this before the computation's deadline (same bounds): a search
#: takes tens of milliseconds and the largest extraction ~0.4 s, so one that starts in time ends in time.
START_MARGIN_S = 1.0
START_MARGIN_FRACTION = 0.2


@dataclass(frozen=True)
class Deadline:
    """When a request's computation must be done (``done_by``) and may still start (``start_by``), counted from
    ``since`` (its arrival); monotonic."""

    since: float
    done_by: float
    start_by: float

    def counted_from(self, moment: float) -> "Deadline":
        """The same deadlines counted from ``moment`` instead, if that is later (when the compute pool's kernels
        were ready, for a request that arrived before): every computation of the request gets the same shift."""
        shift = max(0.0, moment - self.since)
        return Deadline(since=self.since + shift, done_by=self.done_by + shift, start_by=self.start_by + shift)

#: Path parameters are database integers.
ID_LIMITS = {"ge": 1, "le": MAX_ID}

# auto_error=False: we answer missing tokens ourselves (401 only where tokens are required).
_bearer = HTTPBearer(auto_error=False, description="Needed for writes when the server is not on loopback")


def get_context(request: Request) -> AppContext:
    return request.app.state.context


def writer(credentials: HTTPAuthorizationCredentials | None = Depends(_bearer),
           ctx: AppContext = Depends(get_context)) -> str | None:
    """The operator of the request's bearer token, None when no token is needed or given.

    A token that is given must be valid even where none is required: a
    mistyped token should not silently fall back to an anonymous write.
    """
    challenge = {"WWW-Authenticate": "Bearer"}
    if credentials is None:
        if ctx.access.require_token:
            raise ApiError(401, "this server needs 'Authorization: Bearer <token>' for every write",
                           headers=challenge)
        return None
    operator = ctx.access.operator_of(credentials.credentials)
    if operator is None:
        raise ApiError(401, "the bearer token is not valid", headers=challenge)
    return operator


def query_utc(t: datetime | None, name: str) -> datetime | None:
    """A time from the query as UTC (a time without a zone is read as UTC, as everywhere in the archive).

    A time whose conversion leaves the calendar (``0001-01-01T00:00+00:01``)
    is refused at its parameter (found by the schema fuzz run).
    """
    if t is None:
        return None
    try:
        return t.replace(tzinfo=timezone.utc) if t.tzinfo is None or t.utcoffset() is None else t.astimezone(timezone.utc)
    except (OverflowError, ValueError):
        raise ApiError(422, f"invalid request: query.{name}: {t.isoformat()} is outside the years 1 to 9999 in UTC",
                       problems=[{"location": f"query.{name}", "message": "outside the years 1 to 9999 in UTC"}]) from None


def operator_name(token_operator: str | None, body_operator: str | None) -> str | None:
    """The operator for the audit record: the token's wins over the body's."""
    if token_operator:
        return token_operator
    name = (body_operator or "").strip()
    return name or None


def search_after_answer(background: BackgroundTasks, ctx: AppContext, doc: UploadDocument, asked: bool) -> None:
    """Queue the search an upload asked for (``search=true``), to run after the response: a new sequence,
    or one stored before and never searched (:func:`app.workflow.queue.wants_automatic_search`)."""
    if asked and queue.wants_automatic_search(doc):
        background.add_task(queue.search_new_upload, ctx, doc.id)


def attachment(text: str, filename: str) -> PlainTextResponse:
    """A text download (CCSDS messages) under ``filename`` (already reduced to safe characters)."""
    return PlainTextResponse(text, media_type="text/plain; charset=utf-8",
                             headers={"Content-Disposition": f'attachment; filename="{filename}"'})


def too_large(limit: int, close: bool = False, setting: str | None = None) -> ApiError:
    """The 413, stating the limit the body exceeded (and the setting that sets it, when there is one)."""
    where = f" ({setting})" if setting else ""
    return ApiError(413, f"the upload is larger than the limit of {limit} bytes{where}",
                    headers={"Connection": "close"} if close else None)


def _declared_length(request: Request) -> int | None:
    """The body size the client declared (Content-Length), None when it declared none."""
    declared = request.headers.get("content-length", "")
    return int(declared) if declared.isdigit() else None


async def read_body_limited(request: Request, limit: int, reported_limit: int | None = None,
                            setting: str | None = None) -> bytes:
    """The request body, refusing (413) once it exceeds ``limit`` bytes, keeping at most ``limit`` in memory.

    ``limit`` is the endpoint's own and the only size that decides: a body
    within it is read whatever its size.  The rest of an oversized body is
    read and discarded (until :data:`DRAIN_LIMIT_BYTES` have been read, for at
    most :data:`DRAIN_TIMEOUT_S`) before the 413 is sent: many clients write
    the whole body before they read anything, and a server that answers and
    closes early makes them fail with "connection reset by peer" instead of
    showing the 413.  A body declared larger than both ``limit`` and the
    drain limit is refused at once (draining it would mean reading it).  The
    413 states ``reported_limit`` (the limit the user sets, without room
    for multipart framing) and ``setting``, its name.  A body that takes
    longer than :data:`BODY_READ_TIMEOUT_S` to arrive is refused with 408.
    """
    reported = reported_limit or limit
    declared = _declared_length(request)
    if declared is not None and declared > max(limit, DRAIN_LIMIT_BYTES):
        raise too_large(reported, close=True, setting=setting)
    chunks, size = [], 0
    stream = request.stream()
    try:
        async with asyncio.timeout(BODY_READ_TIMEOUT_S):
            if not (declared is not None and declared > limit):
                async for chunk in stream:
                    size += len(chunk)
                    if size > limit:
                        break
                    chunks.append(chunk)
                else:
                    return b"".join(chunks)
    except TimeoutError:
        raise ApiError(408, f"the request body did not arrive within {BODY_READ_TIMEOUT_S:g} s",
                       headers={"Connection": "close"}) from None
    except ClientDisconnect:
        raise ApiError(400, "the client disconnected before the request body was complete",
                       headers={"Connection": "close"}) from None
    if size < DRAIN_LIMIT_BYTES:
        await _drain(stream, DRAIN_LIMIT_BYTES - size)
    # Closed after the answer: an oversized body may not have been read to its end.
    raise too_large(reported, close=True, setting=setting)


async def _drain(stream, budget: int) -> None:
    """Read and discard up to ``budget`` more bytes of a refused body, for at most DRAIN_TIMEOUT_S."""
    try:
        async with asyncio.timeout(DRAIN_TIMEOUT_S):
            async for chunk in stream:
                budget -= len(chunk)
                if budget < 0:
                    return
    except (TimeoutError, ClientDisconnect):
        return


def work_deadline(ctx: AppContext) -> Deadline:
    """The deadlines of a request's computation, so that it is answered within the time-out.

    The time-out users see is ``STARID_SEARCH_TIMEOUT_S`` from the moment the
    request's body is in; a little of it is kept for storing the result, and
    a job that has not started a little before its end is not started at all.
    """
    timeout, now = ctx.settings.search_timeout_s, time.monotonic()
    done_by = now + timeout - min(STORE_RESERVE_S, STORE_RESERVE_FRACTION * timeout)
    return Deadline(since=now, done_by=done_by,
                    start_by=done_by - min(START_MARGIN_S, START_MARGIN_FRACTION * timeout))


def busy(ctx: AppContext, what: str) -> ApiError:
    return ApiError(503, f"{what} was not done within the time-out of {ctx.settings.search_timeout_s:g} s "
                         "(STARID_SEARCH_TIMEOUT_S): the server is busy. Nothing was stored; try again.",
                    headers={"Retry-After": "1"})


async def wait_for_kernels(ctx: AppContext, what: str) -> None:
    """Wait until the compute pool's workers have their compiled kernels (at once once they have).

    Only the first seconds after a start wait (0.3 s; 20-25 s on the first
    start after an install, which compiles them); the rest of the server
    answers meanwhile.  503 only if they are not ready within
    :data:`app.workflow.compute.WARM_UP_TIMEOUT_S` (workers that cannot start).
    """
    ready = ctx.compute.kernels_ready
    if ready.done() and ready.exception() is None:
        return
    t0 = time.monotonic()
    try:
        # The pool's future is marked running: a cancelled wrapper (a client gone) cannot cancel it for others.
        await asyncio.wait_for(asyncio.wrap_future(ready), timeout=WARM_UP_TIMEOUT_S)
    except Exception:  # noqa: BLE001 - not ready in time, or a pool stopping: the same answer
        raise ApiError(503, f"{what} was not done: the server's compute workers are not ready (they load, on a "
                            f"first start compile, their kernels; waited {time.monotonic() - t0:.0f} s). Nothing "
                            "was stored; try again.", headers={"Retry-After": "10"}) from None


async def compute_within(ctx: AppContext, deadline: Deadline, what: str, fn: Callable, *args,
                         lane: str = INTERACTIVE):
    """``fn(*args)`` in the compute pool, or 503 (:func:`busy`) when it is not done by ``deadline.done_by``.

    A job still queued at ``deadline.start_by`` is never started (the pool
    drops it), so a burst of requests that time out does not leave the
    workers busy with answers nobody waits for.  The deadlines count from
    when the pool's kernels were ready (:func:`wait_for_kernels`), if that
    was after the request arrived: a request sent while a first start
    compiles them waits, it is not timed out.
    """
    await wait_for_kernels(ctx, what)
    deadline = deadline.counted_from(ctx.compute.ready_at)
    future = ctx.compute.submit_within(fn, *args, lane=lane, deadline=deadline.start_by)
    try:
        # wrap_future passes a cancellation on to the pool's future: a queued job is dropped.
        return await asyncio.wait_for(asyncio.wrap_future(future),
                                      timeout=max(0.0, deadline.done_by - time.monotonic()))
    except (asyncio.TimeoutError, JobExpired, JobKilled):
        raise busy(ctx, what) from None


def replay_request(request: Request, body: bytes) -> Request:
    """A Request over ``body`` already read, so starlette can parse a multipart form from memory."""
    sent = False

    async def receive() -> dict:
        nonlocal sent
        if sent:
            return {"type": "http.disconnect"}
        sent = True
        return {"type": "http.request", "body": body, "more_body": False}

    return Request(request.scope, receive)
