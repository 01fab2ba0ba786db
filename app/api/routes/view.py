"""/api/view and /api/viewer: each console session's selection, and the 3D view's address for a session."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query

from app.api.routes.common import get_context, writer
from app.api.schemas import ViewEdit, ViewerFollow
from app.workflow import AppContext, view
from app.workflow.documents import ViewDocument, ViewerDocument
from app.workflow.view_state import SESSION_PATTERN

router = APIRouter(prefix="/api", tags=["view"])

Session = Query(None, pattern=SESSION_PATTERN,
                description="the console session (each browser tab has its own); omitted: the session the 3D "
                            "view draws")


@router.get("/view", response_model=ViewDocument,
            summary="A console session's view state (sequence, rank, magnitude) with its sequence's latest state")
def get_view(session: str | None = Session, ctx: AppContext = Depends(get_context)):
    return view.view_document(ctx, session)


@router.put("/view", response_model=ViewDocument,
            summary="Change a console session's view state; only the fields sent change")
def put_view(edit: ViewEdit, session: str | None = Session, token_operator: str | None = Depends(writer),
             ctx: AppContext = Depends(get_context)):
    changes = edit.changes()
    if token_operator is not None and "operator" in changes:
        changes["operator"] = token_operator  # behind tokens, a console's operator is its token's
    return view.set_view(ctx, changes, "console", session)


@router.get("/viewer", response_model=ViewerDocument,
            summary="Where the 3D view listens (loopback only), or why it is not running; with a session, the "
                    "address of a 3D view drawing that console session")
def get_viewer(session: str | None = Query(None, pattern=SESSION_PATTERN,
                                           description="the console session the 3D view's address should draw"),
               ctx: AppContext = Depends(get_context)):
    if ctx.viewer is None:
        return ViewerDocument(available=False, url=None, detail="the 3D view is not running on this server")
    return ctx.viewer.describe(session)


@router.put("/viewer", response_model=ViewDocument,
            summary="Make the 3D view at its bare address (no session named) draw a console session; its state")
def follow_session(body: ViewerFollow, _operator: str | None = Depends(writer),
                   ctx: AppContext = Depends(get_context)):
    return view.follow(ctx, body.session)
