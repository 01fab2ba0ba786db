"""Batch reprocessing on Dask: extraction and identification of many sequences.

``python -m app batch`` (:mod:`app.cli.batch`) runs it; three inputs and outputs:

* **files to JSON lines** (``FILES --out results.jsonl``): each file gives the
  document ``solve --json`` prints (:func:`app.workflow.files.solve_document`),
  appended to the output as soon as its chunk is done;
* **files to the archive** (``FILES``, ``--db``): each file is stored as an
  upload (:func:`app.workflow.archive.parse_upload`, extraction,
  :func:`~app.workflow.archive.store_upload`), then searched and the search
  stored with its method, the catalogue index and the camera calibration
  version it used - :func:`app.workflow.search.prepare_search`,
  :func:`~app.workflow.search.compute_search` and
  :func:`~app.workflow.search.store_search`, the server's own three steps;
* **the archive again** (``--archive``): every stored sequence is searched
  again, e.g. after a new catalogue or index.

A re-run skips what is done: in JSON lines, every file already in the output
(a line cut short by a crash is dropped first); in the archive, every
sequence whose latest search :func:`app.workflow.search.reusable_search`
would reuse (same method, pattern version, options, index and camera
calibration; a timed-out search is done again).

Where the work runs
-------------------
The driver (this process) lists the inputs, hands out chunks of them and
collects small outcomes; everything else runs on Dask workers: a
:class:`distributed.LocalCluster` of ``workers`` processes with one thread
each by default, or any cluster through its scheduler's address.  Each task
is a chunk of sequences, so that Dask's per-task cost (about a millisecond)
is paid once per several identifications of ~50 ms.  Every worker process
loads the catalogue and the bright-pair index once, when it joins
(:class:`LoadSky`, a worker plugin; :func:`worker_sky` caches it for the
process).  For the archive, every worker process also opens the archive
once (:class:`OpenArchive`) and stores its own results, so the driver is
never the bottleneck and each stored search records the index its worker
really searched; the archive itself takes the concurrent writers (SQLite
serialises them in one file on one machine; PostgreSQL is what a cluster of
several machines shares - a SQLite path is refused with ``--scheduler``).
Workers read the files themselves, by the path the driver sees (made
absolute): on other machines the files must be on shared storage at the
same path.  The tasks are this module's functions, sent by reference: every
worker needs this package installed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import NamedTuple

import dask
from distributed import Client, LocalCluster, WorkerPlugin, as_completed

from app.identification import METHODS, SearchOptions
from app.storage import Storage, backend_of, content_sha256
from app.telemetry.errors import TelemetryError
from app.workflow.archive import extraction_job, parse_upload, store_upload
from app.workflow.context import AppContext
from app.workflow.files import input_sha256, invalid_solve_document, solve_document, telemetry_files
from app.workflow.search import compute_search, prepare_search, reusable_search, search_options_record, store_search

log = logging.getLogger(__name__)

#: The lost-in-space methods a batch can run (tracking needs a prior per sequence).
BATCH_METHODS = ("bright_pair", "tf")
#: Sequences per task at most; fewer when there are few sequences, so that every worker gets several tasks.
MAX_CHUNK = 16
#: Tasks in flight per worker thread: enough to keep every worker busy while the driver collects outcomes.
TASKS_PER_THREAD = 3
#: Seconds to wait for a cluster's workers (an existing cluster) and for their start-up.
CLUSTER_TIMEOUT_S = 300.0
#: Seconds to wait for the scheduler of an existing cluster to answer (Dask retries a refused connection until
#: then): a running scheduler answers within a second, even across a slow network, so 20 s leaves room for
#: one that is just starting while a wrong address or a stopped scheduler is told within the time a user waits.
SCHEDULER_CONNECT_TIMEOUT_S = 20.0
#: Dask settings of a local cluster: its workers' statistical profiler (which samples every thread's stack
#: every 10 ms for a dashboard this cluster does not serve), and its monitors' ticks, cost a few percent of
#: every core and the scheduler's share of the driver's core: measured on 2 cores, the driver's process
#: used 0.045 cores instead of 0.08 and the workers about 10 % less CPU per sequence.  An existing
#: cluster keeps its own settings.
LOCAL_CLUSTER_CONFIG = {"distributed.worker.profile.enabled": False,
                        "distributed.admin.system-monitor.interval": "5s",
                        "distributed.admin.tick.interval": "1s"}

Progress = Callable[[int, int, str], None]

class Outcome(NamedTuple):
    """What became of one sequence on a worker."""

    #: "processed" (detail: the search's status), "skipped" (its latest search is reused), "invalid" or
    #: "failed" (detail: the message).
    kind: str
    detail: str | None = None
    #: For the operator, of a file stored now: other stored uploads have its spacecraft and sequence id
    #: (:func:`app.workflow.archive.same_sequence_note`), as ``upload`` says it.
    note: str | None = None


# ---------------------------------------------------------------------------
# Worker side: the catalogue and the archive once per process, and the tasks
# ---------------------------------------------------------------------------

_SKY = None
_ARCHIVES: dict[str, AppContext] = {}
_LOCK = threading.Lock()


def worker_sky():
    """This process's :class:`app.identification.Sky`, loaded on first use (once per worker process)."""
    global _SKY
    with _LOCK:
        if _SKY is None:
            from app.compiled import warm_up
            from app.identification import Sky

            _SKY = Sky()
            warm_up()  # the identification's compiled kernels (loaded from their cache), before any task
        return _SKY


