"""The peer's side of ``bench --suite peer``: cedar-solve (tetra3) answering JSON lines.

This script runs in the peer's own virtual environment (cedar-solve needs
numpy < 2), never in the project's: it imports nothing from ``app`` and only
the standard library besides ``tetra3``.  :mod:`app.bench.peer` starts it
once, as ``PYTHON -I peer_runner.py`` (``-I``: the script's folder, full of
the project's modules, is not put on ``sys.path``), and keeps it for the
whole run, so the peer's start-up and the pipe are not counted against it.

Protocol, one JSON object per line each way:

* first the runner writes ``{"ready": true, "peer": ..., "version": ...,
  "import_s": ..., "load_s": ...}`` once its database is loaded (or
  ``{"ready": false, "error": "..."}`` and exits 1);
* each request ``{"id": K, "centroids": [[y, x], ...], "size": [height,
  width], "fov_estimate": DEG, "fov_max_error": DEG, "solve_timeout_ms": MS}``
  (centroids in tetra3's convention, brightest first) gets one answer
  ``{"id": K, "status": "MATCH_FOUND" | "NO_MATCH" | "TIMEOUT" | "TOO_FEW" |
  ..., "ra_deg", "dec_deg", "roll_deg", "fov_deg", "matches", "prob",
  "solve_ms", "cpu_ms", "t_solve_ms"}``: ``solve_ms`` is ``perf_counter``
  around ``solve_from_centroids`` only, ``cpu_ms`` the process's CPU time
  (``process_time``) over the same call, ``t_solve_ms`` tetra3's own figure; the
  attitude keys are null without a match.  A request it cannot serve gets
  ``{"id": K, "error": "..."}`` and the runner goes on;
* ``{"cmd": "quit"}`` or the end of its input ends it (exit 0).
"""

import json
import math
import sys
import time

STATUS_NAMES = {1: "MATCH_FOUND", 2: "NO_MATCH", 3: "TIMEOUT", 4: "CANCELLED", 5: "TOO_FEW"}


def _number(value):
    """A JSON-safe float (None for None, NaN or infinity)."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _send(obj) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


def _answer(solver, request: dict) -> dict:
    centroids = request["centroids"]
    size = tuple(int(v) for v in request["size"])
    kwargs = {"fov_estimate": request.get("fov_estimate"), "fov_max_error": request.get("fov_max_error"),
              "solve_timeout": request.get("solve_timeout_ms", 5000)}
    import numpy as np

    array = np.asarray(centroids, dtype=float).reshape(-1, 2)
    c0, t0 = time.process_time(), time.perf_counter()
    result = solver.solve_from_centroids(array, size, **kwargs)
    solve_ms = (time.perf_counter() - t0) * 1000.0
    cpu_ms = (time.process_time() - c0) * 1000.0
    status = result.get("status")
    return {"id": request.get("id"), "status": STATUS_NAMES.get(status, str(status)),
            "ra_deg": _number(result.get("RA")), "dec_deg": _number(result.get("Dec")),
            "roll_deg": _number(result.get("Roll")), "fov_deg": _number(result.get("FOV")),
            "matches": result.get("Matches"), "prob": _number(result.get("Prob")),
            "solve_ms": solve_ms, "cpu_ms": cpu_ms, "t_solve_ms": _number(result.get("T_solve"))}


def main() -> int:
    t0 = time.perf_counter()
    try:
        import logging

        logging.disable(logging.INFO)  # tetra3 logs every load and solve at INFO/DEBUG
        import tetra3
        t1 = time.perf_counter()
        solver = tetra3.Tetra3()  # the default database shipped in the wheel
        t2 = time.perf_counter()
    except Exception as exc:  # noqa: BLE001 - any failure is reported to the parent, not raised
        _send({"ready": False, "error": f"{type(exc).__name__}: {exc}"})
        return 1
    try:
        from importlib.metadata import version
        peer_version = version("cedar-solve")
    except Exception:  # noqa: BLE001 - the version is informative only
        peer_version = None
    import numpy

    _send({"ready": True, "peer": "cedar-solve", "version": peer_version, "numpy": numpy.__version__,
           "import_s": t1 - t0, "load_s": t2 - t1})
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        try:
            request = json.loads(line)
        except ValueError as exc:
            _send({"id": None, "error": f"bad request line: {exc}"})
            continue
        if request.get("cmd") == "quit":
            break
        try:
            _send(_answer(solver, request))
        except Exception as exc:  # noqa: BLE001 - one bad request must not end the run
            _send({"id": request.get("id"), "error": f"{type(exc).__name__}: {exc}"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
