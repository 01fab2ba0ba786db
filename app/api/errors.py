"""Every error the API returns is ``{"detail": "<a sentence a person understands>"}``.

422 responses add ``"problems": [{"location": ..., "message": ...}, ...]``
(telemetry validation and request validation alike), so a client can show
each problem next to the field or line it concerns.  Exception handlers here
turn FastAPI's own errors (request validation, unknown routes, wrong
methods) and any unexpected exception into that shape; an unexpected
exception is logged with its traceback and answered 500 without internals.
"""

from __future__ import annotations

import logging
import math

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.storage import StorageError, UnknownSequence, UnstorableValue
from app.telemetry.errors import TelemetryError
from app.workflow.errors import Busy, Conflict, Invalid, NotFound, TooLarge, WorkflowError

log = logging.getLogger(__name__)


#: HTTP status of each kind of workflow refusal.
STATUS_OF = {NotFound: 404, Conflict: 409, Invalid: 422, TooLarge: 413, Busy: 503}


class ApiError(Exception):
    """An expected failure of the HTTP layer itself (authentication, media type, body size), with its status."""

    def __init__(self, status_code: int, detail: str, problems: list[dict] | None = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status_code = status_code
        self.detail = detail
        self.problems = problems
        self.headers = headers


def error_body(detail: str, problems: list[dict] | None = None) -> dict:
    body: dict = {"detail": detail}
    if problems is not None:
        body["problems"] = problems
    return body


def _location(loc) -> str:
    """FastAPI's ("body", "manual_points", 0, "x") -> "body.manual_points[0].x"."""
    text = ""
    for part in loc:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += ("." if text else "") + str(part)
    return text or "request"


#: Range checks whose message would misdescribe a NaN or an infinity ("should be less than 360").
_RANGE_ERRORS = {"less_than", "less_than_equal", "greater_than", "greater_than_equal", "finite_number"}


def _not_finite(value) -> bool:
    """NaN or an infinity, as a number or as the text a query parameter carries."""
    if isinstance(value, float):
        return not math.isfinite(value)
    if isinstance(value, str):
        try:
            return not math.isfinite(float(value))
        except ValueError:
            return False
    return False


#: FastAPI's detail when a request body cannot be decoded at all.
BODY_NOT_PARSED = "There was an error parsing the body"


def validation_problems(errors) -> list[dict]:
    problems = []
    for error in errors:
        message = str(error.get("msg", "invalid value"))
        if error.get("type") == "value_error":
            message = message.removeprefix("Value error, ")  # pydantic's prefix for our own validators' words
        loc = tuple(error.get("loc", ()))
        if error.get("type") == "json_invalid":
            # FastAPI locates it at ("body", offset): the offset is a character of the text, not an item.
            at = f" at character {loc[-1]}" if loc and isinstance(loc[-1], int) else ""
            loc = tuple(part for part in loc if not isinstance(part, int))
            message = "the body is not valid JSON" + (f" ({error['ctx']['error']}{at})"
                                                       if error.get("ctx", {}).get("error") else at)
        elif error.get("type") == "int_parsing_size":
            message = "the number is too large for an integer"
        elif error.get("type") in _RANGE_ERRORS and _not_finite(error.get("input")):
            message = f"must be a finite number, got {error.get('input')}"
        problems.append({"location": _location(loc), "message": message})
    return problems


def summary_of(problems: list[dict]) -> str:
    if len(problems) == 1:
        return f"invalid request: {problems[0]['location']}: {problems[0]['message']}"
    return f"invalid request: {len(problems)} problems: " + "; ".join(
        f"{p['location']}: {p['message']}" for p in problems[:5]) + ("; ..." if len(problems) > 5 else "")


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def api_error(_: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse(error_body(exc.detail, exc.problems), status_code=exc.status_code,
                            headers=exc.headers)

    @app.exception_handler(WorkflowError)
    async def workflow_error(_: Request, exc: WorkflowError) -> JSONResponse:
        status = next((code for kind, code in STATUS_OF.items() if isinstance(exc, kind)), 400)
        return JSONResponse(error_body(exc.detail, exc.problems), status_code=status)

    @app.exception_handler(TelemetryError)
    async def telemetry_error(_: Request, exc: TelemetryError) -> JSONResponse:
        doc = exc.to_dict()
        return JSONResponse(error_body(doc["message"], doc["problems"]), status_code=422)

    @app.exception_handler(RequestValidationError)
    async def request_invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        problems = validation_problems(exc.errors())
        return JSONResponse(error_body(summary_of(problems), problems), status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        if exc.status_code == 400 and detail == BODY_NOT_PARSED:
            # FastAPI's words when the body cannot even be decoded (not UTF-8): a located 422 like any
            # other unreadable body.
            problems = [{"location": "body", "message": "the body is not valid JSON (it is not UTF-8 text)"}]
            return JSONResponse(error_body(summary_of(problems), problems), status_code=422)
        if exc.status_code == 404 and detail == "Not Found":
            detail = "no such endpoint; the API is described at /docs"
        elif exc.status_code == 405:
            detail = "this endpoint does not accept that method; see /docs"
        return JSONResponse(error_body(detail), status_code=exc.status_code,
                            headers=getattr(exc, "headers", None))

    @app.exception_handler(UnknownSequence)
    async def unknown_sequence(_: Request, exc: UnknownSequence) -> JSONResponse:
        return JSONResponse(error_body(str(exc)), status_code=404)

    @app.exception_handler(UnstorableValue)
    async def unstorable(_: Request, exc: UnstorableValue) -> JSONResponse:
        # The backstop for a value the backend cannot hold that no field check caught (request fields
        # refuse U+0000 themselves, with their location): the write was rolled back, nothing is stored.
        return JSONResponse(error_body(f"{exc}; nothing was stored",
                                       [{"location": "request", "message": str(exc)}]), status_code=422)

    @app.exception_handler(StorageError)
    async def storage_error(_: Request, exc: StorageError) -> JSONResponse:
        log.error("storage error: %s", exc)
        return JSONResponse(error_body(f"the archive is not available: {exc}"), status_code=503)

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unexpected error on %s %s", request.method, request.url.path)
        return JSONResponse(error_body("internal server error; the server log has the details"),
                            status_code=500)
