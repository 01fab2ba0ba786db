"""Peer benchmark: this project against cedar-solve (tetra3) on the same snapshots.

``python -m app bench --suite peer [--n N] [--seed S] [--json]``

The peer
--------
cedar-solve needs numpy < 2, so it lives in a virtual environment of its
own, never in the project's: made once from PyPI (``pip install
cedar-solve``) under ``~/.cache/starid/peer-venv`` (``$STARID_CACHE_DIR``'s
``peer-venv``) or at ``$STARID_PEER_VENV``, and reused while it imports.
When it cannot be made (no network, a failed build) the suite says why and
returns ``{"skipped": REASON}``: never a traceback, exit status 0.

The peer runs in ONE long-lived subprocess of that environment
(:mod:`app.bench.peer_runner`): JSON lines of centroids in, JSON lines with
its attitude and its own ``perf_counter`` time around
``Tetra3.solve_from_centroids`` out, so neither its start-up nor the pipe
is counted against it.  Its default database; ``fov_estimate`` the
camera's horizontal field of view and ``fov_max_error`` 2.5 % of it, 5 %
in the row whose focal length is 5 % off.  Every wait on it has a
time-out; a peer that hangs is killed and restarted (at most
:data:`MAX_PEER_RESTARTS` times).

Conventions at the boundary (:func:`to_tetra3_centroids`,
:func:`rotation_from_tetra3`): ours are x = column, y = row, (0, 0) the
centre of the top-left pixel, camera frame (+column, +row, boresight);
tetra3's centroids are (y, x) rows brightest first, measured from the
top-left *corner* (the top-left pixel's centre is (0.5, 0.5)), its pinhole
centred on (height/2, width/2), and its camera frame (boresight, left, up).
Our principal point is put on tetra3's centre, which for the built-in
cameras (cx = (width - 1)/2) is exactly the half-pixel shift.

Ours runs in this process: one :class:`~app.identification.Sky`, and
``perf_counter`` around :func:`~app.identification.solve_sequence` only
(extraction included; for 16-snapshot sequences also the sequence fit).
Warm-up answers each (not counted, :func:`warm_up_frames`) before the timed frames; the two are
interleaved frame by frame, so a slow spell of the machine hits both.

Rows: single snapshots (scenario "single") of the 20 deg 752 x 582 camera;
the same with the true focal length 5 % off (alternating in sign); 16-snapshot
sequences (scenario "nominal": ours on the whole sequence, the peer on its
middle snapshot); a field of few stars seen once (the middle snapshot of a
"sparse" sequence, 4-6 stars, for both: what a frame of the Earth's few blobs
looks like until it is searched, and what a search that gives up on few points
early does not identify); and two rows of frames in which no star is seen (10 random
points; the Earth in view), where the right answer is none and the goal is
the peer's time on the same frame.  Correct = boresight within 0.1 deg and roll within 0.5
deg of the truth; "claimed" = our status ``identified`` / the peer's
``MATCH_FOUND``; a wrong claim is a claimed answer that is not correct.
Our start-up (imports, index load and the first answer) is measured in a
fresh subprocess, three times.
"""

from __future__ import annotations

import collections
import contextlib
import json
import math
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

PEER_PACKAGE = "cedar-solve"
CAMERA_NAME = "tubsat-752x582-20deg"
#: ``fov_max_error`` as a fraction of ``fov_estimate``, and in the focal-error row.
FOV_MAX_ERROR = 0.025
FOCAL_ERROR = 0.05
#: tetra3's own give-up time per frame (its default).
PEER_SOLVE_TIMEOUT_MS = 5000
#: Our waits on the peer process: its first line (import + database), one answer, its exit.
READY_TIMEOUT_S = 120.0
ANSWER_TIMEOUT_S = 60.0
EXIT_TIMEOUT_S = 10.0
#: Making the environment: one pip step (Pillow may build from source), the import check.
INSTALL_TIMEOUT_S = 1800.0
CHECK_TIMEOUT_S = 120.0
MAX_PEER_RESTARTS = 3
STARTUP_RUNS = 3
MARKER = "starid-peer.json"
RUNNER = Path(__file__).with_name("peer_runner.py")

#: The speed goals, as ratios of ours to the peer's figure (or absolute limits).
GOAL_SINGLE_MEDIAN_RATIO = 0.5
GOAL_SINGLE_P95_RATIO = 1.0
GOAL_SINGLE_MAX_MS = 100.0
GOAL_SEQUENCE_MEDIAN_RATIO = 1.0
GOAL_STARTUP_S = 1.0
#: The first run after an install (no compiled kernel in the cache), start to first answer, seconds.
GOAL_FIRST_RUN_S = 15.0
#: A frame with no star: answered (nothing claimed) within the peer's time on the same frame, 95 % of them.
GOAL_NO_MATCH_RATIO = 1.0


class PeerUnavailable(Exception):
    """The peer's environment cannot be made or used; ``str(exc)`` says why, ``output`` is the step's output."""

    def __init__(self, message: str, output: str = ""):
        super().__init__(message)
        self.output = output


class PeerError(Exception):
    """The peer process broke the protocol or died."""


class PeerTimeout(PeerError):
    """The peer process did not answer in time (it has been killed)."""


# --- conventions at the boundary ----------------------------------------------

def tetra3_size(camera) -> tuple[int, int]:
    """tetra3's ``size``: (height, width)."""
    return int(camera.height), int(camera.width)


