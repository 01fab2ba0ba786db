"""/api/health: is the archive usable and the catalogue index loaded."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from app.api import service
from app.api.context import AppContext
from app.api.routes.common import get_context

router = APIRouter(prefix="/api", tags=["system"])


@router.get("/health", summary="Database and index status")
def health(ctx: AppContext = Depends(get_context)):
    return service.health(ctx)