def worker_archive(database: str) -> AppContext:
    """This process's context on the archive ``database`` (opened once per worker process)."""
    sky = worker_sky()
    with _LOCK:
        ctx = _ARCHIVES.get(database)
        if ctx is None:
            from app.config import settings

            ctx = _ARCHIVES[database] = AppContext(storage=Storage.open(database), sky=sky, settings=settings())
        return ctx


def close_worker_archive(database: str) -> None:
    with _LOCK:
        ctx = _ARCHIVES.pop(database, None)
    if ctx is not None:
        ctx.storage.close()


class LoadSky(WorkerPlugin):
    """Loads the catalogue and index when a worker joins, before it takes any task."""

    name = "starid-sky"

    def setup(self, worker) -> None:
        worker_sky()


class OpenArchive(WorkerPlugin):
    """Opens the archive on every worker for a batch into it, and closes it after."""

    name = "starid-archive"

    def __init__(self, database: str) -> None:
        self.database = database

    def setup(self, worker) -> None:
        worker_archive(self.database)

    def teardown(self, worker) -> None:
        close_worker_archive(self.database)


def index_record(sky) -> dict:
    """The catalogue index a search records (the ``index`` of :func:`search_options_record`)."""
    return search_options_record(SimpleNamespace(sky=sky), SearchOptions(), None)["index"]


def worker_info() -> dict:
    """What a worker searches with, and where it runs (``Client.run`` on every worker)."""
    return {"index": index_record(worker_sky()), "host": socket.gethostname(), "pid": os.getpid(),
            "cwd": os.getcwd()}


def _local(path: str, driver_cwd: str) -> str:
    """The path a worker opens: as given when it runs where the driver does, else made absolute."""
    return path if os.path.isabs(path) or os.getcwd() == driver_cwd else os.path.join(driver_cwd, path)


def solve_files_task(paths: list[str], driver_cwd: str, method: str,
                     max_candidates: int | None) -> list[tuple[Outcome, str]]:
    """Each file's outcome and its ``solve --json`` line (read here, as ``solve`` reads them; a failure is
    that file's error).  The outcome comes apart so that the driver need not parse the line."""
    sky = worker_sky()
    options = SearchOptions() if max_candidates is None else SearchOptions(max_candidates=max_candidates)
    out = []
    for path in paths:
        local = _local(path, driver_cwd)
        digest = input_sha256(local)  # before reading it: a file changed meanwhile is answered again next time
        [(_, sequence, problem)] = telemetry_files([local])
        try:
            if problem is not None:
                doc = invalid_solve_document(path, str(problem), digest)
            else:
                doc = solve_document(path, sequence, sky, options=options, method=method, digest=digest)
        except Exception as exc:  # noqa: BLE001 - one file's failure must not end the batch
            doc = invalid_solve_document(
                path, f"{path}: could not be processed ({type(exc).__name__}: {exc}); the file passed validation, "
                      "so this is a bug: please report it with the file", digest)
        outcome = Outcome("invalid", doc.error) if doc.status == "invalid" else Outcome("processed", doc.status)
        out.append((outcome, doc.model_dump_json()))
    return out


def _search_one(ctx: AppContext, seq_id: int, method: str, max_candidates: int | None) -> Outcome:
    """The server's search of a stored sequence (prepare, compute, store) unless its latest one is reused."""
    if reusable_search(ctx, seq_id, method, max_candidates) is not None:
        return Outcome("skipped")
    job = prepare_search(ctx, seq_id, method, max_candidates)
    result = compute_search(job, sky=ctx.sky)
    store_search(ctx, job, result)
    return Outcome("processed", result.status)


