"""Load benchmark of the REST API: 20 concurrent clients on loopback.

``python -m app bench --suite load [--n SECONDS] [--seed S] [--json]``.

What is measured
----------------
The real server is started as a subprocess (``python -m app serve --port
<free> --db <tmp>``), exactly as an operator would start it, on a fresh
temporary database.  Once ``/api/health`` answers, ``clients`` threads run
the operator's loop for ``duration_s`` seconds, each on its own keep-alive
HTTP connection (``http.client``, no extra dependency):

1. ``POST /api/sequences``: a telemetry file.  Every other loop uses a
   sequence simulated fresh for this run (never seen by the server, so it
   is parsed, extracted, stored and later searched from scratch); the other
   loops upload one of the sample files (after its first upload the server
   recognises the content and answers 200 with the stored sequence).
2. ``POST /api/sequences/{id}/search``.
3. ``GET /api/sequences/{id}/candidates/1`` when the search found a candidate.
4. A pause of about ``think_s`` seconds (default 1 s: an operator looks at
   the result, a script paces itself); with ``think_s=0`` the clients loop
   without pause and the run measures the server's saturation throughput.

Every request's wall-clock latency is recorded on the client side from
sending the request to reading the whole body.  An error is any exception
(connection reset, time-out) or any status other than the one the loop
expects (200/201 for an upload, 200 for the rest).  The fresh sequences are
simulated *before* the clock starts so the clients' CPU use does not load the
2 shared cores during the measurement; the run stops early, with the pool
exhausted flagged, rather than upload a fresh sequence twice.

Latency percentiles are nearest-rank percentiles of all requests of a kind
(p95 = the smallest latency at least 95 % of the requests did not exceed).
The target is zero errors and a 95th-percentile search latency of
at most 150 ms.

With ``adversarial`` (``--adversarial``: 2) that many more clients send
worst-case files without pause for the whole run: every file
valid and inside every limit, 64 snapshots of 64 sources, each made fresh so
that none is answered from the archive (:func:`worst_case_telemetry`:
random sources, sources piled on one pixel, a dense cluster, in turn).  The
target is unchanged and counts the ordinary clients only; the hostile
clients' answers (201 stored, or 503 when the bulk lane could not take them
within the time-out) are reported beside it.

With ``database`` (``--database postgresql://...``) the servers share a fresh
PostgreSQL database made on that server for the run (and dropped after it)
instead of a SQLite file; with ``servers`` (``--servers 2``) that many
servers run on it, each with its own worker pool as configured
(one search worker per core by default), and client i uploads through
server i and searches and views through the next one.
"""

from __future__ import annotations

import contextlib
import http.client
import json
import math
import os
import tempfile
import threading
import time
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.bench.server import free_port, start_server, stop_server, tail, wait_ready

REPO = Path(__file__).resolve().parents[2]
SAMPLE_DIR = REPO / "sample_telemetry"
DEFAULT_SECONDS = 30
DEFAULT_CLIENTS = 20
#: The acceptance target for the 95th-percentile search latency.
TARGET_P95_SEARCH_MS = 150.0
#: Loops a client without pause makes per second, at most (measured: 20 clients, ~1.9 each);
#: with a pause, one loop per pause plus ~50 ms of requests.  Fresh sequences for half the
#: loops, with 30 % to spare, are simulated (~60 ms each) before the clock starts.
MAX_LOOPS_PER_CLIENT_S = 2.2
MIN_FRESH = 60


def fresh_needed(clients: int, duration_s: float, think_s: float) -> int:
    loops_per_s = min(MAX_LOOPS_PER_CLIENT_S, 1.0 / (think_s + 0.05))
    return max(MIN_FRESH, math.ceil(0.5 * 1.3 * loops_per_s * clients * duration_s))


