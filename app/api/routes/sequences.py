"""/api/sequences: upload, list, read, edit the pattern, search, candidates, confirm, AEM."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, BackgroundTasks, Body, Depends, Path, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, PlainTextResponse
from starlette.datastructures import UploadFile

from app.api.errors import ApiError
from app.api.routes.common import (ID_LIMITS, attachment, compute_within, get_context, operator_name,
                                   read_body_limited, replay_request, search_after_answer, too_large, work_deadline,
                                   writer)
from app.api.schemas import ConfirmRequest, PatternEdit, PatternReset, SearchRequest, ShortText
from app.frames import looks_like_image
from app.storage import SEQUENCE_ORDERS
from app.workflow import AppContext, archive, confirm as confirming, queue, search as searching
from app.workflow.documents import (AttitudeDocument, CandidateView, PatternDocument, SearchDocument, SequenceDetail,
                                    SequencePage, UploadDocument)

router = APIRouter(prefix="/api/sequences", tags=["sequences"])

#: Room for multipart boundaries and part headers on top of the file size limit.
MULTIPART_OVERHEAD = 64 * 1024
#: Raw-body media types read as telemetry (JSON or CSV; the content decides which).
RAW_TYPES = ("application/json", "text/csv", "text/plain", "application/octet-stream")

SeqId = Path(description="archive id of the sequence", **ID_LIMITS)
_UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "description": "A telemetry file (tubsat-snapshots/1, JSON or CSV): as a multipart `file` field "
                       "or as the raw body.",
        "content": {
            "multipart/form-data": {"schema": {"type": "object", "required": ["file"],
                                               "properties": {"file": {"type": "string", "format": "binary"}}}},
            "application/json": {"schema": {"type": "object"}},
            "text/csv": {"schema": {"type": "string"}},
            "text/plain": {"schema": {"type": "string"}},
        },
    },
    "responses": {"200": {"description": "The same content was uploaded before: the stored sequence"},
                  "413": {"description": "Larger than the upload limit"},
                  "422": {"description": "Invalid telemetry, with located problems"},
                  "503": {"description": "Not processed within the time-out (STARID_SEARCH_TIMEOUT_S); nothing "
                                         "was stored, try again"}},
}


async def _upload_bytes(request: Request, limit: int) -> tuple[bytes, str | None]:
    """The telemetry bytes and the client's file name from a multipart or raw body."""
    media_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media_type == "multipart/form-data":
        # The envelope may add a little; the message names the file's own limit.
        body = await read_body_limited(request, limit + MULTIPART_OVERHEAD, reported_limit=limit)
        form = await replay_request(request, body).form(max_files=1, max_fields=10)
        files = [v for v in form.values() if isinstance(v, UploadFile)]
        if not files:
            raise ApiError(422, "the multipart upload has no file; send the telemetry as the 'file' field",
                           problems=[{"location": "body.file", "message": "missing file"}])
        data = await files[0].read()
        if len(data) > limit:
            raise too_large(limit)
        return data, files[0].filename
    if media_type and media_type not in RAW_TYPES:
        raise ApiError(415, f"unsupported media type {media_type!r}: send multipart/form-data with a 'file' "
                            f"field, or the file itself as application/json, text/csv or text/plain")
    data = await read_body_limited(request, limit)
    if not data and not media_type:  # not an empty file: no file at all
        raise ApiError(422, "the request has no body: send the telemetry as the multipart 'file' field, or the file "
                            "itself as the body (application/json, text/csv or text/plain)",
                       problems=[{"location": "body", "message": "no body"}])
    return data, None


def _refuse_an_image(data: bytes, name: str | None) -> None:
    """An image sent as telemetry is said to be one, with where images go (its bytes read as text said only
    'not valid UTF-8 text: byte 0x89 at offset 0')."""
    if looks_like_image("", data[:16]):
        where = f"{name}: " if name else ""
        raise ApiError(422, f"{where}an image (FITS, PNG, JPEG or TIFF), not telemetry: send images to "
                            "POST /api/frames, which finds the stars in them",
                       problems=[{"location": "body.file", "message": "an image, not telemetry: send it to "
                                                                       "POST /api/frames"}])


