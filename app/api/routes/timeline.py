"""/api/spacecraft/{name}/timeline: a spacecraft's attitude over a time range, with gaps, overlaps and jumps."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Path, Query

from app.api.routes.common import get_context, query_utc
from app.api.schemas import IsoTime, SpacecraftName
from app.workflow import AppContext
from app.workflow.documents import TimelineDocument
from app.workflow.timeline import DEFAULT_GAP_S, DEFAULT_POINTS, MAX_POINTS, spacecraft_timeline

router = APIRouter(prefix="/api/spacecraft", tags=["spacecraft"])
Spacecraft = Annotated[SpacecraftName, Path(description="the spacecraft name of its telemetry files")]
#: At most a year of seconds: a gap threshold beyond it means none.
MAX_GAP_S = 366 * 86400.0


@router.get("/{name}/timeline", response_model=TimelineDocument,
            summary="The spacecraft's attitude over time: RA/Dec/roll, body rate and 1-sigma per sequence, "
                    "statuses and verdicts, gaps, overlaps and jumps the body rate does not explain")
def timeline(name: Spacecraft,
             start: Annotated[IsoTime | None, Query(description="first snapshot times from this one (UTC, ISO 8601); "
                                                               "without start and end: the newest `limit`")] = None,
             end: Annotated[IsoTime | None, Query(description="first snapshot times before this one")] = None,
             limit: Annotated[int, Query(ge=1, le=MAX_POINTS, description="most sequences answered; a range "
                                         "holding more is refused (422)")] = DEFAULT_POINTS,
             gap_s: Annotated[float, Query(gt=0, le=MAX_GAP_S, allow_inf_nan=False,
                                           description="seconds without any sequence that make a gap")] = DEFAULT_GAP_S,
             ctx: AppContext = Depends(get_context)):
    # A plain def: FastAPI runs it in its thread pool; it reads at most MAX_POINTS sequences.
    return spacecraft_timeline(ctx, name, query_utc(start, "start"), query_utc(end, "end"), limit, gap_s)