def _file_one(ctx: AppContext, path: str, method: str, max_candidates: int | None) -> Outcome:
    """Store a telemetry file as an upload (extracted here) unless stored already, then search it."""
    limit = ctx.settings.max_upload_bytes
    try:
        with open(path, "rb") as stream:
            data = stream.read(limit + 1)  # parse_upload refuses what is over the limit, with the message
        upload = parse_upload(ctx, data, Path(path).name)
    except OSError as exc:
        return Outcome("invalid", f"cannot read the file: {exc.strerror or type(exc).__name__}")
    except TelemetryError as exc:
        return Outcome("invalid", str(exc))
    row = ctx.storage.find_sequence(content_sha256(upload.raw_text))
    if row is not None:
        return _search_one(ctx, row.id, method, max_candidates)
    stored = store_upload(ctx, upload, extraction_job(upload.sequence, upload.known_hot))
    return _search_one(ctx, stored.id, method, max_candidates)._replace(note=stored.note)


def archive_task(items: list, database: str, driver_cwd: str | None, method: str,
                 max_candidates: int | None) -> list[Outcome]:
    """Files (paths) stored and searched, or archived sequences (ids) searched again, into ``database``."""
    ctx = worker_archive(database)
    out = []
    for item in items:
        try:
            if isinstance(item, str):
                out.append(_file_one(ctx, _local(item, driver_cwd), method, max_candidates))
            else:
                out.append(_search_one(ctx, item, method, max_candidates))
        except Exception as exc:  # noqa: BLE001 - reported per sequence, the batch goes on
            out.append(Outcome("failed", f"{type(exc).__name__}: {exc}"))
    return out


# ---------------------------------------------------------------------------
# The cluster
# ---------------------------------------------------------------------------

@dataclass
class Cluster:
    """A Dask client with its workers ready (the catalogue loaded on each)."""

    client: Client
    local: LocalCluster | None
    threads: int
    workers: list[dict]
    startup_s: float

    def close(self) -> None:
        self.client.close()
        if self.local is not None:
            self.local.close()


def connect(scheduler: str) -> Client:
    """A client of the scheduler at ``scheduler``; OSError naming it when it does not answer within
    :data:`SCHEDULER_CONNECT_TIMEOUT_S`, ValueError when it is no scheduler address."""
    try:
        return Client(scheduler, timeout=SCHEDULER_CONNECT_TIMEOUT_S)
    except ValueError as exc:  # e.g. "unknown address scheme 'http'"
        raise ValueError(f"the scheduler address {scheduler!r} is not a Dask one: {exc}; "
                         "give e.g. tcp://host:8786") from None
    except OSError:  # TimeoutError too: refused, unknown host or no answer, retried until the time-out
        raise OSError(f"no Dask scheduler answered at {scheduler} within {SCHEDULER_CONNECT_TIMEOUT_S:g} s: "
                      "is it running, and is the address right (e.g. tcp://host:8786)?") from None


def start_cluster(scheduler: str | None = None, workers: int = 1) -> Cluster:
    """A local cluster of ``workers`` single-threaded processes, or the cluster at ``scheduler``
    (``tcp://host:8786``); returns once every worker has loaded the catalogue."""
    t0 = time.perf_counter()
    # A local cluster's scheduler runs in this process: its INFO chatter is not the user's business.
    for name in ("distributed", "tornado"):
        logging.getLogger(name).setLevel(logging.WARNING)
    local = None
    if scheduler:
        client = connect(scheduler)
        client.wait_for_workers(1, timeout=CLUSTER_TIMEOUT_S)
    else:
        with dask.config.set(LOCAL_CLUSTER_CONFIG):  # the workers take the configuration when they start
            local = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                                 silence_logs=logging.ERROR)
        client = Client(local)
        client.wait_for_workers(workers, timeout=CLUSTER_TIMEOUT_S)
    try:
        client.register_plugin(LoadSky())  # runs on every worker, and on workers that join later
        info = list(client.run(worker_info).values())
        threads = sum(client.nthreads().values())
    except BaseException:
        client.close()
        if local is not None:
            local.close()
        raise
    return Cluster(client=client, local=local, threads=threads, workers=info, startup_s=time.perf_counter() - t0)


# ---------------------------------------------------------------------------
# The driver
# ---------------------------------------------------------------------------