def to_tetra3_centroids(xy, brightness, camera) -> np.ndarray:
    """Our sources -> tetra3's centroids: (y, x) rows, brightest first, from the top-left corner.

    tetra3 puts the pinhole's centre at (height/2, width/2) and the top-left
    pixel's centre at (0.5, 0.5); we put it at (cy, cx) and (0, 0).  Each
    source is moved so that our principal point lands on tetra3's centre
    (for cx = (width - 1)/2, cy = (height - 1)/2 that is +0.5 px on both
    axes).  Ties in brightness keep the file order.
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    order = np.argsort(-np.asarray(brightness, dtype=float), kind="stable")
    height, width = tetra3_size(camera)
    x = xy[order, 0] - camera.cx + width / 2.0
    y = xy[order, 1] - camera.cy + height / 2.0
    return np.column_stack([y, x])


#: Our camera axes (+column, +row, boresight) in tetra3's (boresight, left, up).
_TETRA3_TO_OURS = np.array([[0.0, -1.0, 0.0],
                            [0.0, 0.0, -1.0],
                            [1.0, 0.0, 0.0]])


def tetra3_rotation(ra_deg: float, dec_deg: float, roll_deg: float) -> np.ndarray:
    """tetra3's rotation matrix (ICRS -> its camera frame) from the RA, Dec, Roll it reports.

    Its rows are the camera axes in ICRS: the boresight ``b``, "left" and
    "up".  Roll 0 has north up and east to the left; a positive roll turns
    them so that tetra3's own read-back (``ra = atan2(R01, R00)``,
    ``dec = atan2(R02, |R[1:3, 2]|)``, ``roll = atan2(R12, R22)``) gives the
    three angles again.
    """
    ra, dec, roll = np.radians([ra_deg, dec_deg, roll_deg])
    b = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    east = np.array([-math.sin(ra), math.cos(ra), 0.0])
    north = np.array([-math.sin(dec) * math.cos(ra), -math.sin(dec) * math.sin(ra), math.cos(dec)])
    left = math.cos(roll) * east + math.sin(roll) * north
    up = math.cos(roll) * north - math.sin(roll) * east
    return np.vstack([b, left, up])


def rotation_from_tetra3(ra_deg: float, dec_deg: float, roll_deg: float) -> np.ndarray:
    """The peer's answer as our rotation matrix (ICRS -> our camera frame, ``v_cam = R v_icrs``)."""
    return _TETRA3_TO_OURS @ tetra3_rotation(ra_deg, dec_deg, roll_deg)


def peer_request(snapshot, camera, fov_max_error_fraction: float = FOV_MAX_ERROR,
                 solve_timeout_ms: int = PEER_SOLVE_TIMEOUT_MS) -> dict:
    """The runner's request for one snapshot (without its ``id``)."""
    fov = float(camera.fov_deg[0])
    return {"centroids": to_tetra3_centroids(snapshot.xy, snapshot.brightness, camera).tolist(),
            "size": list(tetra3_size(camera)), "fov_estimate": fov,
            "fov_max_error": fov * fov_max_error_fraction, "solve_timeout_ms": solve_timeout_ms}


# --- the peer's environment -----------------------------------------------------

def peer_venv_dir() -> Path:
    """``$STARID_PEER_VENV``, else ``peer-venv`` in the project's cache folder (``~/.cache/starid``)."""
    explicit = os.environ.get("STARID_PEER_VENV")
    if explicit:
        return Path(explicit).expanduser()
    from app.config import settings

    return Path(settings().cache_dir) / "peer-venv"


