"""The application context: everything a server or a command builds once at start-up.

One :class:`AppContext` holds the archive (:class:`app.storage.Storage`), the
identification context (:class:`app.identification.Sky`, ~1 s to load), the
access policy, the compute pool, the shared view state and a small cache of
parsed sequences with their stored extractions.  The API's routes receive it
through ``request.app.state.context``, the 3D view holds it; nothing here is
a module-level global, so tests build as many as they like.

The ``viewer`` slot holds the 3D view once an interface started one:
:meth:`AppContext.close` calls its ``stop()``.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from app.config import Settings, settings as default_settings
from app.extraction import Extraction
from app.storage import Storage
from app.telemetry import Sequence
from app.workflow.access import AccessPolicy
from app.workflow.compute import ComputePool
from app.workflow.documents import HealthDocument, IndexHealth
from app.workflow.view_state import ViewStateStore

log = logging.getLogger(__name__)

#: Parsed sequences kept in memory (a 16 x 10 sequence and its extraction are a few kB).
SEQUENCE_CACHE_SIZE = 256


@dataclass(frozen=True, eq=False)
class LoadedSequence:
    """A stored upload parsed again, with its stored extraction (see :func:`app.workflow.archive.loaded`)."""

    sequence: Sequence
    extraction: Extraction


class SequenceCache:
    """Thread-safe LRU of :class:`LoadedSequence` by database id.

    Uploads are never changed, so an entry never goes stale.
    """

    def __init__(self, size: int = SEQUENCE_CACHE_SIZE) -> None:
        self._size = size
        self._items: OrderedDict[int, LoadedSequence] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, seq_id: int) -> LoadedSequence | None:
        with self._lock:
            item = self._items.get(seq_id)
            if item is not None:
                self._items.move_to_end(seq_id)
            return item

    def put(self, seq_id: int, item: LoadedSequence) -> None:
        with self._lock:
            self._items[seq_id] = item
            self._items.move_to_end(seq_id)
            while len(self._items) > self._size:
                self._items.popitem(last=False)


@dataclass(eq=False)
class AppContext:
    storage: Storage
    sky: Any  # app.identification.Sky
    settings: Settings = field(default_factory=default_settings)
    access: AccessPolicy = field(default_factory=AccessPolicy)
    cache: SequenceCache = field(default_factory=SequenceCache)
    #: The 3D view once an interface started it (app.viewer); None until then.
    viewer: Any = None
    #: The selection the console and the 3D view share (GET/PUT /api/view).
    view: ViewStateStore = field(default_factory=ViewStateStore)
    #: Where searches run (CPU-bound); by default threads sharing ``sky``.
    _compute: ComputePool | None = None

    @property
    def compute(self) -> ComputePool:
        """Searches run here, at most ``settings.search_workers`` at once."""
        if self._compute is None:
            self._compute = ComputePool(0, threads=self.settings.search_workers, sky=self.sky,
                                        hard_limit_s=3 * self.settings.search_timeout_s)
        return self._compute

    def close(self) -> None:
        if self.viewer is not None and hasattr(self.viewer, "stop"):
            try:
                self.viewer.stop()
            except Exception:  # a viewer failing to stop must not lose the database close
                log.exception("the 3D view did not stop cleanly")
        if self._compute is not None:
            self._compute.shutdown()
        self.storage.close()


def build_context(*, database: str | None = None, host: str = "127.0.0.1",
                  config: Settings | None = None, sky=None) -> AppContext:
    """Open the archive, load the catalogue and index (logging their counts), set the access policy.

    Raises :class:`app.workflow.access.TokenConfigError` (bad or missing tokens)
    or :class:`app.storage.StorageError` (database unusable) with a message.
    """
    from app.workflow.access import load_tokens

    config = config or default_settings()
    access = AccessPolicy.for_host(host, load_tokens(config.tokens, config.tokens_file))
    storage = Storage.open(database or config.database)
    compute = None
    try:
        if sky is None:
            from app.identification import Sky

            if config.search_processes:
                # Before the Sky: the workers load (a first start: compile) their kernels while this process
                # loads (builds) the indexes, then load the indexes it wrote (their lock, app.cache).  Not
                # waited for: the server answers while the workers get ready (compute.kernels_ready).
                compute = ComputePool(config.search_workers, bulk_processes=config.bulk_workers,
                                      hard_limit_s=3 * config.search_timeout_s)
            log.info("loading the star catalogue and the bright-pair index...")
            sky = Sky().with_every_depth()  # a first start builds the deeper index the workers then load
            log.info("catalogue ready: %d stars to Hp %.1f, %d bright pairs", sky.index.n_stars,
                     sky.index.mag_limit, sky.index.n_pairs)
    except BaseException:
        if compute is not None:
            compute.shutdown()
        storage.close()
        raise
    context = AppContext(storage=storage, sky=sky, settings=config, access=access, _compute=compute)
    # Made here in either case, so that a thread pool's kernels warm up from the start as the workers' do.
    log.info("searches run in %s; they wait for the compiled kernels, which load meanwhile", context.compute.kind)
    return context


def health(ctx: AppContext) -> HealthDocument:
    """Is the archive usable and the catalogue index loaded; where searches run."""
    db = ctx.storage.health()
    db.pop("path", None)  # a server path is nobody's business over HTTP
    index = ctx.sky.index if ctx.sky is not None else None
    index_doc = IndexHealth(loaded=index is not None)
    if index is not None:
        index_doc = IndexHealth(loaded=True, stars=int(index.n_stars), pairs=int(index.n_pairs),
                                mag_limit=float(index.mag_limit))
    ok = bool(db.get("ok")) and index is not None
    return HealthDocument(status="ok" if ok else "degraded", db=db, index=index_doc,
                          auth_required_for_writes=ctx.access.require_token,
                          max_upload_bytes=ctx.settings.max_upload_bytes,
                          search_timeout_s=ctx.settings.search_timeout_s, search_workers=ctx.compute.kind,
                          compute_ready=ctx.compute.ready)
