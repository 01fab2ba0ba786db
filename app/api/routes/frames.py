"""/api/frames: a pass of star-camera frames (FITS, PNG, JPEG, TIFF) uploaded as one sequence;
/api/sequences/{id}/frames: the previews kept of its frames, with their overlays."""

from __future__ import annotations

import asyncio
import math
import time
import unicodedata
from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, BackgroundTasks, Depends, Path, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from starlette.datastructures import UploadFile

from app.api.errors import ApiError
from app.api.routes.common import (ID_LIMITS, get_context, read_body_limited, replay_request, search_after_answer,
                                   wait_for_kernels, writer)
from app.api.schemas import SpacecraftName
from app.frames import FrameLimits
from app.timefmt import parse_utc_time
from app.workflow import AppContext, frames as framing
from app.workflow.compute import BULK
from app.workflow.documents import FramePreviewsDocument, UploadDocument
from app.workflow.errors import Busy

# No prefix: the uploads live under /api/frames, the previews under the sequence they belong to.
router = APIRouter(tags=["frames"])

#: Room for multipart boundaries and part headers on top of the frames' size limit.
MULTIPART_OVERHEAD = 256 * 1024
#: Extra wall-clock time beyond the frames' own budget (waiting for a worker, extraction).
FRAMES_GRACE_S = 20.0
#: Largest sidecar accepted.
MAX_SIDECAR_BYTES = 1024 * 1024

_UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "description": "The frames of one pass as `files` fields (FITS, PNG, JPEG or TIFF, 8 or 16 bit, TIFF "
                       "also 32-bit float; a multi-extension FITS holds a whole pass), an optional `sidecar` "
                       "(tubsat-frames/1 JSON: per-file times and the camera, docs/formats.md) and optional "
                       "text fields `sequence_id`, `spacecraft`, `fov_deg` (horizontal field of view, degrees, "
                       "known to +-5 %) and `time` (ISO 8601, UTC unless it says its zone: the time of a pass "
                       "of one frame, over the sidecar's and the file's own; frames with no time at all are "
                       "solved at an assumed time, J2000.0, and say so).",
        "content": {"multipart/form-data": {"schema": {
            "type": "object", "required": ["files"],
            "properties": {"files": {"type": "array", "items": {"type": "string", "format": "binary"}},
                           "sidecar": {"type": "string", "format": "binary"},
                           "sequence_id": {"type": "string"}, "spacecraft": {"type": "string"},
                           "fov_deg": {"type": "number"},
                           "time": {"type": "string", "format": "date-time"}}}}},
    },
    "responses": {"200": {"description": "The same frames (and sidecar and fields) were uploaded before: the "
                                         "stored sequence"},
                  "413": {"description": "Larger than the frames' size limit (STARID_FRAMES_MAX_BYTES, "
                                         "128 MiB by default)"},
                  "415": {"description": "Not multipart/form-data"},
                  "422": {"description": "Invalid images or sidecar, with located problems"},
                  "503": {"description": "Reading and detecting the frames did not finish within the time-out"}},
}


def _text_field(form, name: str, limit: int = 128) -> str | None:
    value = form.get(name)
    if value is None:
        return None
    if isinstance(value, UploadFile):
        raise ApiError(422, f"{name} must be a text field", problems=[{"location": f"body.{name}",
                                                                      "message": "must be text, not a file"}])
    value = value.strip()
    if len(value) > limit:
        raise ApiError(422, f"{name} is longer than {limit} characters",
                       problems=[{"location": f"body.{name}", "message": f"at most {limit} characters"}])
    # As in telemetry files: control characters break CSV and log lines, and PostgreSQL cannot store U+0000.
    if any(unicodedata.category(c) in ("Cc", "Cs") for c in value):
        raise ApiError(422, f"{name} contains control characters",
                       problems=[{"location": f"body.{name}",
                                  "message": "must not contain control characters or lone surrogates"}])
    return value or None


def _fov(form) -> float | None:
    text = _text_field(form, "fov_deg", 32)
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or not 0.1 <= value <= 120.0:
        raise ApiError(422, "fov_deg must be a number from 0.1 to 120 degrees",
                       problems=[{"location": "body.fov_deg", "message": f"must be 0.1 to 120 degrees, got {text!r}"}])
    return value


def _time(form) -> datetime | None:
    text = _text_field(form, "time", 64)
    if text is None:
        return None
    try:
        return parse_utc_time(text)
    except ValueError as exc:
        raise ApiError(422, f"time: {exc}", problems=[{"location": "body.time", "message": str(exc)}]) from None


@router.post("/api/frames", status_code=201, openapi_extra=_UPLOAD_BODY, response_model=UploadDocument,
             summary="Upload the frames of one pass (201 created, 200 if the same frames were stored)")