def _clean_env() -> dict:
    """This process's environment without what would tie a child to the project's venv."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV",
                                                             "PYTHONSTARTUP", "PIP_REQUIRE_VIRTUALENV")}
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _venv_python(path: Path) -> Path:
    return path / "bin" / "python"


def _tail(text: str, lines: int = 3) -> str:
    """The last lines of a tool's output, its ``ERROR`` lines when it has some (pip's reasons)."""
    kept = [line.strip() for line in (text or "").strip().splitlines() if line.strip()]
    errors = [line for line in kept if line.startswith("ERROR")]
    return " | ".join((errors or kept)[-lines:]) or "(no output)"


def _run_step(argv: list[str], what: str, timeout: float, log) -> str:
    """Run one set-up step; its output is appended to ``log``; PeerUnavailable on failure."""
    try:
        done = subprocess.run(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True, timeout=timeout, env=_clean_env())
    except subprocess.TimeoutExpired as exc:
        out = exc.output.decode(errors="replace") if isinstance(exc.output, bytes) else (exc.output or "")
        log.write(out)
        raise PeerUnavailable(f"{what} did not finish within {timeout:.0f} s: {_tail(out)}", out) from None
    except OSError as exc:
        raise PeerUnavailable(f"{what} could not be started: {exc}") from None
    log.write(f"$ {' '.join(argv)}\n{done.stdout}\n")
    if done.returncode != 0:
        raise PeerUnavailable(f"{what} failed (exit {done.returncode}): {_tail(done.stdout)}", done.stdout)
    return done.stdout


def _check_env(path: Path) -> dict | None:
    """``version`` and ``numpy`` when the environment at ``path`` imports tetra3 with numpy < 2, else None."""
    python = _venv_python(path)
    if not python.exists():
        return None
    code = ("import json, numpy, tetra3; from importlib.metadata import version; "
            "print(json.dumps({'numpy': numpy.__version__, 'version': version('cedar-solve')}))")
    try:
        done = subprocess.run([str(python), "-I", "-c", code], stdin=subprocess.DEVNULL, capture_output=True,
                              text=True, timeout=CHECK_TIMEOUT_S, env=_clean_env())
        facts = json.loads(done.stdout.strip().splitlines()[-1]) if done.returncode == 0 else None
    except (subprocess.TimeoutExpired, OSError, ValueError, IndexError):
        return None
    if not facts or int(facts["numpy"].split(".")[0]) >= 2:
        return None
    return facts


def ensure_peer_env(path: Path | None = None, *, log=None) -> tuple[Path, dict]:
    """The peer environment's interpreter and facts (``version``, ``numpy``, ``made``), made if needed.

    Reused whenever it imports tetra3 with numpy < 2 (one made by hand
    too); otherwise (re)made, if the folder is missing, empty or marked as
    made here (a folder of someone else's is never deleted): ``python -m venv``, ``pip install cedar-solve``
    (and, should that fail for another reason than PyPI having no
    cedar-solve, e.g. its pinned Pillow not building: numpy < 2, scipy and a
    binary Pillow first, then cedar-solve without its pinned dependencies),
    the import checked, the marker written.  A lock file keeps two runs from making it at once.
    Raises :class:`PeerUnavailable` with the reason.
    """
    import fcntl

    path = Path(path) if path is not None else peer_venv_dir()
    log = log or (lambda message: print(message, file=sys.stderr, flush=True))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = open(path.parent / f".{path.name}.lock", "w")
    except OSError as exc:
        raise PeerUnavailable(f"cannot use {path}: {exc}") from None
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        facts = _check_env(path)
        if facts is not None:
            return _venv_python(path), {**facts, "made": False, "path": str(path)}
        if path.exists() and not (path / MARKER).exists() and any(path.iterdir()):
            raise PeerUnavailable(f"{path} is neither a working {PEER_PACKAGE} environment nor one this benchmark "
                                  "made, so it is left alone: remove it or set STARID_PEER_VENV to another folder")
        log(f"peer: making the virtual environment {path} with {PEER_PACKAGE} from PyPI (once; a few minutes)")
        t0 = time.perf_counter()
        shutil.rmtree(path, ignore_errors=True)
        path.mkdir(parents=True)
        (path / MARKER).write_text(json.dumps({"package": PEER_PACKAGE, "state": "making", "since": time.time()}))
        with tempfile.TemporaryFile("w+") as out:
            _run_step([sys.executable, "-m", "venv", str(path)], "making the virtual environment", CHECK_TIMEOUT_S, out)
            python = str(_venv_python(path))
            pip = [python, "-m", "pip", "install", "--disable-pip-version-check", "--no-input"]
            try:
                _run_step(pip + [PEER_PACKAGE], f"pip install {PEER_PACKAGE}", INSTALL_TIMEOUT_S, out)
            except PeerUnavailable as first:
                if f"No matching distribution found for {PEER_PACKAGE}" in first.output or "timed out" in str(first):
                    shutil.rmtree(path, ignore_errors=True)
                    raise  # PyPI unreachable or without the package: nothing else to try
                log(f"peer: {first}; trying numpy<2, scipy and a binary Pillow, then {PEER_PACKAGE} --no-deps")
                try:
                    _run_step(pip + ["numpy<2", "scipy", "pillow"], "pip install numpy<2 scipy pillow",
                              INSTALL_TIMEOUT_S, out)
                    _run_step(pip + ["--no-deps", PEER_PACKAGE], f"pip install --no-deps {PEER_PACKAGE}",
                              INSTALL_TIMEOUT_S, out)
                except PeerUnavailable as second:
                    shutil.rmtree(path, ignore_errors=True)
                    raise PeerUnavailable(f"{first}; then {second}") from None
            facts = _check_env(path)
            if facts is None:
                out.seek(0)
                detail = _tail(out.read())
                shutil.rmtree(path, ignore_errors=True)
                raise PeerUnavailable(f"{PEER_PACKAGE} installed but does not import with numpy < 2: {detail}")
            (path / MARKER).write_text(json.dumps({"package": PEER_PACKAGE, "state": "ready", "made": time.time(),
                                                   **facts}))
        log(f"peer: environment ready in {time.perf_counter() - t0:.0f} s "
            f"({PEER_PACKAGE} {facts['version']}, numpy {facts['numpy']})")
        return _venv_python(path), {**facts, "made": True, "path": str(path)}


# --- the long-lived peer process --------------------------------------------------

class PeerProcess:
    """One subprocess speaking the runner's JSON-lines protocol (see :mod:`app.bench.peer_runner`).

    ``argv`` starts it (the real peer: ``[venv python, "-I", peer_runner.py]``;
    the tests give a fake).  Every wait is bounded: ``ready_timeout`` for its
    first line, ``answer_timeout`` for each answer; a peer that misses one is
    killed and :class:`PeerTimeout` raised.  ``close`` asks it to quit, then
    terminates and finally kills it.
    """

    def __init__(self, argv: list[str], *, ready_timeout: float = READY_TIMEOUT_S,
                 answer_timeout: float = ANSWER_TIMEOUT_S, env: dict | None = None):
        self.argv = [str(a) for a in argv]
        self.ready_timeout = ready_timeout
        self.answer_timeout = answer_timeout
        self.env = env
        self.proc: subprocess.Popen | None = None
        self.ready: dict | None = None
        self._lines: queue.Queue = queue.Queue()
        self._stderr: collections.deque = collections.deque(maxlen=20)
        self._threads: list[threading.Thread] = []
        self._next_id = 0

    def __enter__(self) -> PeerProcess:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> dict:
        """Start the process and wait for its ``ready`` line (returned)."""
        try:
            self.proc = subprocess.Popen(self.argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         stderr=subprocess.PIPE, text=True, bufsize=1, env=self.env,
                                         start_new_session=True)
        except OSError as exc:
            raise PeerError(f"cannot start the peer ({self.argv[0]}): {exc}") from None
        self._threads = [threading.Thread(target=self._pump_stdout, daemon=True),
                         threading.Thread(target=self._pump_stderr, daemon=True)]
        for t in self._threads:
            t.start()
        ready = self._read(self.ready_timeout, "its ready line")
        if not ready.get("ready"):
            self.close()
            raise PeerError(f"the peer could not start: {ready.get('error') or ready}")
        self.ready = ready
        return ready

    def _pump_stdout(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            for line in self.proc.stdout:
                self._lines.put(line)
        self._lines.put(None)  # end of output: the peer exited or closed it

    def _pump_stderr(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            for line in self.proc.stderr:
                self._stderr.append(line)

    def _read(self, timeout: float, what: str) -> dict:
        try:
            line = self._lines.get(timeout=timeout)
        except queue.Empty:
            self.kill()
            raise PeerTimeout(f"the peer gave no {what} within {timeout:g} s (killed)") from None
        if line is None:
            self.close()
            raise PeerError(f"the peer exited (status {self.proc.returncode}) before {what}; "
                            f"stderr: {self.stderr_tail()}")
        try:
            obj = json.loads(line)
        except ValueError:
            self.kill()
            raise PeerError(f"the peer wrote something that is not a JSON line: {line[:200]!r}") from None
        if not isinstance(obj, dict):
            self.kill()
            raise PeerError(f"the peer wrote a JSON line that is not an object: {line[:200]!r}")
        return obj

    def solve(self, request: dict) -> dict:
        """Send one request (an ``id`` is added) and return its answer."""
        if self.proc is None or self.proc.poll() is not None:
            raise PeerError("the peer is not running")
        self._next_id += 1
        rid = self._next_id
        try:
            self.proc.stdin.write(json.dumps({**request, "id": rid}) + "\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError, ValueError):
            self.close()
            raise PeerError(f"the peer closed its input; stderr: {self.stderr_tail()}") from None
        answer = self._read(self.answer_timeout, f"answer to request {rid}")
        if answer.get("id") != rid:
            self.kill()
            raise PeerError(f"the peer answered request {answer.get('id')!r}, expected {rid}")
        if "error" in answer:
            raise PeerError(f"the peer could not serve request {rid}: {answer['error']}")
        return answer

    def stderr_tail(self) -> str:
        return _tail("".join(self._stderr))

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._join()

    def close(self) -> int | None:
        """Ask the peer to quit; terminate, then kill it if it does not.  Returns its exit status."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            with contextlib.suppress(BrokenPipeError, OSError, ValueError):
                self.proc.stdin.write(json.dumps({"cmd": "quit"}) + "\n")
                self.proc.stdin.flush()
            with contextlib.suppress(BrokenPipeError, OSError, ValueError):
                self.proc.stdin.close()
            try:
                self.proc.wait(timeout=EXIT_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.proc.terminate()
                try:
                    self.proc.wait(timeout=EXIT_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
        self._join()
        return self.proc.returncode

    def _join(self) -> None:
        for stream in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            with contextlib.suppress(OSError, ValueError):
                stream.close()
        for t in self._threads:
            t.join(timeout=EXIT_TIMEOUT_S)


class RestartingPeer:
    """A :class:`PeerProcess` restarted after a time-out or a crash, at most ``max_restarts`` times."""

    def __init__(self, argv: list[str], *, max_restarts: int = MAX_PEER_RESTARTS, **kwargs):
        self.argv, self.kwargs, self.max_restarts = argv, kwargs, max_restarts
        self.restarts = 0
        self.peer = PeerProcess(argv, **kwargs)
        self.ready = self.peer.start()

    def solve(self, request: dict) -> dict:
        """The peer's answer, or ``{"status": "TIMEOUT_KILLED" | "ERROR", "error": ...}``."""
        try:
            return self.peer.solve(request)
        except PeerTimeout as exc:
            status, error = "TIMEOUT_KILLED", str(exc)
        except PeerError as exc:
            if self.peer.proc is not None and self.peer.proc.poll() is None:
                return {"status": "ERROR", "error": str(exc)}  # one bad request; the peer goes on
            status, error = "ERROR", str(exc)
        if self.restarts >= self.max_restarts:
            raise PeerError(f"the peer failed {self.restarts + 1} times, last: {error}")
        self.restarts += 1
        self.peer.close()
        self.peer = PeerProcess(self.argv, **self.kwargs)
        self.peer.start()
        return {"status": status, "error": error}

    def close(self) -> None:
        self.peer.close()


# --- measuring -------------------------------------------------------------------------

def _pct(values, q) -> float | None:
    return round(float(np.percentile(values, q)), 2) if len(values) else None


def _timing(ms: list[float], prefix: str = "ms") -> dict:
    return {f"{prefix}_median": _pct(ms, 50), f"{prefix}_p95": _pct(ms, 95),
            f"{prefix}_max": round(float(np.max(ms)), 2) if ms else None,
            f"{prefix}_mean": round(float(np.mean(ms)), 2) if ms else None}


def _verdict(R_est, R_true) -> tuple[bool, float | None, float | None]:
    """(correct, boresight error, roll error in arcsec) of an answer (None: no answer); with no truth
    (``R_true`` None: no star in the frame) every answer is wrong."""
    from app.bench.identification import is_correct

    if R_est is None or R_true is None:
        return False, None, None
    return is_correct(np.asarray(R_est), np.asarray(R_true))


def _peer_rotation(answer: dict):
    if answer.get("status") != "MATCH_FOUND" or answer.get("ra_deg") is None:
        return None
    return rotation_from_tetra3(answer["ra_deg"], answer["dec_deg"], answer["roll_deg"])


def _summary(frames: list[SimpleNamespace], who: str) -> dict:
    """Timing and correctness of one tool over the frames (``frames[i].<who>``: ms, claimed, correct)."""
    rows = [getattr(f, who) for f in frames]
    eligible = [r for r, f in zip(rows, frames) if f.eligible]
    cpu = [r.cpu_ms for r in rows if r.cpu_ms is not None]
    out = {"n": len(rows), **_timing([r.ms for r in rows]), **_timing(cpu, "cpu_ms"),
           "claimed": sum(r.claimed for r in rows),
           "correct": sum(r.claimed and r.correct for r in rows),
           "correct_fraction": round(sum(r.claimed and r.correct for r in rows) / len(rows), 4) if rows else None,
           "eligible": len(eligible),
           "correct_fraction_eligible": (round(sum(r.claimed and r.correct for r in eligible) / len(eligible), 4)
                                         if eligible else None),
           "wrong_claimed": sum(r.claimed and not r.correct for r in rows),
           "not_solved": sum(not r.claimed for r in rows),
           "boresight_err_arcsec_median": _pct([r.bore for r in rows if r.claimed and r.correct], 50),
           "roll_err_arcsec_median": _pct([r.roll for r in rows if r.claimed and r.correct], 50)}
    if who == "ours":
        out["top1_correct_any_status"] = sum(r.top1 for r in rows)
    else:
        out["statuses"] = dict(collections.Counter(r.status for r in rows))
        out["round_trip_ms_median"] = _pct([r.round_trip_ms for r in rows], 50)
    return out


def _ours(sky, sequence, R_true) -> SimpleNamespace:
    from app.identification import IDENTIFIED, solve_sequence

    c0, t0 = time.process_time(), time.perf_counter()
    solved = solve_sequence(sequence, sky)
    ms = (time.perf_counter() - t0) * 1000.0
    cpu_ms = (time.process_time() - c0) * 1000.0
    cands = solved.solution.candidates
    R_ref_true = None if R_true is None else R_true[solved.extraction.reference]
    top1, bore, roll = _verdict(cands[0].rotation_matrix if cands else None, R_ref_true)
    claimed = solved.solution.status == IDENTIFIED
    return SimpleNamespace(ms=ms, cpu_ms=cpu_ms, claimed=claimed, correct=top1, top1=top1, bore=bore, roll=roll,
                           status=solved.solution.status, extraction=solved.extraction)


def _theirs(peer: RestartingPeer, snapshot, camera, R_true, fov_max_error: float) -> SimpleNamespace:
    t0 = time.perf_counter()
    answer = peer.solve(peer_request(snapshot, camera, fov_max_error))
    round_trip = (time.perf_counter() - t0) * 1000.0
    # A frame the peer was killed on (or could not serve) counts with the time it took us to find out.
    ms = float(answer["solve_ms"]) if answer.get("solve_ms") is not None else round_trip
    R = _peer_rotation(answer)
    correct, bore, roll = _verdict(R, R_true)
    return SimpleNamespace(ms=ms, cpu_ms=answer.get("cpu_ms"), round_trip_ms=round_trip, claimed=R is not None,
                           correct=correct, bore=bore, roll=roll, status=answer.get("status"))


def middle_snapshot(sequence, truth):
    """A sequence's middle snapshot as a one-snapshot sequence, with its truth."""
    from dataclasses import replace

    middle = len(sequence.snapshots) // 2
    one = replace(sequence, snapshots=(replace(sequence.snapshots[middle], index=0),))
    return one, {**truth, **{key: [truth[key][middle]] for key in ("rotation_matrices", "sources", "times")}}


def run_row(sky, peer: RestartingPeer, label: str, scenario: str, n: int, seed: int, focal_error: float = 0.0,
            fov_max_error: float = FOV_MAX_ERROR, middle_only: bool = False) -> dict:
    """``n`` simulated frames (or sequences), ours and the peer's interleaved; ``middle_only``: each
    sequence's middle snapshot alone, for both (a field of few stars seen once)."""
    from app.bench.identification import _star_sources, _tracked_stars
    from app.camera import CAMERAS
    from app.simulate import simulate_sequence, true_optics

    camera = CAMERAS[CAMERA_NAME]
    rng = np.random.default_rng([seed, 16, int(focal_error * 1000), scenario == "single"] + [2] * middle_only)
    frames = []
    for i in range(n):
        sign = 1 if i % 2 == 0 else -1
        true_camera = true_optics(camera, focal_error=sign * focal_error) if focal_error else None
        sequence, truth = simulate_sequence(rng, camera, scenario, true_camera=true_camera)
        if middle_only:
            sequence, truth = middle_snapshot(sequence, truth)
        R_true = [np.asarray(R) for R in truth["rotation_matrices"]]
        middle = len(sequence.snapshots) // 2
        ours = _ours(sky, sequence, R_true)
        theirs = _theirs(peer, sequence.snapshots[middle], camera, R_true[middle], fov_max_error)
        eligible = (_star_sources(sequence, truth) >= 5 if len(sequence.snapshots) == 1
                    else _tracked_stars(ours.extraction, truth) >= 4)
        del ours.extraction
        frames.append(SimpleNamespace(ours=ours, peer=theirs, eligible=eligible))
    return {"label": label, "scenario": scenario, "focal_error": focal_error,
            "fov_max_error_fraction": fov_max_error,
            "ours": _summary(frames, "ours"), "peer": _summary(frames, "peer")}


def _no_match_frame(rng, camera, kind: str):
    """One snapshot in which no star is seen: ``"noise"``, 10 points scattered uniformly over the sensor with
    random brightness (hot pixels, noise); ``"earth"``, the middle snapshot of a simulated Earth-in-view
    sequence (bright drifting blobs), drawn again until it has at least 3 sources (fewer is answered at once
    by both tools).  A one-snapshot :class:`~app.telemetry.Sequence`."""
    from dataclasses import replace

    from app.simulate import simulate_sequence

    while True:
        one, _ = middle_snapshot(*simulate_sequence(rng, camera, "single" if kind == "noise" else "earth"))
        (snapshot,) = one.snapshots
        if kind == "noise":
            xy = rng.uniform([0.0, 0.0], [camera.width - 1.0, camera.height - 1.0], size=(10, 2))
            snapshot = replace(snapshot, xy=xy, brightness=rng.uniform(50.0, 250.0, size=10))
        if snapshot.n_sources >= 3:
            return replace(one, snapshots=(snapshot,))


def warm_up_frames(camera, seed: int) -> list:
    """One frame of each row's kind, none of them timed: a nominal sequence, a single snapshot, one seen 5 % long,
    a sparse field's middle snapshot, 10 random points and the Earth in view.

    Besides each process's first calls, a search pays once per install for what it keeps on disk at first use:
    the bright triangles (~70 ms, the first frame whose first edge does not settle) and a cell map for each new
    check radius (30-50 ms, :meth:`app.identification.Sky.near_star_cells`). The rows time a search as it runs
    after that."""
    from app.simulate import simulate_sequence, true_optics

    rng = np.random.default_rng([seed, 16, 7])
    nominal, _ = simulate_sequence(rng, camera, "nominal")
    single, _ = simulate_sequence(rng, camera, "single")
    long, _ = simulate_sequence(rng, camera, "single", true_camera=true_optics(camera, focal_error=FOCAL_ERROR))
    sparse, _ = middle_snapshot(*simulate_sequence(rng, camera, "sparse"))
    return [nominal, single, long, sparse, _no_match_frame(rng, camera, "noise"), _no_match_frame(rng, camera, "earth")]


def run_no_match_row(sky, peer: RestartingPeer, label: str, kind: str, n: int, seed: int) -> dict:
    """``n`` frames in which no star is seen (:func:`_no_match_frame`), ours and the peer's interleaved:
    right = nothing claimed."""
    from app.camera import CAMERAS

    camera = CAMERAS[CAMERA_NAME]
    rng = np.random.default_rng([seed, 16, 99, kind == "noise"])
    frames = []
    for _ in range(n):
        sequence = _no_match_frame(rng, camera, kind)
        ours = _ours(sky, sequence, None)
        theirs = _theirs(peer, sequence.snapshots[0], camera, None, FOV_MAX_ERROR)
        del ours.extraction
        frames.append(SimpleNamespace(ours=ours, peer=theirs, eligible=True))
    per_frame = [f.ours.ms / max(f.peer.ms, 1e-3) for f in frames]
    return {"label": label, "scenario": kind, "focal_error": 0.0, "fov_max_error_fraction": FOV_MAX_ERROR,
            "no_stars": True, "ours": _summary(frames, "ours"), "peer": _summary(frames, "peer"),
            "per_frame_ratio_median": _pct(per_frame, 50), "per_frame_ratio_p95": _pct(per_frame, 95),
            "ours_within_peer_time": sum(r <= 1.0 for r in per_frame)}


_STARTUP_CODE = """
import json, sys, time
t0 = time.perf_counter()
from app.identification import Sky, solve_sequence
from app.telemetry import load_telemetry_file
t1 = time.perf_counter()
sky = Sky()
t2 = time.perf_counter()
solved = solve_sequence(load_telemetry_file(sys.argv[1]), sky)
t3 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "index_load_s": t2 - t1, "first_answer_s": t3 - t2,
                  "status": solved.solution.status, "answered_at": time.time()}))
"""


def measure_startup(seed: int, runs: int = STARTUP_RUNS) -> dict:
    """Our warm start in a fresh interpreter: imports, index load (Sky) and the first answer.

    ``answer_s`` is the time from the subprocess's launch to its answer
    (interpreter start, imports, index, the first sequence solved: what a
    user waits for), ``total_s`` its whole wall time (the interpreter's
    teardown after the answer included: ~0.15 s, freeing numba's compiled
    code and the arrays), ``cpu_s`` its CPU time (less moved by other work
    on a shared machine); the median and the worst of ``runs`` runs.  Warm as a user's second run
    is: a first run, not counted (``first_run_s``), leaves every cache warm -
    the index, the compiled kernels (it compiles them when their code
    changed), and Python's bytecode, which an install compiles or a first run
    writes.  The bytecode goes to a temporary directory
    (``PYTHONPYCACHEPREFIX``), so that a ``PYTHONDONTWRITEBYTECODE`` in the
    environment (this workplace's) does not make every run compile the
    program's source again (0.1 s of each start, measured).

    Then the first run after an install, once: the same program with an
    empty kernel cache (a ``NUMBA_CACHE_DIR`` of its own; the index cache is
    kept, as an install that has built it once): ``install_run_s`` (wall,
    start to first answer), ``install_cpu_s`` (its processes' CPU, the
    compile helpers' included) and the one line it logged.
    """
    import resource

    from app.camera import CAMERAS
    from app.simulate import simulate_sequence
    from app.telemetry.formats import dump_json

    def children_cpu_s() -> float:
        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        return usage.ru_utime + usage.ru_stime

    sequence, _ = simulate_sequence(np.random.default_rng([seed, 16, 99]), CAMERAS[CAMERA_NAME], "nominal")
    runs_out = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "startup.json"
        path.write_text(dump_json(sequence))
        repo = Path(__file__).resolve().parents[2]
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        env["PYTHONPYCACHEPREFIX"] = str(Path(tmp) / "bytecode")
        for _ in range(runs + 1):
            runs_out.append(_run_startup(path, repo, env, children_cpu_s))
        install = _run_startup(path, repo, {**env, "NUMBA_CACHE_DIR": str(Path(tmp) / "empty-kernel-cache")},
                               children_cpu_s)
    first, runs_out = runs_out[0], runs_out[1:]
    good = [r for r in runs_out if "error" not in r]
    out = {"first_run_s": round(first["total_s"], 3) if "total_s" in first else first.get("error"),
           "runs": [{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()} for r in runs_out]}
    out.update(install_run_s=round(install["answer_s"], 2) if "answer_s" in install else None,
               install_cpu_s=round(install["cpu_s"], 1) if "cpu_s" in install else None,
               install_said=install.get("said") or install.get("error"))
    for key in ("import_s", "index_load_s", "first_answer_s", "answer_s", "total_s", "cpu_s"):
        values = [r[key] for r in good]
        out[f"{key}_median"] = round(float(np.median(values)), 3) if values else None
        out[f"{key}_max"] = round(float(np.max(values)), 3) if values else None
    return out


def _run_startup(path: Path, repo: Path, env: dict, children_cpu_s) -> dict:
    """One fresh process of :data:`_STARTUP_CODE` on ``path``: its report with ``total_s`` (wall) and
    ``cpu_s``, and ``said`` (the kernels' warm-up line it logged), or ``{"error": ...}``."""
    t0, cpu0, launched = time.perf_counter(), children_cpu_s(), time.time()
    try:
        done = subprocess.run([sys.executable, "-c", _STARTUP_CODE, str(path)], capture_output=True,
                              text=True, timeout=300, cwd=repo, env=env)
    except subprocess.TimeoutExpired:
        return {"error": "no answer within 300 s"}
    total, cpu = time.perf_counter() - t0, children_cpu_s() - cpu0
    if done.returncode != 0:
        return {"error": _tail(done.stderr)}
    said = [line for line in done.stderr.splitlines() if "numba kernels" in line]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    return {**report, "answer_s": report.pop("answered_at") - launched, "total_s": total, "cpu_s": cpu,
            "said": said[-1].strip() if said else None}


def _ratio(a, b) -> float | None:
    return round(a / b, 3) if a is not None and b else None


def run(n_sequences: int = 100, seed: int = 1) -> dict:
    """The peer suite; ``{"skipped": REASON}`` when the peer's environment cannot be made or started."""
    from app.camera import CAMERAS

    t0 = time.perf_counter()
    try:
        python, facts = ensure_peer_env()
    except PeerUnavailable as exc:
        reason = f"cedar-solve environment unavailable: {exc}"
        print(f"peer: skipped: {reason}", file=sys.stderr)
        return {"skipped": reason}
    env_s = time.perf_counter() - t0

    from app.identification import Sky, solve_sequence

    load_before = round(os.getloadavg()[0], 2)
    camera = CAMERAS[CAMERA_NAME]
    sky = Sky()
    try:
        peer = RestartingPeer([str(python), "-I", str(RUNNER)], env=_clean_env())
    except PeerError as exc:
        reason = f"cedar-solve could not be started: {exc}"
        print(f"peer: skipped: {reason}", file=sys.stderr)
        return {"skipped": reason}
    try:
        # Warm-up (not counted): both pay their first-call costs on frames of their own, one of each row's kind.
        for warm in warm_up_frames(camera, seed):
            solve_sequence(warm, sky)
            peer.solve(peer_request(warm.snapshots[len(warm.snapshots) // 2], camera))
        rows = [run_row(sky, peer, "single snapshot", "single", n_sequences, seed),
                run_row(sky, peer, "single, focal length 5 % off", "single", n_sequences, seed,
                        focal_error=FOCAL_ERROR, fov_max_error=FOCAL_ERROR),
                run_row(sky, peer, "16-snapshot sequence", "nominal", n_sequences, seed),
                run_row(sky, peer, "few stars: a sparse field", "sparse", n_sequences, seed, middle_only=True),
                run_no_match_row(sky, peer, "no star: 10 random points", "noise", n_sequences, seed),
                run_no_match_row(sky, peer, "no star: the Earth in view", "earth", n_sequences, seed)]
    except PeerError as exc:
        reason = f"cedar-solve failed during the run: {exc}"
        print(f"peer: skipped: {reason}", file=sys.stderr)
        return {"skipped": reason}
    finally:
        peer.close()
    startup = measure_startup(seed)
    single, sequence = rows[0], rows[2]
    no_star = [row for row in rows if row.get("no_stars")]
    fov = float(camera.fov_deg[0])
    ratios = {
        "single_median": _ratio(single["ours"]["ms_median"], single["peer"]["ms_median"]),
        "single_p95": _ratio(single["ours"]["ms_p95"], single["peer"]["ms_p95"]),
        "single_max": _ratio(single["ours"]["ms_max"], single["peer"]["ms_max"]),
        "sequence_median_vs_peer_single_median": _ratio(sequence["ours"]["ms_median"], single["peer"]["ms_median"]),
        "sequence_p95_vs_peer_single_median": _ratio(sequence["ours"]["ms_p95"], single["peer"]["ms_median"]),
        # The same in CPU time (process_time): far less moved by other work on the machine.
        "single_median_cpu": _ratio(single["ours"]["cpu_ms_median"], single["peer"]["cpu_ms_median"]),
        "single_p95_cpu": _ratio(single["ours"]["cpu_ms_p95"], single["peer"]["cpu_ms_p95"]),
        "sequence_median_vs_peer_single_median_cpu": _ratio(sequence["ours"]["cpu_ms_median"],
                                                            single["peer"]["cpu_ms_median"]),
    }
    goals = {
        "single_median_le_0.5x_peer": ratios["single_median"] is not None
        and ratios["single_median"] <= GOAL_SINGLE_MEDIAN_RATIO,
        "single_p95_le_1x_peer_p95": ratios["single_p95"] is not None and ratios["single_p95"] <= GOAL_SINGLE_P95_RATIO,
        "single_max_le_100ms": single["ours"]["ms_max"] is not None and single["ours"]["ms_max"] <= GOAL_SINGLE_MAX_MS,
        "sequence_median_le_1x_peer_single_median": ratios["sequence_median_vs_peer_single_median"] is not None
        and ratios["sequence_median_vs_peer_single_median"] <= GOAL_SEQUENCE_MEDIAN_RATIO,
        "startup_le_1s": startup["answer_s_max"] is not None and startup["answer_s_max"] <= GOAL_STARTUP_S,
        "first_run_after_install_le_15s": startup["install_run_s"] is not None
        and startup["install_run_s"] <= GOAL_FIRST_RUN_S,
        "no_star_p95_per_frame_le_1x_peer": all(row["per_frame_ratio_p95"] is not None
                                                and row["per_frame_ratio_p95"] <= GOAL_NO_MATCH_RATIO
                                                and row["ours"]["claimed"] == 0 for row in no_star),
    }
    return {"peer": {"package": PEER_PACKAGE, "version": facts.get("version"), "numpy": facts.get("numpy"),
                     "venv": facts.get("path"), "venv_made_now": facts.get("made"),
                     "venv_ready_s": round(env_s, 1),
                     "import_s": round(peer.ready.get("import_s", float("nan")), 3),
                     "database_load_s": round(peer.ready.get("load_s", float("nan")), 3),
                     "restarts": peer.restarts},
            "camera": CAMERA_NAME, "fov_estimate_deg": round(fov, 4),
            "fov_max_error_deg": round(fov * FOV_MAX_ERROR, 4), "n": n_sequences, "seed": seed,
            "rows": rows, "ratios": ratios, "startup": startup, "goals": goals,
            # Other work on this 2-core machine slows both tools: the 1-minute load average around the run.
            "load_average_before": load_before, "load_average_after": round(os.getloadavg()[0], 2)}


def format_table(result: dict) -> str:
    if "skipped" in result:
        return f"skipped: {result['skipped']}"

    def f(v, fmt=".1f"):
        return "-" if v is None else format(v, fmt)

    p = result["peer"]
    lines = [f"peer: {p['package']} {p['version']} (numpy {p['numpy']}, default database) in {p['venv']}, "
             f"one subprocess (import {p['import_s']:.2f} s, database {p['database_load_s']:.2f} s, "
             f"restarts {p['restarts']}); its own perf_counter around solve_from_centroids",
             f"camera {result['camera']}: fov_estimate {result['fov_estimate_deg']:.3f} deg, fov_max_error "
             f"{result['fov_max_error_deg']:.3f} deg (2.5 %); n = {result['n']} per row, seed {result['seed']}; "
             f"load average {result['load_average_before']} before, {result['load_average_after']} after (2 cores)",
             "",
             f"{'row':<30} {'tool':<12} {'ms50':>7} {'ms95':>7} {'max':>7} {'mean':>7} {'correct':>8} "
             f"{'(elig)':>8} {'wrong':>6} {'unsolved':>8} {'bore50':>7} {'roll50':>7} {'cpu50':>7} {'cpu95':>7}"]
    for row in result["rows"]:
        for who, name in (("ours", "ours"), ("peer", "cedar-solve")):
            s = row[who]
            # A frame without stars is answered right when nothing is claimed.
            right = 1 - s["claimed"] / s["n"] if row.get("no_stars") else s["correct_fraction"]
            lines.append(f"{row['label']:<30} {name:<12} {f(s['ms_median']):>7} {f(s['ms_p95']):>7} "
                         f"{f(s['ms_max']):>7} {f(s['ms_mean']):>7} {f(right, '.3f'):>8} "
                         f"{f(right if row.get('no_stars') else s['correct_fraction_eligible'], '.3f'):>8} "
                         f"{s['wrong_claimed']:>6} "
                         f"{s['not_solved']:>8} {f(s['boresight_err_arcsec_median']):>7} "
                         f"{f(s['roll_err_arcsec_median']):>7} {f(s['cpu_ms_median']):>7} {f(s['cpu_ms_p95']):>7}")
        o, q = row["ours"], row["peer"]
        lines.append(f"{'':<30} {'ours/peer':<12} {f(_ratio(o['ms_median'], q['ms_median']), '.2f'):>7} "
                     f"{f(_ratio(o['ms_p95'], q['ms_p95']), '.2f'):>7} {f(_ratio(o['ms_max'], q['ms_max']), '.2f'):>7} "
                     f"{f(_ratio(o['ms_mean'], q['ms_mean']), '.2f'):>7} {'':>8} {'':>8} {'':>6} {'':>8} {'':>7} "
                     f"{'':>7} {f(_ratio(o['cpu_ms_median'], q['cpu_ms_median']), '.2f'):>7} "
                     f"{f(_ratio(o['cpu_ms_p95'], q['cpu_ms_p95']), '.2f'):>7}")
    lines.append("(correct: claimed and within 0.1 deg / 0.5 deg roll of the truth, over all frames and over "
                 "eligible ones: >= 5 stars in a single snapshot, >= 4 tracked stars in a sequence; wrong: claimed "
                 "but not correct; bore50, roll50: median errors of the correct answers, arcsec; cpu50, cpu95: CPU time "
                 "(process_time) over the same call, less moved by other work on the machine; 16-snapshot rows: ours = extraction + identification + sequence fit of the "
                 "sequence, the peer = its middle snapshot; the few-star row: both tools on the middle snapshot of a "
                 "sparse sequence (4-6 stars); the 5 % row gives the peer fov_max_error 5 %; "
                 "no-star rows: correct = nothing claimed, wrong = a claim)")
    for row in result["rows"]:
        if row.get("no_stars"):
            lines.append(f"{row['label']}: ours / the peer's time on the same frame, median "
                         f"{f(row['per_frame_ratio_median'], '.2f')}x, p95 {f(row['per_frame_ratio_p95'], '.2f')}x; "
                         f"within the peer's time on {row['ours_within_peer_time']} of {row['ours']['n']} frames")
    r, s = result["ratios"], result["startup"]
    lines += ["",
              f"16-snapshot sequence (ours) vs the peer's single-frame median: median "
              f"{f(r['sequence_median_vs_peer_single_median'], '.2f')}x, p95 "
              f"{f(r['sequence_p95_vs_peer_single_median'], '.2f')}x (CPU time: median "
              f"{f(r['sequence_median_vs_peer_single_median_cpu'], '.2f')}x)",
              f"our start-up in a fresh process (median / worst of {len(s['runs'])}): to the first answer "
              f"{f(s['answer_s_median'], '.2f')} / {f(s['answer_s_max'], '.2f')} s = interpreter start + imports "
              f"{f(s['import_s_median'], '.2f')} s + index load {f(s['index_load_s_median'], '.2f')} s + first answer "
              f"{f(s['first_answer_s_median'], '.2f')} s; the process ends at {f(s['total_s_median'], '.2f')} / "
              f"{f(s['total_s_max'], '.2f')} s",
              f"the first run after an install (no compiled kernel cached): {f(s['install_run_s'], '.1f')} s to the "
              f"first answer, {f(s['install_cpu_s'], '.1f')} s of CPU; it said: {s['install_said']}",
              "speed goals: " + ", ".join(f"{k} {'met' if v else 'NOT met'}" for k, v in result["goals"].items())]
    return "\n".join(lines)
