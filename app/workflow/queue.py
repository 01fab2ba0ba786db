"""The work queue: new uploads searched without an operator, bulk lists for the console.

An operator receiving a pass of telemetry wants the sequences searched by
the time they look at them, and the ones that need a person (ambiguous, no
match) first in the list (``order=queue`` of
:meth:`app.storage.Storage.list_sequences`).  :func:`search_new_upload` is
what an upload asks for with ``?search=true``: the default search (bright
pairs) of the automatic pattern, run in the compute pool like any other
search, after the upload has been answered.
"""

from __future__ import annotations

import logging

from app.workflow import search as searching
from app.workflow.context import AppContext
from app.workflow.documents import SearchDocument, SequencePage, SequenceSummary, SpacecraftDocument, UploadDocument
from app.workflow.errors import WorkflowError

log = logging.getLogger(__name__)

#: The search a new upload gets: lost-in-space by bright pairs, the default of POST .../search.
AUTO_SEARCH_METHOD = "bright_pair"
#: Wall-clock time an automatic search may wait for a worker on top of its own budget.
AUTO_SEARCH_GRACE_S = 60.0


def wants_automatic_search(doc: UploadDocument) -> bool:
    """Whether an upload that asked to be searched right away (the console's "search new uploads
    automatically") gets a search: a new sequence, and also one stored before but never searched (an
    earlier upload without the flag, or whose search could not run); a searched one keeps its search."""
    return doc.created or doc.sequence.status == "new"


def search_new_upload(ctx: AppContext, seq_id: int) -> SearchDocument | None:
    """Search a new upload as if an operator pressed Search; None (logged) if it could not run.

    It runs after the upload's response, with nobody to tell, so a failure
    is logged and the sequence simply stays ``new`` in the queue.
    """
    try:
        reused = searching.reusable_search(ctx, seq_id, AUTO_SEARCH_METHOD, None)
        if reused is not None:
            return reused
        job = searching.prepare_search(ctx, seq_id, AUTO_SEARCH_METHOD, None)
        future = ctx.compute.submit(searching.compute_search, job)
        result = future.result(timeout=ctx.settings.search_timeout_s + AUTO_SEARCH_GRACE_S)
        return searching.store_search(ctx, job, result)
    except WorkflowError as exc:
        log.warning("automatic search of sequence %d not done: %s", seq_id, exc.detail)
    except Exception:  # a background job must never take the server down; the log has the reason
        log.exception("automatic search of sequence %d failed", seq_id)
    return None


def spacecraft_list(ctx: AppContext) -> list[SpacecraftDocument]:
    """Every spacecraft of the archive with its number of sequences (for filters and bulk exports)."""
    return [SpacecraftDocument(name=name, sequences=n) for name, n in ctx.storage.spacecraft_names()]


def list_sequences(ctx: AppContext, offset: int, limit: int, *, spacecraft: str | None = None,
                   status: str | None = None, search: str | None = None, order: str = "newest") -> SequencePage:
    """A page of the sequence list, filtered and in ``order`` (``queue``: what needs an operator first)."""
    rows, total = ctx.storage.list_sequences(offset, limit, spacecraft=spacecraft, status=status,
                                             search=(search or "").strip() or None, order=order)
    return SequencePage(items=[SequenceSummary.of(r) for r in rows], total=total, offset=offset, limit=limit)
