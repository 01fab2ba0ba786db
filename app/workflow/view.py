"""The view workflow: the shared selection (:mod:`app.workflow.view_state`) read with its archive state,
and written after checking it against the archive."""

from __future__ import annotations

from app.timefmt import utc_text
from app.workflow.context import AppContext
from app.workflow.documents import ViewDocument
from app.workflow.errors import Invalid


def view_document(ctx: AppContext) -> ViewDocument:
    """The shared view state plus what the archive says about its sequence now.

    The derived fields (latest search, its size, the pattern version, the
    current confirmation) are read fresh on every call, so a reader notices
    a search, an edit or a confirmation made by the other window even though
    only the selection itself is stored.
    """
    state = ctx.view.get()
    doc = ViewDocument(sequence=state.sequence, rank=state.rank, mag=state.mag, revision=state.revision,
                       updated_by=state.updated_by, updated_at=utc_text(state.updated_at))
    row = ctx.storage.get_sequence(state.sequence) if state.sequence is not None else None
    if row is not None:
        search = ctx.storage.latest_search(row.id)
        version = ctx.storage.current_pattern(row.id)
        confirmation = ctx.storage.current_confirmation(row.id)
        doc.status = row.status
        doc.pattern_version = version.version if version else None
        doc.confirmation_id = confirmation.id if confirmation else None
        if search is not None:
            doc.search_id = search.id
            doc.n_candidates = len(search.result.get("candidates", []))
    return doc


def set_view(ctx: AppContext, changes: dict, writer_name: str) -> ViewDocument:
    """Write the given view fields (checked against the archive) and return the new document.

    A new sequence without a rank starts at rank 1 of its latest search (or
    none); a rank must exist in the latest search of the sequence shown.
    """
    changes = dict(changes)
    seq_id = changes.get("sequence", ctx.view.get().sequence)
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
        ctx.view.update(**changes, updated_by=writer_name)
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    return view_document(ctx)