#: Scenarios of the fresh sequences: what a ground station receives day to day.
FRESH_SCENARIOS = ("nominal", "nominal", "clean", "ghosts", "planet", "sparse")
REQUEST_TIMEOUT_S = 120.0
#: Pause of each client between its loops, seconds: an operator looks at the result, a script
#: paces its uploads.  20 clients at ~1 loop/s are 1,200 sequences a minute, far more than a
#: ground station receives; ``--think 0`` removes the pause (the saturation test).
DEFAULT_THINK_S = 1.0
#: Clients sending worst-case files with ``--adversarial``.
ADVERSARIAL_CLIENTS = 2
#: Worst-case files prepared per hostile client and second of the run (each upload takes ~0.4 s
#: of a bulk worker; a hostile client cannot send more than a few a second).
HOSTILE_FILES_PER_S = 4
#: The shapes of worst-case telemetry, in turn: what costs extraction the most within the limits.
WORST_CASE_SHAPES = ("random", "one_pixel", "cluster")


@dataclass(frozen=True)
class Upload:
    """One telemetry file to upload: its name, bytes and media type, and whether it is fresh."""

    name: str
    body: bytes
    content_type: str
    fresh: bool


@dataclass(frozen=True)
class Record:
    """One request as the client saw it."""

    kind: str  # "upload", "search" or "candidate"
    #: "new" (201 upload, search computed now) or "stored" (200 upload of known content, search
    #: answered from the archive); None for candidates and errors.
    detail: str | None
    latency_s: float
    status: int  # HTTP status, 0 when no response came back
    error: str | None  # None when the status was the expected one


# ---------------------------------------------------------------------------
# The workload
# ---------------------------------------------------------------------------

def sample_uploads(sample_dir: Path = SAMPLE_DIR) -> list[Upload]:
    """The sample telemetry files (JSON and CSV, not the truth files)."""
    files = sorted(p for p in sample_dir.iterdir()
                   if p.suffix in (".json", ".csv") and not p.name.endswith(".truth.json"))
    return [Upload(p.name, p.read_bytes(), "text/csv" if p.suffix == ".csv" else "application/json", False)
            for p in files]


def fresh_uploads(n: int, seed: int) -> list[Upload]:
    """``n`` sequences simulated now with ``seed`` (cameras and scenarios in turn), as JSON files."""
    from app.simulate import camera_cycle, simulate_sequence
    from app.telemetry.formats import dump_json

    rng = np.random.default_rng(seed)
    uploads = []
    for i in range(n):
        scenario = FRESH_SCENARIOS[i % len(FRESH_SCENARIOS)]
        sequence, _truth = simulate_sequence(rng, camera_cycle(None, i), scenario,
                                             sequence_id=f"load-{seed}-{i:05d}")
        uploads.append(Upload(f"load-{i:05d}.json", dump_json(sequence).encode(), "application/json", True))
    return uploads


def worst_case_telemetry(seed: int, shape: str = "random", n_snapshots: int = 64, n_sources: int = 64) -> bytes:
    """A valid JSON telemetry file inside every limit that costs extraction the most.

    ``random``: sources uniform over the sensor, unrelated between snapshots
    (the rotation search finds ~900 candidate pairs per snapshot pair);
    ``one_pixel``: every source of every snapshot on one pixel (16 million
    same-pixel pairs without a bound); ``cluster``: all sources in a 50 px
    square (many short chords, many near neighbours).  ``seed`` makes each
    file different, so that a server never answers one from its archive.
    """
    rng = np.random.default_rng([seed, WORST_CASE_SHAPES.index(shape)])
    width, height = 752, 582
    if shape == "one_pixel":
        x0, y0 = rng.uniform(0, width - 1), rng.uniform(0, height - 1)
    else:
        x0, y0 = rng.uniform(0, width - 51), rng.uniform(0, height - 51)
    snapshots = []
    for i in range(n_snapshots):
        if shape == "random":
            xy = np.column_stack([rng.uniform(0, width - 1, n_sources), rng.uniform(0, height - 1, n_sources)])
        elif shape == "one_pixel":
            xy = np.tile([x0, y0], (n_sources, 1))
        else:
            xy = np.column_stack([rng.uniform(x0, x0 + 50, n_sources), rng.uniform(y0, y0 + 50, n_sources)])
        brightness = rng.uniform(0, 255, n_sources)
        snapshots.append({"index": i, "time": f"2021-06-01T00:{i // 60:02d}:{i % 60:02d}.000Z",
                          "sources": [{"x": round(float(x), 2), "y": round(float(y), 2), "brightness": round(float(b), 1)}
                                      for (x, y), b in zip(xy, brightness)]})
    return json.dumps({"format": "tubsat-snapshots/1", "sequence_id": f"worst-{shape}-{seed}",
                       "spacecraft": "HOSTILE", "camera": "tubsat-752x582-20deg",
                       "snapshots": snapshots}).encode()