@dataclass
class BatchReport:
    """What a batch did and how fast (``sequences_per_s``: processed sequences over the processing time,
    from the first task sent to the last outcome in, the cluster's start-up excluded)."""

    mode: str
    total: int = 0
    processed: int = 0
    skipped: int = 0
    again: int = 0  # files to JSON lines: answered before, but changed since (or failed): solved again
    invalid: int = 0
    failed: int = 0
    statuses: dict[str, int] = field(default_factory=dict)
    workers: int = 0
    threads: int = 0
    startup_s: float = 0.0
    processing_s: float = 0.0
    errors: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # the first 20 of the operator's notes, each naming its file

    @property
    def sequences_per_s(self) -> float | None:
        return round(self.processed / self.processing_s, 2) if self.processing_s > 0 and self.processed else None

    def add(self, label: str, outcome: Outcome) -> None:
        """One sequence's outcome."""
        kind, detail, note = outcome
        if note is not None and len(self.notes) < 20:
            self.notes.append(f"{label}: {note}")
        if kind == "processed":
            self.processed += 1
            self.statuses[detail] = self.statuses.get(detail, 0) + 1
        elif kind == "skipped":
            self.skipped += 1
        else:
            setattr(self, kind, getattr(self, kind) + 1)
            if len(self.errors) < 20:  # a file's own message names it already
                self.errors.append(detail if str(detail).startswith(f"{label}: ") else f"{label}: {detail}")

    def to_json(self) -> dict:
        return {"mode": self.mode, "total": self.total, "processed": self.processed, "skipped": self.skipped,
                "again": self.again,
                "invalid": self.invalid, "failed": self.failed, "statuses": self.statuses, "workers": self.workers,
                "threads": self.threads, "startup_s": round(self.startup_s, 2),
                "processing_s": round(self.processing_s, 3), "sequences_per_s": self.sequences_per_s,
                "errors": self.errors, "notes": self.notes}


def chunk_size(n: int, threads: int) -> int:
    """Sequences per task: at most :data:`MAX_CHUNK`, and at least four tasks per worker thread."""
    return max(1, min(MAX_CHUNK, math.ceil(n / max(1, 4 * threads))))


def check_method(method: str) -> None:
    if method not in BATCH_METHODS or method not in METHODS:
        raise ValueError(f"a batch runs a lost-in-space method: one of {', '.join(BATCH_METHODS)}")


def _run_chunks(cluster: Cluster, items: list, size: int, submit: Callable, collect: Callable) -> None:
    """Send ``items`` in chunks of ``size`` (``submit(chunk) -> future``), at most a few per worker thread in
    flight, and hand each chunk with its result or error to ``collect(chunk, result, error)``."""
    running = as_completed()
    chunk_of = {}
    limit = max(1, TASKS_PER_THREAD * cluster.threads)
    chunks = [items[i:i + size] for i in range(0, len(items), size)]
    sent = 0
    while sent < len(chunks) or chunk_of:
        while sent < len(chunks) and len(chunk_of) < limit:
            future = submit(chunks[sent])
            chunk_of[future.key] = chunks[sent]
            running.add(future)
            sent += 1
        future = next(running)
        chunk = chunk_of.pop(future.key)
        try:
            collect(chunk, future.result(), None)
        except Exception as exc:  # noqa: BLE001 - the whole chunk failed (e.g. its worker died too often)
            collect(chunk, None, f"{type(exc).__name__}: {exc}")


def answered_files(out_path: Path) -> dict[str, str | None]:
    """Each file's ``input_sha256`` in a JSON-lines output (its last line's); a last line cut short (a crash
    mid-write) is removed."""
    if not out_path.exists():
        return {}
    data = out_path.read_bytes()
    end = data.rfind(b"\n") + 1
    if end < len(data):
        with out_path.open("r+b") as f:
            f.truncate(end)
    answered = {}
    for line in data[:end].splitlines():
        try:
            doc = json.loads(line)
            answered[doc["file"]] = doc.get("input_sha256")
        except (ValueError, KeyError, TypeError, AttributeError):
            continue
    return answered


def _drop_lines(out_path: Path, files: set[str]) -> None:
    """Remove the lines of ``files`` from a JSON-lines output (written anew, then moved into place)."""
    kept = []
    for line in out_path.read_bytes().splitlines(keepends=True):
        try:
            if json.loads(line)["file"] in files:
                continue
        except (ValueError, KeyError, TypeError):
            pass
        kept.append(line)
    tmp = out_path.with_name(out_path.name + ".tmp")
    tmp.write_bytes(b"".join(kept))
    tmp.replace(out_path)


