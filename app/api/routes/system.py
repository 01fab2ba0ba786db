"""/api/health: is the archive usable and the catalogue index loaded."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from app.api.routes.common import get_context
from app.workflow import AppContext
from app.workflow.context import health as health_of
from app.workflow.documents import HealthDocument

router = APIRouter(prefix="/api", tags=["system"])


@router.get("/health", response_model=HealthDocument, summary="Database and index status")
def health(ctx: AppContext = Depends(get_context)):
    return health_of(ctx)
