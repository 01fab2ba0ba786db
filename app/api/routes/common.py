"""What every router needs: the context, the writer check, bounded body reading."""

from __future__ import annotations

from fastapi import Depends, Request
from fastapi.responses import PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.api.errors import ApiError
from app.api.schemas import MAX_ID
from app.workflow import AppContext

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


def operator_name(token_operator: str | None, body_operator: str | None) -> str | None:
    """The operator for the audit record: the token's wins over the body's."""
    if token_operator:
        return token_operator
    name = (body_operator or "").strip()
    return name or None


def attachment(text: str, filename: str) -> PlainTextResponse:
    """A text download (CCSDS messages) under ``filename`` (already reduced to safe characters)."""
    return PlainTextResponse(text, media_type="text/plain; charset=utf-8",
                             headers={"Content-Disposition": f'attachment; filename="{filename}"'})


def too_large(limit: int) -> ApiError:
    return ApiError(413, f"the upload is larger than the limit of {limit} bytes")


async def read_body_limited(request: Request, limit: int, reported_limit: int | None = None) -> bytes:
    """The request body, refusing (413) as soon as it exceeds ``limit`` bytes.

    A declared Content-Length above the limit is refused before anything is
    read; a chunked or lying body is cut off while it streams in.
    """
    declared = request.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > limit:
        raise too_large(reported_limit or limit)
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise too_large(reported_limit or limit)
        chunks.append(chunk)
    return b"".join(chunks)


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
