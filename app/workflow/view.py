"""The view workflow: a console session's selection (:mod:`app.workflow.view_state`) read with its
archive state, and written after checking it against the archive.

``session=None`` means the session the 3D view at its bare address draws
(:attr:`app.workflow.view_state.ViewStateStore.followed`); a 3D view opened
from a console names that console's session.
"""

from __future__ import annotations

from app.storage import ConfirmationRow
from app.timefmt import utc_text
from app.workflow.context import AppContext
from app.workflow.documents import ConfirmRequestDocument, ViewDocument
from app.workflow.errors import Invalid
from app.workflow.text import require_audit_text
from app.workflow.view_state import check_session


def _session(ctx: AppContext, session: str | None) -> str:
    """The session meant, checked: Invalid (located at the query parameter) for a malformed id."""
    if session is None:
        return ctx.view.followed
    try:
        return check_session(session)
    except ValueError as exc:
        raise Invalid(str(exc), location="query.session", message=str(exc)) from None


def view_document(ctx: AppContext, session: str | None = None) -> ViewDocument:
    """A session's view state plus what the archive says about its sequence now.

    The derived fields (latest search, its size, the pattern version, the
    current verdict) are read fresh on every call, so a reader notices a
    search, an edit or a verdict made elsewhere even though only the
    selection itself is stored.
    """
    name = _session(ctx, session)
    state = ctx.view.get(name)
    request = state.confirm_request
    doc = ViewDocument(sequence=state.sequence, rank=state.rank, mag=state.mag, revision=state.revision,
                       updated_by=state.updated_by, updated_at=utc_text(state.updated_at), session=name,
                       followed_by_3d=name == ctx.view.followed, operator=state.operator,
                       confirm_request=None if request is None else ConfirmRequestDocument(
                           sequence=request.sequence, rank=request.rank, search_id=request.search_id,
                           number=request.number, comment=request.comment))
    row = ctx.storage.get_sequence(state.sequence) if state.sequence is not None else None
    if row is not None:
        search = ctx.storage.latest_search(row.id)
        version = ctx.storage.current_pattern(row.id)
        verdict = ctx.storage.current_verdict(row.id)
        doc.status = row.status
        doc.pattern_version = version.version if version else None
        if isinstance(verdict, ConfirmationRow):
            doc.confirmation_id = verdict.id
        elif verdict is not None:
            doc.rejection_id = verdict.id
        if search is not None:
            doc.search_id = search.id
            doc.n_candidates = len(search.result.get("candidates", []))
    return doc


def set_view(ctx: AppContext, changes: dict, writer_name: str, session: str | None = None) -> ViewDocument:
    """Write the given view fields of a session (checked against the archive) and return the new document.

    A new sequence without a rank starts at rank 1 of its latest search (or
    none); a rank must exist in the latest search of the sequence shown.
    """
    name = _session(ctx, session)
    changes = dict(changes)
    seq_id = changes.get("sequence", ctx.view.get(name).sequence)
    if "sequence" in changes and seq_id is not None and ctx.storage.get_sequence(seq_id) is None:
        raise Invalid(f"no sequence with id {seq_id}", location="body.sequence", message="no such sequence")
    search = ctx.storage.latest_search(seq_id) if seq_id is not None else None
    n_candidates = len(search.result.get("candidates", [])) if search is not None else 0
    if "sequence" in changes and "rank" not in changes:
        changes["rank"] = 1 if n_candidates else None
    rank = changes.get("rank")
    if rank is not None and not 1 <= rank <= n_candidates:
        raise Invalid(f"rank {rank} is not a candidate of the latest search (it has {n_candidates})",
                      location="body.rank", message=f"not in 1..{n_candidates}")
    try:
        ctx.view.update(session=name, **changes, updated_by=writer_name)
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    return view_document(ctx, name)


def request_confirmation(ctx: AppContext, sequence: int, rank: int, search_id: int | None,
                         session: str | None = None, comment: str | None = None) -> ViewDocument:
    """Send the confirmation of ``rank`` of ``sequence`` (of its search ``search_id``) to the console of
    ``session``, which opens its second step for it: the 3D view's Confirm of a rank that needs one.  The
    ``comment`` typed with it goes along (the console puts it in its comment box)."""
    require_audit_text(comment=comment)
    name = _session(ctx, session)
    try:
        ctx.view.request_confirmation(name, sequence, rank, search_id, comment)
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    return view_document(ctx, name)


def follow(ctx: AppContext, session: str) -> ViewDocument:
    """Make the 3D view at the bare address draw ``session`` (a console opening its 3D tab calls this) and return
    its state.  A 3D view opened at a console's own address draws that console whatever this says."""
    name = _session(ctx, session)
    ctx.view.follow(name)
    return view_document(ctx, name)
