"""/api/attitudes: confirmed attitudes (newest first) and their CCSDS APM."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Path, Query
from fastapi.responses import PlainTextResponse

from app.api import service
from app.api.context import AppContext
from app.api.routes.common import ID_LIMITS, get_context

router = APIRouter(prefix="/api/attitudes", tags=["attitudes"])
AttitudeId = Path(description="id of the confirmed attitude", **ID_LIMITS)


@router.get("", summary="A page of confirmed attitudes, newest first (superseded ones included)")
def list_attitudes(offset: int = Query(0, ge=0, le=2**62), limit: int = Query(50, ge=1, le=1000),
                   ctx: AppContext = Depends(get_context)):
    return service.list_attitudes(ctx, offset, limit)


@router.get("/{attitude_id}", summary="One confirmed attitude with its audit record")
def get_attitude(attitude_id: int = AttitudeId, ctx: AppContext = Depends(get_context)):
    return service.get_attitude(ctx, attitude_id)


@router.get("/{attitude_id}/apm", response_class=PlainTextResponse,
            summary="CCSDS APM 2.0 (KVN) of a confirmed attitude, byte for byte as rendered at confirmation")
def get_apm(attitude_id: int = AttitudeId, ctx: AppContext = Depends(get_context)):
    c = service.require_attitude(ctx, attitude_id)
    row = ctx.storage.get_sequence(c.seq_id)
    name = service.download_name(f"{row.sequence_id}-attitude-{c.id}" if row else None,
                                 f"attitude-{c.id}", ".apm")
    return PlainTextResponse(c.apm_text, media_type="text/plain; charset=utf-8",
                             headers={"Content-Disposition": f'attachment; filename="{name}"'})
