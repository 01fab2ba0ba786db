"""/api/spacecraft/{name}: the spacecraft's camera calibrations."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, Depends, Path

from app.api.routes.common import get_context, operator_name, writer
from app.api.schemas import CalibrateRequest, SpacecraftName
from app.workflow import AppContext, calibrate
from app.workflow.documents import StoredCalibration

router = APIRouter(prefix="/api/spacecraft", tags=["spacecraft"])
# Annotated, so that the name's check (no NUL) runs on the path too: FastAPI drops it from
# `name: SpacecraftName = Path(...)`.
Spacecraft = Annotated[SpacecraftName, Path(description="the spacecraft name of its telemetry files")]


@router.post("/{name}/calibrate", status_code=201, response_model=StoredCalibration,
             summary="Fit the spacecraft's camera over its newest identified or confirmed sequences; store it as "
                     "the next calibration version")
def calibrate_camera(name: Spacecraft, body: CalibrateRequest | None = Body(None),
                     token_operator: str | None = Depends(writer), ctx: AppContext = Depends(get_context)):
    # A plain def: FastAPI runs it in its thread pool, off the event loop; the work is bounded by
    # calibrate.MAX_SEQUENCES (a few seconds).
    body = body or CalibrateRequest()
    return calibrate.calibrate_spacecraft(ctx, name, operator_name(token_operator, body.operator), body.parameters)


@router.get("/{name}/camera", response_model=StoredCalibration,
            summary="The spacecraft's current camera calibration (404 when it has none)")
def current_camera(name: Spacecraft, ctx: AppContext = Depends(get_context)):
    return calibrate.current_camera(ctx, name)


@router.get("/{name}/calibrations", response_model=list[StoredCalibration],
            summary="Every calibration of the spacecraft's camera, oldest first (empty when it has none)")
def calibrations(name: Spacecraft, ctx: AppContext = Depends(get_context)):
    return calibrate.calibration_history(ctx, name)
