"""The peer's side of ``bench --suite frames``: cedar-solve's centroiding + solving on whole images.

Runs in the peer's own environment (see :mod:`app.bench.peer`, whose environment it reuses),
imports nothing from ``app``, started once as ``PYTHON -I peer_frames_runner.py``.  The
protocol is :mod:`app.bench.peer_runner`'s (JSON lines; a ``ready`` line first; ``{"cmd":
"quit"}`` ends it), with requests ``{"id", "image": PATH of a .npy array (rows from the top),
"size": [height, width], "fov_estimate": DEG, "fov_max_error": DEG, "solve_timeout_ms": MS,
"max_returned": N}`` answered by ``{"id", "status", "ra_deg", "dec_deg", "roll_deg", "fov_deg",
"matches", "n_centroids", "centroid_ms", "solve_ms"}``: ``centroid_ms`` is ``perf_counter``
around ``tetra3.get_centroids_from_image`` (its defaults), ``solve_ms`` around
``solve_from_centroids``; reading the file is not counted.
"""

import json
import math
import sys
import time

STATUS_NAMES = {1: "MATCH_FOUND", 2: "NO_MATCH", 3: "TIMEOUT", 4: "CANCELLED", 5: "TOO_FEW"}


def _number(value):
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _send(obj) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


def _answer(tetra3, solver, request: dict) -> dict:
    import numpy as np

    image = np.load(request["image"]).astype(np.float32)
    size = tuple(int(v) for v in request["size"])
    t0 = time.perf_counter()
    centroids = tetra3.get_centroids_from_image(image, max_returned=request.get("max_returned"))
    t1 = time.perf_counter()
    result = solver.solve_from_centroids(centroids, size, fov_estimate=request.get("fov_estimate"),
                                         fov_max_error=request.get("fov_max_error"),
                                         solve_timeout=request.get("solve_timeout_ms", 5000))
    t2 = time.perf_counter()
    status = result.get("status")
    return {"id": request.get("id"), "status": STATUS_NAMES.get(status, str(status)),
            "ra_deg": _number(result.get("RA")), "dec_deg": _number(result.get("Dec")),
            "roll_deg": _number(result.get("Roll")), "fov_deg": _number(result.get("FOV")),
            "matches": result.get("Matches"), "n_centroids": int(len(centroids)),
            "centroid_ms": (t1 - t0) * 1000.0, "solve_ms": (t2 - t1) * 1000.0}


def main() -> int:
    try:
        import logging

        logging.disable(logging.INFO)
        import tetra3
        solver = tetra3.Tetra3()
    except Exception as exc:  # noqa: BLE001 - reported to the parent
        _send({"ready": False, "error": f"{type(exc).__name__}: {exc}"})
        return 1
    _send({"ready": True, "peer": "cedar-solve"})
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
            _send(_answer(tetra3, solver, request))
        except Exception as exc:  # noqa: BLE001 - one bad request must not end the run
            _send({"id": request.get("id"), "error": f"{type(exc).__name__}: {exc}"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