@router.post("", status_code=201, openapi_extra=_UPLOAD_BODY, response_model=UploadDocument,
             summary="Upload a telemetry file (201 created, 200 if the same content exists)")
async def upload(request: Request, background: BackgroundTasks,
                 filename: str | None = Query(None, max_length=255,
                                              description="name of the file, for a raw body (a label only)"),
                 search: bool = Query(False, description="true: search a new upload (bright pairs) right after "
                                                         "answering, as the console's work queue does"),
                 _operator: str | None = Depends(writer), ctx: AppContext = Depends(get_context)):
    data, form_name = await _upload_bytes(request, ctx.settings.max_upload_bytes)
    deadline = work_deadline(ctx)  # the time-out runs from here, as a search's does
    name, lane = archive.clean_filename(form_name or filename), archive.parse_lane(data)
    _refuse_an_image(data, name)
    if lane is None:
        upload = await run_in_threadpool(archive.parse_upload, ctx, data, name)
    else:  # a large file is validated in a worker: its parsing holds none of the server's threads
        sequence, defaulted = await compute_within(ctx, deadline, "the upload's parsing", archive.telemetry_job, data,
                                                   name, ctx.settings.default_camera, ctx.settings.max_upload_bytes,
                                                   lane=lane)
        upload = await run_in_threadpool(archive.parsed_upload, ctx, data, name, sequence, defaulted)
    stored = await run_in_threadpool(archive.stored_upload, ctx, upload)
    if stored is not None:
        search_after_answer(background, ctx, stored, search)
        return JSONResponse(stored.model_dump(mode="json"), status_code=200, background=background)
    # Extraction is CPU-bound: in the compute pool, large files on their own lane.  Nothing is stored
    # before it is done, so an upload that times out leaves nothing behind.
    extraction = await compute_within(ctx, deadline, "the upload's extraction", archive.extraction_job,
                                      upload.sequence, upload.known_hot, lane=archive.extraction_lane(upload.sequence))
    doc = await run_in_threadpool(archive.store_upload, ctx, upload, extraction)
    search_after_answer(background, ctx, doc, search)  # after the response: the queue shows "new" meanwhile
    return JSONResponse(doc.model_dump(mode="json"), status_code=201 if doc.created else 200,
                        background=background)


@router.get("", response_model=SequencePage,
            summary="A page of sequences (newest first, or as the work queue: ambiguous and no match first)")
def list_sequences(offset: int = Query(0, ge=0, le=2**62), limit: int = Query(50, ge=1, le=1000),
                   spacecraft: Annotated[ShortText | None, Query()] = None,
                   status: Literal["new", "identified", "ambiguous", "no_match", "confirmed", "rejected"] | None = None,
                   search: Annotated[ShortText | None, Query(description="part of the sequence id or file name, "
                                                                         "or the archive id")] = None,
                   order: Literal[tuple(SEQUENCE_ORDERS)] = Query(  # type: ignore[valid-type]
                       "newest", description="newest | oldest | queue (what needs an operator first) | time "
                                             "(snapshot time, newest first) | time_asc | spacecraft"),
                   ctx: AppContext = Depends(get_context)):
    return queue.list_sequences(ctx, offset, limit, spacecraft=spacecraft, status=status, search=search,
                                order=order)


@router.get("/{seq_id}", response_model=SequenceDetail,
            summary="A sequence: telemetry, extraction, current pattern, latest search, confirmation")
def get_sequence(seq_id: int = SeqId, ctx: AppContext = Depends(get_context)):
    return archive.sequence_detail(ctx, seq_id)


@router.put("/{seq_id}/pattern", response_model=PatternDocument, summary="Set the operator's pattern (a new version)")
def put_pattern(edit: PatternEdit, seq_id: int = SeqId, token_operator: str | None = Depends(writer),
                ctx: AppContext = Depends(get_context)):
    return archive.set_pattern(ctx, seq_id, edit.definition(), operator_name(token_operator, edit.operator),
                               locate=edit.location_of)


@router.post("/{seq_id}/pattern/reset", response_model=PatternDocument,
             summary="Restore the automatic pattern (a new version)")
