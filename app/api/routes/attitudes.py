"""/api/attitudes: confirmed attitudes (newest first), their CCSDS APM and ACM, and bulk AEM exports."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Path, Query
from fastapi.responses import PlainTextResponse

from app.api.routes.common import ID_LIMITS, attachment, get_context, query_utc
from app.api.schemas import IsoTime, SpacecraftName
from app.workflow import AppContext, confirm as confirming
from app.workflow.documents import AttitudeDocument, AttitudePage

router = APIRouter(prefix="/api/attitudes", tags=["attitudes"])
AttitudeId = Path(description="id of the confirmed attitude", **ID_LIMITS)


@router.get("", response_model=AttitudePage,
            summary="A page of confirmed attitudes, newest first (superseded ones included)")
def list_attitudes(offset: int = Query(0, ge=0, le=2**62), limit: int = Query(50, ge=1, le=1000),
                   ctx: AppContext = Depends(get_context)):
    return confirming.list_attitudes(ctx, offset, limit)


# Before /{attitude_id}: "aem" is a path of its own, not an attitude id.
@router.get("/aem", response_class=PlainTextResponse,
            summary="CCSDS AEM 2.0 (KVN) of a spacecraft's confirmed attitudes in a time range, one segment per "
                    "sequence as rendered at its confirmation")
def bulk_aem(spacecraft: Annotated[SpacecraftName, Query(description="the spacecraft name")],
             start: Annotated[IsoTime | None, Query(description="first reference epoch included (UTC, ISO 8601)")] = None,
             end: Annotated[IsoTime | None, Query(description="reference epochs before this one (UTC, ISO 8601)")] = None,
             ctx: AppContext = Depends(get_context)):
    return attachment(*confirming.bulk_aem(ctx, spacecraft, query_utc(start, "start"), query_utc(end, "end")))


@router.get("/{attitude_id}", response_model=AttitudeDocument, summary="One confirmed attitude with its audit record")
def get_attitude(attitude_id: int = AttitudeId, ctx: AppContext = Depends(get_context)):
    return confirming.get_attitude(ctx, attitude_id)


@router.get("/{attitude_id}/apm", response_class=PlainTextResponse,
            summary="CCSDS APM 2.0 (KVN) of a confirmed attitude, byte for byte as rendered at confirmation")
def get_apm(attitude_id: int = AttitudeId, ctx: AppContext = Depends(get_context)):
    return attachment(*confirming.attitude_apm(ctx, attitude_id))


@router.get("/{attitude_id}/aem", response_class=PlainTextResponse,
            summary="CCSDS AEM 2.0 (KVN) of a confirmed attitude: one quaternion per snapshot, byte for byte as "
                    "rendered at its confirmation (superseded or not)")
def get_aem(attitude_id: int = AttitudeId, ctx: AppContext = Depends(get_context)):
    return attachment(*confirming.attitude_aem(ctx, attitude_id))


@router.get("/{attitude_id}/acm", response_class=PlainTextResponse,
            summary="CCSDS ACM 2.0 (KVN) of a confirmed attitude: every snapshot's attitude with the body rate, the "
                    "covariance and the attitude determination (method, sensor), as rendered at confirmation")
def get_acm(attitude_id: int = AttitudeId, ctx: AppContext = Depends(get_context)):
    return attachment(*confirming.attitude_acm(ctx, attitude_id))