class HostileFiles:
    """Thread-safe source of fresh worst-case files, shapes in turn."""

    def __init__(self, n: int, seed: int) -> None:
        self._files = [worst_case_telemetry(seed * 100_000 + i, WORST_CASE_SHAPES[i % len(WORST_CASE_SHAPES)])
                       for i in range(n)]
        self._lock = threading.Lock()

    def next(self) -> bytes | None:
        with self._lock:
            return self._files.pop() if self._files else None


class Workload:
    """Thread-safe source of uploads: fresh and sample files in turn, each fresh one used once."""

    def __init__(self, fresh: list[Upload], samples: list[Upload]) -> None:
        self._fresh = list(reversed(fresh))
        self._samples = samples
        self._turn = 0
        self._lock = threading.Lock()
        self.exhausted = threading.Event()

    def next(self) -> Upload | None:
        """The next file, or None once the fresh pool is used up (the run then stops)."""
        with self._lock:
            self._turn += 1
            if self._turn % 2 == 0:
                return self._samples[(self._turn // 2) % len(self._samples)]
            if not self._fresh:
                self.exhausted.set()
                return None
            return self._fresh.pop()


# ---------------------------------------------------------------------------
# The server process
# ---------------------------------------------------------------------------

# ---------------------------------------------------------------------------
# The clients
# ---------------------------------------------------------------------------

class Client:
    """One keep-alive HTTP/1.1 connection that reconnects after a failure."""

    def __init__(self, port: int) -> None:
        self._port = port
        self._connection: http.client.HTTPConnection | None = None

    def request(self, method: str, path: str, body: bytes | None = None,
                content_type: str | None = None) -> tuple[int, bytes, float]:
        """(status, body, latency in s); raises OSError / HTTPException on transport failures."""
        if self._connection is None:
            self._connection = http.client.HTTPConnection("127.0.0.1", self._port, timeout=REQUEST_TIMEOUT_S)
        headers = {"Content-Type": content_type} if content_type else {}
        t0 = time.perf_counter()
        try:
            self._connection.request(method, path, body=body, headers=headers)
            response = self._connection.getresponse()
            data = response.read()
        except (OSError, http.client.HTTPException):
            self.close()
            raise
        return response.status, data, time.perf_counter() - t0

    def close(self) -> None:
        if self._connection is not None:
            self._connection.close()
            self._connection = None


def _timed(client: Client, records: list[Record], kind: str, expected: tuple[int, ...], method: str,
           path: str, body: bytes | None = None, content_type: str | None = None) -> dict | None:
    """Send one request, append its record, return the JSON body when the status was expected."""
    t0 = time.perf_counter()
    try:
        status, data, latency = client.request(method, path, body, content_type)
    except (OSError, http.client.HTTPException) as exc:
        records.append(Record(kind, None, time.perf_counter() - t0, 0, f"{type(exc).__name__}: {exc}"))
        return None
    if status not in expected:
        records.append(Record(kind, None, latency, status, f"{method} {path} -> {status}: {data[:200]!r}"))
        return None
    try:
        doc = json.loads(data)
    except ValueError:
        records.append(Record(kind, None, latency, status,
                              f"{method} {path} -> {status} with a body that is not JSON"))
        return None
    detail = None
    if kind == "upload":
        detail = "new" if status == 201 else "stored"
    elif kind == "search":
        detail = "stored" if doc.get("reused") else "new"
    records.append(Record(kind, detail, latency, status, None))
    return doc


def client_loop(port: int, workload: Workload, stop_at: float, records: list[Record],
                think_s: float = 0.0, rng: np.random.Generator | None = None, search_port: int | None = None) -> None:
    """Upload, search, fetch candidate 1, pause, until ``stop_at`` (perf_counter) or the pool runs out.

    The pause (an operator looking at the result, a script's pacing) is
    uniform in [0.5, 1.5] x ``think_s``, and the first loop starts after a
    uniform [0, 1] x ``think_s`` so that the clients do not move in step.
    """
    rng = rng or np.random.default_rng()
    client = Client(port)
    viewer = client if search_port in (None, port) else Client(search_port)  # another server (--servers 2)
    try:
        time.sleep(min(max(0.0, stop_at - time.perf_counter()), rng.uniform(0.0, think_s)))
        first = True
        while time.perf_counter() < stop_at:
            if not first and think_s > 0:
                time.sleep(min(max(0.0, stop_at - time.perf_counter()), rng.uniform(0.5, 1.5) * think_s))
                if time.perf_counter() >= stop_at:
                    return
            first = False
            upload = workload.next()
            if upload is None:
                return
            doc = _timed(client, records, "upload", (200, 201), "POST",
                         f"/api/sequences?filename={upload.name}", upload.body, upload.content_type)
            if doc is None:
                continue
            seq_id = doc["id"]
            found = _timed(viewer, records, "search", (200,), "POST", f"/api/sequences/{seq_id}/search",
                           b"{}", "application/json")
            if found is None or not found.get("candidates"):
                continue  # nothing to show: an Earth or a too-sparse field
            _timed(viewer, records, "candidate", (200,), "GET", f"/api/sequences/{seq_id}/candidates/1")
    finally:
        client.close()
        viewer.close()


def hostile_loop(port: int, files: HostileFiles, stop_at: float, records: list[Record]) -> None:
    """Upload worst-case files back to back until ``stop_at``: 201 (stored) and 503 (busy) are expected."""
    client = Client(port)
    try:
        while time.perf_counter() < stop_at:
            body = files.next()
            if body is None:
                return
            t0 = time.perf_counter()
            try:
                status, data, latency = client.request("POST", "/api/sequences", body, "application/json")
            except (OSError, http.client.HTTPException) as exc:
                records.append(Record("hostile upload", None, time.perf_counter() - t0, 0,
                                      f"{type(exc).__name__}: {exc}"))
                continue
            ok = status in (200, 201, 503)
            detail = {201: "new", 200: "stored", 503: "busy"}.get(status)
            records.append(Record("hostile upload", detail, latency, status,
                                  None if ok else f"POST /api/sequences -> {status}: {data[:200]!r}"))
    finally:
        client.close()


@contextlib.contextmanager
def _archive(database: str | None, tmp_dir: Path):
    """The servers' archive: a SQLite file in ``tmp_dir``, or a fresh database made on the PostgreSQL
    server of ``database`` for this run and dropped after it."""
    if database is None:
        yield str(tmp_dir / "load.sqlite3")
        return
    import psycopg

    if not database.startswith(("postgresql://", "postgres://")):
        raise ValueError(f"--database takes a postgresql:// URL, not {database.split('://')[0]!r}")
    name = f"starid_load_{os.getpid()}_{int(time.time())}"
    try:
        admin = psycopg.connect(database, autocommit=True)
        admin.execute(f'CREATE DATABASE "{name}"')
    except psycopg.Error as exc:
        raise RuntimeError(f"cannot make a database for the run on {database.split('@')[-1]}: {exc}") from None
    try:
        parts = urllib.parse.urlsplit(database)
        yield urllib.parse.urlunsplit(parts._replace(path=f"/{name}"))
    finally:
        try:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        finally:
            admin.close()


# ---------------------------------------------------------------------------
# Figures
# ---------------------------------------------------------------------------

def percentile_ms(latencies_s: list[float], q: float) -> float | None:
    """Nearest-rank q-th percentile in ms: the ceil(q/100 * n)-th smallest latency."""
    if not latencies_s:
        return None
    ordered = sorted(latencies_s)
    rank = max(1, math.ceil(q / 100.0 * len(ordered)))
    return round(ordered[rank - 1] * 1000.0, 1)


def summarise(records: list[Record], duration_s: float) -> dict:
    """Counts, error messages and latency percentiles per request kind (and per new/stored detail)."""
    kinds = {}
    groups = [(kind, None) for kind in ("upload", "search", "candidate")]
    groups += [(kind, detail) for kind in ("upload", "search") for detail in ("new", "stored")]
    for kind, detail in groups:
        mine = [r for r in records if r.kind == kind and (detail is None or r.detail == detail)]
        name = kind if detail is None else f"{kind} ({detail})"
        latencies = [r.latency_s for r in mine if r.error is None]
        kinds[name] = {"requests": len(mine), "errors": sum(r.error is not None for r in mine),
                       "p50_ms": percentile_ms(latencies, 50), "p95_ms": percentile_ms(latencies, 95),
                       "max_ms": percentile_ms(latencies, 100),
                       "per_s": round(len(mine) / duration_s, 2) if duration_s > 0 else None}
    errors = [r.error for r in records if r.error is not None]
    return {"requests": len(records), "errors": len(errors), "error_examples": errors[:5], "by_kind": kinds}


def run(n_sequences: int = DEFAULT_SECONDS, seed: int = 1, clients: int = DEFAULT_CLIENTS,
        think_s: float = DEFAULT_THINK_S, adversarial: int = 0, servers: int = 1, database: str | None = None) -> dict:
    """Start the server, run ``clients`` client threads for ``n_sequences`` *seconds*, stop it.

    Each client pauses about ``think_s`` between its loops (0: none, the
    saturation test); ``adversarial`` more clients send worst-case files
    without pause.  (The bench command's ``--n`` is seconds for this suite.)
    Returns the figures of :func:`summarise` (ordinary clients) plus the
    hostile clients' figures, the set-up and whether the target held.
    Raises RuntimeError when the server cannot be started.
    """
    duration_s = float(n_sequences)
    if servers > 1 and database is None:
        raise ValueError("several servers share one archive: give --database postgresql://...")
    if duration_s <= 0 or clients < 1 or not think_s >= 0 or servers < 1:
        raise ValueError("the load benchmark needs a positive duration, at least one client and a "
                         "pause of zero or more seconds")
    n_fresh = fresh_needed(clients, duration_s, think_s)
    t0 = time.perf_counter()
    workload = Workload(fresh_uploads(n_fresh, seed), sample_uploads())
    hostile = HostileFiles(math.ceil(HOSTILE_FILES_PER_S * adversarial * duration_s), seed)
    prepare_s = time.perf_counter() - t0

    with tempfile.TemporaryDirectory(prefix="starid-load-") as tmp, _archive(database, Path(tmp)) as archive:
        tmp_dir = Path(tmp)
        log_path = tmp_dir / "server.log"
        ports = [free_port() for _ in range(servers)]
        processes = []
        try:
            for port in ports:
                processes.append(start_server(archive, port, log_path))
            t1 = time.perf_counter()
            for port, process in zip(ports, processes):
                wait_ready(port, process, log_path)
            startup_s = time.perf_counter() - t1
            port, process = ports[0], processes[0]
            records_per_client: list[list[Record]] = [[] for _ in range(clients)]
            hostile_records: list[list[Record]] = [[] for _ in range(adversarial)]
            start = time.perf_counter()
            threads = [threading.Thread(target=client_loop,
                                        args=(ports[i % servers], workload, start + duration_s, mine, think_s,
                                              np.random.default_rng([seed, i]), ports[(i + 1) % servers]),
                                        name=f"load-client-{i}", daemon=True)
                       for i, mine in enumerate(records_per_client)]
            threads += [threading.Thread(target=hostile_loop, args=(port, hostile, start + duration_s, mine),
                                         name=f"hostile-client-{i}", daemon=True)
                        for i, mine in enumerate(hostile_records)]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
            elapsed_s = time.perf_counter() - start
            server_alive = all(p.poll() is None for p in processes)
        finally:
            for p in processes:
                stop_server(p)
        server_log_tail = tail(log_path, 2000) if not server_alive else None

    records = [r for mine in records_per_client for r in mine]
    result = summarise(records, elapsed_s)
    search = result["by_kind"]["search"]
    hostile_done = [r for mine in hostile_records for r in mine]
    hostile_ok = [r.latency_s for r in hostile_done if r.error is None and r.status in (200, 201)]
    result["hostile"] = None if not adversarial else {
        "clients": adversarial, "uploads": len(hostile_done),
        "stored": sum(r.status == 201 for r in hostile_done), "busy_503": sum(r.status == 503 for r in hostile_done),
        "errors": sum(r.error is not None for r in hostile_done),
        "error_examples": [r.error for r in hostile_done if r.error is not None][:3],
        "stored_p50_ms": percentile_ms(hostile_ok, 50), "stored_p95_ms": percentile_ms(hostile_ok, 95),
        "max_ms": percentile_ms([r.latency_s for r in hostile_done if r.status], 100)}
    result.update(
        clients=clients, think_s=think_s, duration_s=round(elapsed_s, 1), seed=seed, fresh_pool=n_fresh,
        fresh_uploaded=n_fresh - len(workload._fresh), pool_exhausted=workload.exhausted.is_set(),
        prepare_s=round(prepare_s, 1), server_startup_s=round(startup_s, 1), server_survived=server_alive,
        servers=servers, database="postgresql" if database else "sqlite",
        server_log_tail=server_log_tail, cpu_count=os.cpu_count(),
        uploads_per_s=result["by_kind"]["upload"]["per_s"],
        target={"p95_search_ms": TARGET_P95_SEARCH_MS, "zero_errors": True},
        target_met=(result["errors"] == 0 and search["p95_ms"] is not None
                    and search["p95_ms"] <= TARGET_P95_SEARCH_MS and server_alive))
    return result


def format_table(result: dict) -> str:
    pause = (f"pausing ~{result['think_s']:g} s between loops" if result["think_s"] > 0
             else "without pause (saturation)")
    servers = (f"{result['servers']} servers on one {result['database']} archive"
               if result.get("servers", 1) > 1 else f"one server on {result.get('database', 'sqlite')}")
    lines = [f"{result['clients']} clients {pause}, {servers}, for {result['duration_s']} s on loopback "
             f"({result['cpu_count']} CPUs; server start {result['server_startup_s']} s; "
             f"{result['fresh_uploaded']} fresh simulated sequences of {result['fresh_pool']} prepared"
             f"{', POOL EXHAUSTED' if result['pool_exhausted'] else ''})",
             f"requests {result['requests']}, errors {result['errors']}, uploads/s {result['uploads_per_s']}",
             "",
             f"{'request':<16} {'count':>7} {'errors':>6} {'per s':>7} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8}"]
    for kind, k in result["by_kind"].items():
        cells = [("-" if v is None else f"{v}") for v in (k["per_s"], k["p50_ms"], k["p95_ms"], k["max_ms"])]
        lines.append(f"{kind:<16} {k['requests']:>7} {k['errors']:>6} {cells[0]:>7} {cells[1]:>8} "
                     f"{cells[2]:>8} {cells[3]:>8}")
    search_p95 = result["by_kind"]["search"]["p95_ms"]
    hostile = result.get("hostile")
    if hostile:
        lines.append("")
        lines.append(f"plus {hostile['clients']} hostile clients sending worst-case files (64 x 64 sources) "
                     f"without pause: {hostile['uploads']} uploads, {hostile['stored']} stored "
                     f"(p50 {hostile['stored_p50_ms']} ms, p95 {hostile['stored_p95_ms']} ms), "
                     f"{hostile['busy_503']} answered 503, {hostile['errors']} other errors; "
                     f"slowest answer {hostile['max_ms']} ms")
        for example in hostile["error_examples"]:
            lines.append(f"  hostile error: {example}")
    lines.append("")
    lines.append(f"target: 0 errors and p95 search <= {result['target']['p95_search_ms']:.0f} ms -> "
                 f"{'MET' if result['target_met'] else 'MISSED'} (p95 search {search_p95} ms)")
    for example in result["error_examples"]:
        lines.append(f"  error: {example}")
    if not result["server_survived"]:
        lines.append("the server process died during the run; its log ends with:")
        lines.append(result["server_log_tail"] or "")
    return "\n".join(lines)
