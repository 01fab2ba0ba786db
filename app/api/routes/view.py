"""/api/view and /api/viewer: the selection shared by the console and the 3D view (issue 5)."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from app.api import service
from app.api.context import AppContext
from app.api.routes.common import get_context, writer
from app.api.schemas import ViewEdit

router = APIRouter(prefix="/api", tags=["view"])


@router.get("/view", summary="The shared view state (sequence, rank, magnitude) with its sequence's latest state")
def get_view(ctx: AppContext = Depends(get_context)):
    return service.view_document(ctx)


@router.put("/view", summary="Change the shared view state; only the fields sent change")
def put_view(edit: ViewEdit, _operator: str | None = Depends(writer), ctx: AppContext = Depends(get_context)):
    return service.set_view(ctx, edit.changes(), "console")


@router.get("/viewer", summary="Where the 3D view listens (loopback only), or why it is not running")
def get_viewer(ctx: AppContext = Depends(get_context)):
    viewer = ctx.viewer
    if viewer is None:
        return {"available": False, "url": None, "detail": "the 3D view is not running on this server"}
    return viewer.describe()