def files_to_jsonl(cluster: Cluster, paths: list[str], out_path: Path, *, method: str = "bright_pair",
                   max_candidates: int | None = None, redo: bool = False,
                   progress: Progress | None = None) -> BatchReport:
    """Identify ``paths`` on the cluster; append one ``solve --json`` line per file to ``out_path``.

    A file whose line is there with the same ``input_sha256`` as the file has now is skipped as done; the
    others are solved (again: a changed file, a line of a worker's failure, or of a version before the
    digest), and their older lines removed, so that the output keeps one line per file.
    """
    check_method(method)
    report = BatchReport(mode="files to JSON lines", total=len(paths), workers=len(cluster.workers),
                         threads=cluster.threads, startup_s=cluster.startup_s)
    if redo and out_path.exists():
        out_path.unlink()
    answered = answered_files(out_path)
    todo = [p for p in paths if answered.get(p) is None or answered[p] != input_sha256(p)]
    again = {p for p in todo if p in answered}
    if again:
        _drop_lines(out_path, again)
    report.skipped, report.again = len(paths) - len(todo), len(again)
    finished = report.skipped
    cwd = os.getcwd()
    t0 = time.perf_counter()
    with out_path.open("a", encoding="utf-8") as out:
        def collect(chunk: list[str], results: list[tuple[Outcome, str]] | None, error: str | None) -> None:
            nonlocal finished
            if error is not None:  # no digest: solved again next time
                results = [(Outcome("failed", error), invalid_solve_document(path, f"{path}: {error}", None)
                            .model_dump_json()) for path in chunk]
            for path, (outcome, _) in zip(chunk, results):
                report.add(path, outcome)
            out.write("".join(line + "\n" for _, line in results))
            out.flush()
            finished += len(chunk)
            if progress:
                progress(finished, report.total, "")

        _run_chunks(cluster, todo, chunk_size(len(todo), cluster.threads),
                    lambda chunk: cluster.client.submit(solve_files_task, chunk, cwd, method, max_candidates,
                                                        pure=False),
                    collect)
    report.processing_s = time.perf_counter() - t0
    return report


def to_archive(database: str, cluster: Cluster, *, paths: list[str] | None = None, method: str = "bright_pair",
               max_candidates: int | None = None, progress: Progress | None = None) -> BatchReport:
    """Store and search ``paths`` (files to the archive), or search every archived sequence again
    (``paths`` None), on the cluster's workers; sequences whose latest search would be reused are skipped.

    Files with the same content are sent once (the others count as skipped).  Raises StorageError when
    the archive cannot be opened here, ValueError for a SQLite archive with a cluster of its own.
    """
    check_method(method)
    if cluster.local is None and backend_of(str(database)) == "sqlite":
        raise ValueError("the workers of an existing cluster may run on other machines, which cannot share a SQLite "
                         "file: give a postgresql:// archive (or use the local cluster)")
    # Opened here first: an unusable archive fails before any work, and the schema is brought up to date once.
    with Storage.open(database) as storage:
        if paths is None:
            items = _archived_ids(storage)
            duplicates = 0
        else:
            items, seen = [], set()
            for path in paths:
                try:
                    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
                except OSError:
                    digest = None  # the worker reports why it cannot be read
                if digest is None or digest not in seen:
                    items.append(path)
                    seen.add(digest)
            duplicates = len(paths) - len(items)
    report = BatchReport(mode="the archive again" if paths is None else "files to the archive",
                         total=len(items) + duplicates, skipped=duplicates, workers=len(cluster.workers),
                         threads=cluster.threads, startup_s=cluster.startup_s)
    finished = report.skipped
    database = str(database)
    cwd = os.getcwd()
    t0 = time.perf_counter()

    def collect(chunk: list, outcomes: list[Outcome] | None, error: str | None) -> None:
        nonlocal finished
        for item, outcome in zip(chunk, outcomes or [Outcome("failed", error)] * len(chunk)):
            report.add(item if isinstance(item, str) else f"sequence {item}", outcome)
        finished += len(chunk)
        if progress:
            progress(finished, report.total, "")

    cluster.client.register_plugin(OpenArchive(database))
    try:
        _run_chunks(cluster, items, chunk_size(len(items), cluster.threads),
                    lambda chunk: cluster.client.submit(archive_task, chunk, database, cwd, method, max_candidates,
                                                        pure=False),
                    collect)
    finally:
        cluster.client.unregister_worker_plugin(OpenArchive.name)
    report.processing_s = time.perf_counter() - t0
    return report


def _archived_ids(storage: Storage) -> list[int]:
    ids, offset = [], 0
    while True:
        rows, total = storage.list_sequences(offset, 1000, order="oldest")
        ids += [r.id for r in rows]
        offset += len(rows)
        if not rows or offset >= total:
            return ids