async def upload_frames(request: Request, background: BackgroundTasks,
                        search: bool = Query(False, description="true: search a new pass (bright pairs) right "
                                                                "after answering, as the console's work queue does"),
                        _operator: str | None = Depends(writer), ctx: AppContext = Depends(get_context)):
    limits = FrameLimits()
    media_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media_type != "multipart/form-data":
        raise ApiError(415, f"unsupported media type {media_type or 'none'!r}: send multipart/form-data with "
                            "the frames as 'files' fields")
    body = await read_body_limited(request, limits.max_bytes + MULTIPART_OVERHEAD, reported_limit=limits.max_bytes,
                                   setting="STARID_FRAMES_MAX_BYTES")
    form = await replay_request(request, body).form(max_files=limits.max_frames + 1, max_fields=10)
    try:
        uploads = form.getlist("files")
        if any(not isinstance(item, UploadFile) for item in uploads):
            raise ApiError(422, "files must be file fields",
                           problems=[{"location": "body.files", "message": "must be files, not text"}])
        if not uploads:
            raise ApiError(422, "no frames: send the images as 'files' fields",
                           problems=[{"location": "body.files", "message": "missing files"}])
        files = [(item.filename or f"frame-{i}", await item.read()) for i, item in enumerate(uploads)]
        sidecar = form.get("sidecar")
        sidecar_bytes = None
        if sidecar is not None:
            sidecar_bytes = await sidecar.read() if isinstance(sidecar, UploadFile) else sidecar.encode("utf-8")
            if len(sidecar_bytes) > MAX_SIDECAR_BYTES:
                raise ApiError(422, "the sidecar is larger than 1 MiB",
                               problems=[{"location": "body.sidecar", "message": "larger than 1 MiB"}])
        sequence_id, spacecraft, fov = _text_field(form, "sequence_id"), _text_field(form, "spacecraft"), _fov(form)
        caller_time = _time(form)
    finally:
        await form.close()
    prepared = await run_in_threadpool(framing.prepare_frames, ctx, files, sidecar_bytes, sequence_id, spacecraft, fov,
                                       caller_time)
    if isinstance(prepared, UploadDocument):  # the same frames were stored before
        search_after_answer(background, ctx, prepared, search)
        return JSONResponse(prepared.model_dump(mode="json"), status_code=200, background=background)
    await wait_for_kernels(ctx, "the frames' reading")  # the time-out counts from when the workers are ready
    deadline = limits.timeout_s + FRAMES_GRACE_S
    # The bulk lane: whole frames are heavy, and must never hold up the ordinary searches; a job still
    # queued when its answer is due is dropped, not started.
    future = ctx.compute.submit_within(framing.frames_job, prepared, lane=BULK,
                                       deadline=time.monotonic() + limits.timeout_s)
    try:
        result = await asyncio.wait_for(asyncio.wrap_future(future), timeout=deadline)
    except asyncio.TimeoutError:
        raise Busy(f"the frames were not read and detected within {deadline:.0f} s (the server is busy); "
                   "try again") from None
    doc = await run_in_threadpool(framing.store_frames, ctx, prepared, result)
    search_after_answer(background, ctx, doc, search)  # after the response, as for spot lists
    return JSONResponse(doc.model_dump(mode="json"), status_code=201 if doc.created else 200,
                        background=background)


@router.get("/api/frames/hot-pixels", response_model=framing.HotPixelMapDocument,
            summary="A spacecraft camera's hot-pixel map (current hot pixels and every version)")
def hot_pixels(spacecraft: Annotated[SpacecraftName, Query(description="the spacecraft name of its frames")],
               sensor: str = Query(..., pattern=r"^[0-9]{1,6}x[0-9]{1,6}$", description="WIDTHxHEIGHT, e.g. 752x582"),
               ctx: AppContext = Depends(get_context)):
    return framing.hot_pixel_map_document(ctx, spacecraft, sensor)


SeqId = Path(description="archive id of the sequence", **ID_LIMITS)
_PNG_RESPONSE = {200: {"content": {"image/png": {}}, "description": "The preview: 8-bit grey PNG"},
                 404: {"description": "No such sequence, or no frame image of that snapshot"}}


@router.get("/api/sequences/{seq_id}/frames", response_model=FramePreviewsDocument,
            summary="The frame previews of a sequence uploaded as frames, with detections, rejected blobs and "
                    "hot pixels (an empty list for spot lists)")
def frame_previews(seq_id: int = SeqId, ctx: AppContext = Depends(get_context)):
    return framing.frame_previews_document(ctx, seq_id)


@router.get("/api/sequences/{seq_id}/frames/{snapshot}.png", response_class=Response, responses=_PNG_RESPONSE,
            summary="One snapshot's frame preview (stretched to 8 bits, at most 1024 pixels wide)")
def frame_preview_png(seq_id: int = SeqId, snapshot: int = Path(ge=0, le=100_000, description="snapshot index"),
                      ctx: AppContext = Depends(get_context)):
    png = framing.frame_preview_png(ctx, seq_id, snapshot)
    return Response(png, media_type="image/png")


_ANNOTATED_RESPONSE = {200: {"content": {"image/png": {}},
                             "description": "The frame with the candidate's stars named, the constellation lines, "
                                            "the unmatched sources and an RA/Dec grid (colour PNG, docs/annotate.md)"},
                       404: {"description": "No such sequence, no frame image of that snapshot, no search yet, no "
                                            "candidate of that rank, or no attitude known at that snapshot"}}


@router.get("/api/sequences/{seq_id}/frames/{snapshot}/annotated.png", response_class=Response,
            responses=_ANNOTATED_RESPONSE,
            summary="One snapshot's frame annotated with a candidate of the latest search (as astrometry.net's)")
def annotated_frame_png(seq_id: int = SeqId, snapshot: int = Path(ge=0, le=100_000, description="snapshot index"),
                        rank: int = Query(1, **ID_LIMITS, description="the candidate's rank in the latest search"),
                        ctx: AppContext = Depends(get_context)):
    from app.workflow.annotate import annotated_frame_png as annotated

    png = annotated(ctx, seq_id, snapshot, rank)
    return Response(png, media_type="image/png",
                    headers={"Content-Disposition": f'inline; filename="sequence-{seq_id}-{snapshot}-rank-{rank}.png"'})
