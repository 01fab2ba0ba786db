"""/api/view and /api/viewer: the selection shared by the console and the 3D view."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from app.api.routes.common import get_context, writer
from app.api.schemas import ViewEdit
from app.workflow import AppContext, view
from app.workflow.documents import ViewDocument, ViewerDocument

router = APIRouter(prefix="/api", tags=["view"])


@router.get("/view", response_model=ViewDocument,
            summary="The shared view state (sequence, rank, magnitude) with its sequence's latest state")
def get_view(ctx: AppContext = Depends(get_context)):
    return view.view_document(ctx)


@router.put("/view", response_model=ViewDocument, summary="Change the shared view state; only the fields sent change")
def put_view(edit: ViewEdit, _operator: str | None = Depends(writer), ctx: AppContext = Depends(get_context)):
    return view.set_view(ctx, edit.changes(), "console")


@router.get("/viewer", response_model=ViewerDocument,
            summary="Where the 3D view listens (loopback only), or why it is not running")
def get_viewer(ctx: AppContext = Depends(get_context)):
    if ctx.viewer is None:
        return ViewerDocument(available=False, url=None, detail="the 3D view is not running on this server")
    return ctx.viewer.describe()