def reset_pattern(body: PatternReset | None = Body(None), seq_id: int = SeqId,
                  token_operator: str | None = Depends(writer), ctx: AppContext = Depends(get_context)):
    return archive.reset_pattern(ctx, seq_id, operator_name(token_operator, body.operator if body else None))


@router.post("/{seq_id}/search", response_model=SearchDocument,
             responses={503: {"description": "Not done within the time-out (STARID_SEARCH_TIMEOUT_S); nothing was "
                                             "stored, try again"}},
             summary="Identify the current pattern; ranked candidates and the status")
async def search(body: SearchRequest | None = Body(None), seq_id: int = SeqId,
                 _operator: str | None = Depends(writer), ctx: AppContext = Depends(get_context)):
    body = body or SearchRequest()
    deadline = work_deadline(ctx)
    # An unchanged pattern searched again is answered from the archive without queueing behind
    # the CPU-bound searches of other sequences (see workflow.search.reusable_search).
    reused = await run_in_threadpool(searching.reusable_search, ctx, seq_id, body.method, body.max_candidates)
    if reused is not None:
        return reused
    job = await run_in_threadpool(searching.prepare_search, ctx, seq_id, body.method, body.max_candidates,
                                  body.prior.request() if body.prior else None)
    # The compute pool: at most search_workers CPU-bound searches at once, the event loop stays free.
    result = await compute_within(ctx, deadline, "the search", searching.compute_search, job)
    return await run_in_threadpool(searching.store_search, ctx, job, result)


@router.get("/{seq_id}/candidates/{rank}", response_model=CandidateView,
            summary="One candidate of the latest search with its sky section")
async def get_candidate(seq_id: int = SeqId, rank: int = Path(**ID_LIMITS),
                        mag: float = Query(6.0, ge=-2.0, le=7.0, allow_inf_nan=False,
                                           description="faintest catalogue star shown (Hp)"),
                        ctx: AppContext = Depends(get_context)):
    # The archive is read in a thread; the sky section (CPU) is computed in the compute pool, like a search.
    deadline = work_deadline(ctx)
    job = await run_in_threadpool(searching.prepare_candidate_view, ctx, seq_id, rank, mag)
    return await compute_within(ctx, deadline, "the candidate view", searching.candidate_view_job, job)


@router.post("/{seq_id}/confirm", status_code=201, response_model=AttitudeDocument,
             responses={200: {"description": "The same candidate of the same search was confirmed already: "
                                             "the stored record (no second audit record)"},
                        409: {"description": "Not the credible best candidate and no override_reason, another "
                                             "verdict without supersede, or a search that was replaced"}},
             summary="Confirm a candidate of the latest search (guard rails: see the request body)")
def confirm(body: ConfirmRequest, seq_id: int = SeqId, token_operator: str | None = Depends(writer),
            ctx: AppContext = Depends(get_context)):
    operator = operator_name(token_operator, body.operator)
    if operator is None:
        raise ApiError(422, "a confirmation needs the operator's name",
                       problems=[{"location": "body.operator", "message": "missing operator"}])
    if body.search_id is not None:
        # An id that is no search of this sequence is a wrong value (422 at body.search_id); the guard rail
        # behind (409) refuses a search of this sequence that a newer one replaced.
        searching.require_search_of(ctx, seq_id, body.search_id)
    comment = (body.comment or "").strip() or None
    doc, created = confirming.record_confirmation(ctx, seq_id, body.rank, operator, comment,
                                                  override_reason=body.override_reason, supersede=body.supersede,
                                                  search_id=body.search_id,
                                                  replaces=None if body.replaces is None else body.replaces.key())
    return JSONResponse(doc.model_dump(mode="json"), status_code=201 if created else 200)


@router.get("/{seq_id}/aem", response_class=PlainTextResponse,
            summary="CCSDS AEM 2.0 (KVN): one quaternion per snapshot of the confirmed sequence")
def get_aem(seq_id: int = SeqId, ctx: AppContext = Depends(get_context)):
    return attachment(*confirming.sequence_aem(ctx, seq_id))
