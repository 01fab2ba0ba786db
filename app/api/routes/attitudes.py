"""/api/attitudes: confirmed attitudes (newest first) and their CCSDS APM."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Path, Query
from fastapi.responses import PlainTextResponse

from app.api.routes.common import ID_LIMITS, attachment, get_context
from app.workflow import AppContext, confirm as confirming
from app.workflow.documents import AttitudeDocument, AttitudePage

router = APIRouter(prefix="/api/attitudes", tags=["attitudes"])
AttitudeId = Path(description="id of the confirmed attitude", **ID_LIMITS)


@router.get("", response_model=AttitudePage,
            summary="A page of confirmed attitudes, newest first (superseded ones included)")
def list_attitudes(offset: int = Query(0, ge=0, le=2**62), limit: int = Query(50, ge=1, le=1000),
                   ctx: AppContext = Depends(get_context)):
    return confirming.list_attitudes(ctx, offset, limit)


@router.get("/{attitude_id}", response_model=AttitudeDocument, summary="One confirmed attitude with its audit record")
def get_attitude(attitude_id: int = AttitudeId, ctx: AppContext = Depends(get_context)):
    return confirming.get_attitude(ctx, attitude_id)


@router.get("/{attitude_id}/apm", response_class=PlainTextResponse,
            summary="CCSDS APM 2.0 (KVN) of a confirmed attitude, byte for byte as rendered at confirmation")
def get_apm(attitude_id: int = AttitudeId, ctx: AppContext = Depends(get_context)):
    return attachment(*confirming.attitude_apm(ctx, attitude_id))
