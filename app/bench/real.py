"""Real-frames benchmark.

``python -m app bench --suite real [--frames DIR] [--time-from-reference] [--n N] [--json]``

Real star-camera frames whose answers come from elsewhere, solved as a new user would solve them,
side by side with cedar-solve, in one process.

The frames
----------
``DIR`` (``--frames``, else ``$STARID_REAL_FRAMES``, else ``<repository root>/../shared/real-frames``)
holds ``NAME.png`` with ``NAME.json``: ``ra_deg``, ``dec_deg`` of the image centre pixel from
astrometry.net's WCS, ``pixel_scale_arcsec`` and ``fov_deg_horizontal`` (= the scale times the
width), ``time_approximate`` (see the folder's README).  A frame's group is its name up to the first
``-`` (``feb16``, ``xmas``, ``may8``).  ``--n N`` takes the first N frames in name order.

The exact field of view
-----------------------
The WCS scale at its tangent point is ``1/f`` radians per pixel (gnomonic projection), so the
focal length is ``f = 206264.806"/pixel_scale_arcsec`` px and the horizontal field of view in the
sense both tools give it (a pinhole's angle between the left and right edges),
``2 atan(width / 2f)`` (:func:`exact_fov_deg`).  The JSON's ``fov_deg_horizontal`` is the small-angle
``width / f``: larger by 0.1 % (6 deg), 0.45 % (13 deg), 1.8-1.9 % (27 deg), an error of its own
that this benchmark does not add.  The scale is astrometry.net's fit of each frame (with its SIP
terms): it differs from frame to frame of one camera by up to 1.8 % (feb16) and 3.2 % (xmas).

Ours
----
Each frame is solved through the workflow the ``solve`` command uses
(:func:`app.workflow.files.telemetry_files`, then :func:`~app.workflow.files.solve_document`
with the default search options and method), with one :class:`~app.identification.Sky` for the
whole run, under four optics: ``--fov-deg`` exact, 5 % long (x 1.05), 5 % short (x 0.95) and none.
The image is linked into a folder of the benchmark's own, so no sidecar is read (and none gives a
time); ``--time-from-reference`` writes one there with the JSON's ``time_approximate``, for
comparison.  A run that the workflow refuses is reported with its status ``invalid`` and the
reason, as the command would print it.  ``perf_counter`` around the whole solve: reading the
file, detection, identification.  One warm-up solve (the first frame, exact) before, not counted.

The peer
--------
cedar-solve (tetra3) in its own environment (:func:`app.bench.peer.ensure_peer_env`, made once
from PyPI), one long-lived :mod:`app.bench.peer_frames_runner`: its own centroiding
(``get_centroids_from_image``, defaults) and ``solve_from_centroids`` with its default database
on the same pixels (decoded by :func:`app.frames.read_frames`), interleaved frame by frame with
ours.  Its time is its own ``perf_counter`` around those two calls (loading the array not
counted).  Its optics: ``fov_estimate`` exact with its default ``fov_max_error`` (None: the
estimate only seeds the search), the estimate 5 % long and short with ``fov_max_error`` 10 % of the
estimate (tetra3 takes it in degrees and keeps a pattern when ``|fov - fov_estimate| <=
fov_max_error``: the window our own search gives a field of view given by hand, +-10 %, so that the
truth, 5.3 % of the short estimate away, lies inside both), and ``fov_estimate`` None.  Its RA, Dec are those of the image centre, (height/2, width/2) from the top-left corner in
its convention, our ((width-1)/2, (height-1)/2): the reference's point, as ours.

Figures
-------
A run is *claimed* when ours says ``identified`` / the peer ``MATCH_FOUND``; its error is the great
circle between the reported RA, Dec of the image centre pixel (ours: the first candidate's
``centre_ra_deg``, ``centre_dec_deg``, its boresight - the principal point's direction - when it
has none) and the reference's (:func:`boresight_error_deg`).
Per tool, optics and group (and all frames): identified within 0.1 deg, confidently wrong
(claimed and more than 0.5 deg off), the median error of the claimed answers in arcsec, the
slowest frame in seconds, and the invalid runs; the real-sky goals are checked on them.  When the
peer cannot be made or started the suite says why and reports ours alone.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.attitude import angle_between, solve_wahba, wahba_covariance
from app.bench.peer import PeerError
from app.catalogue import radec_to_vectors
from app.frames.assemble import FOV_FOCAL_TOLERANCE

#: Fewest matched stars whose halves are fitted apart (:func:`half_fit_pulls`): 3 a half at least.
HALF_FIT_MIN_STARS = 6

#: The optics a frame is solved under: name -> factor on the exact field of view (None: none given).
OPTICS = {"exact": 1.0, "long": 1.05, "short": 0.95, "none": None}
OPTICS_LABELS = {"exact": "exact", "long": "5 % long", "short": "5 % short", "none": "none given"}
#: The peer's ``fov_max_error`` as a fraction of its ``fov_estimate`` when the estimate is off: the window
#: ours searches around a field of view given by hand (app.frames.assemble.FOV_FOCAL_TOLERANCE).
PEER_FOV_MAX_ERROR = FOV_FOCAL_TOLERANCE
PEER_SOLVE_TIMEOUT_MS = 5000
#: Right: within this of the reference; confidently wrong: claimed and farther than this.
RIGHT_DEG = 0.1
WRONG_DEG = 0.5
ARCSEC_PER_RADIAN = 180.0 * 3600.0 / math.pi
SIDECAR_FORMAT = "tubsat-frames/1"

#: The real-sky goals: the fraction of frames identified within 0.1 deg per optics, the worst frame's
#: seconds with and without a field of view, the median error.
GOAL_RIGHT_FRACTION = {"exact": 24 / 25, "long": 22 / 25, "short": 22 / 25, "none": 20 / 25}
GOAL_SLOWEST_S = {"exact": 2.0, "long": 2.0, "short": 2.0, "none": 10.0}
GOAL_MEDIAN_ARCSEC = 30.0


class FramesUnavailable(Exception):
    """The frames folder is missing or a reference file is unusable; ``str(exc)`` says where and why."""


@dataclass(frozen=True)
class RealFrame:
    """One frame and its reference (the image centre pixel's direction, the exact field of view)."""

    name: str
    image: Path
    width: int
    height: int
    ra_deg: float
    dec_deg: float
    fov_deg: float
    time: str | None

    @property
    def group(self) -> str:
        return group_of(self.name)


# --- the pure parts ------------------------------------------------------------------------------

def group_of(name: str) -> str:
    """A frame's group: its name up to the first ``-`` (``may8-gain40-img0`` -> ``may8``)."""
    return name.split("-", 1)[0]


def exact_fov_deg(width: int, pixel_scale_arcsec: float) -> float:
    """The pinhole's horizontal field of view, ``2 atan(width / 2f)`` with ``f = 1 / scale`` (radians/px)."""
    focal_px = ARCSEC_PER_RADIAN / pixel_scale_arcsec
    return math.degrees(2.0 * math.atan(width / (2.0 * focal_px)))


def fov_from_focal_deg(width: int, focal_length_px: float) -> float:
    """The horizontal field of view of a fitted focal length, in the same sense."""
    return math.degrees(2.0 * math.atan(width / (2.0 * focal_length_px)))


def boresight_error_deg(ra_deg: float, dec_deg: float, ref_ra_deg: float, ref_dec_deg: float) -> float:
    """Great-circle angle between two directions, degrees (atan2 of |u x v| and u . v: exact near 0 and 180)."""
    u, v = radec_to_vectors(np.radians([ra_deg, ref_ra_deg]), np.radians([dec_deg, ref_dec_deg]))
    return float(np.degrees(angle_between(u, v)))


def summarise(runs: list[dict]) -> dict:
    """The figures of one tool under one optics over some frames (each run: ``claimed``, ``error_deg``,
    ``seconds``, ``status``).

    ``right``: claimed within :data:`RIGHT_DEG`; ``wrong``: claimed and more than :data:`WRONG_DEG`
    off (between the two: neither); ``median_error_arcsec`` over the claimed answers; ``slowest_s``
    over every run (an invalid one too: its time was spent).
    """
    claimed = [r for r in runs if r["claimed"] and r["error_deg"] is not None]
    errors = [r["error_deg"] for r in claimed]
    seconds = [r["seconds"] for r in runs if r["seconds"] is not None]
    return {"frames": len(runs),
            "right": sum(e <= RIGHT_DEG for e in errors),
            "wrong": sum(e > WRONG_DEG for e in errors),
            "claimed": len(claimed),
            "invalid": sum(r["status"] in ("invalid", "error") for r in runs),
            "median_error_arcsec": round(statistics.median(errors) * 3600.0, 1) if errors else None,
            "slowest_s": round(max(seconds), 3) if seconds else None}


#: The header of :func:`summary_columns`.
SUMMARY_HEADER = f"{'right':>7} {'wrong':>6} {'claimed':>8} {'median as':>10} {'slowest s':>10}"


def summary_columns(s: dict) -> str:
    """A :func:`summarise` summary as a table's columns under :data:`SUMMARY_HEADER`."""
    median = "-" if s["median_error_arcsec"] is None else f"{s['median_error_arcsec']:.1f}"
    slowest = "-" if s["slowest_s"] is None else f"{s['slowest_s']:.2f}"
    return f"{s['right']:>3}/{s['frames']:<3} {s['wrong']:>6} {s['claimed']:>8} {median:>10} {slowest:>10}"


def summarise_by_group(frames: list[dict], tool: str, optics: str) -> dict:
    """``{group: summary, ..., "all": summary}`` of ``frames[i][tool][optics]`` (groups in name order)."""
    groups = sorted({f["group"] for f in frames})
    out = {g: summarise([f[tool][optics] for f in frames if f["group"] == g]) for g in groups}
    out["all"] = summarise([f[tool][optics] for f in frames])
    return out


# --- the frames ----------------------------------------------------------------------------------

def default_frames_dir() -> Path:
    """``$STARID_REAL_FRAMES``, else ``shared/real-frames`` beside the repository's folder."""
    explicit = os.environ.get("STARID_REAL_FRAMES")
    if explicit:
        return Path(explicit).expanduser()
    return Path(__file__).resolve().parents[2].parent / "shared" / "real-frames"


def load_frame(reference: Path) -> RealFrame:
    """One ``NAME.json`` and its ``NAME.png``; FramesUnavailable naming the file and the key that is wrong."""
    try:
        doc = json.loads(reference.read_text())
    except (OSError, ValueError) as exc:
        raise FramesUnavailable(f"{reference}: cannot be read as JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise FramesUnavailable(f"{reference}: must be a JSON object")
    values = {}
    for key in ("ra_deg", "dec_deg", "pixel_scale_arcsec", "width", "height"):
        value = doc.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                or (key in ("pixel_scale_arcsec", "width", "height") and value <= 0):
            raise FramesUnavailable(f"{reference}: {key} must be a finite number"
                                    f"{' above 0' if key not in ('ra_deg', 'dec_deg') else ''}, got {value!r}")
        values[key] = float(value)
    image = reference.with_suffix(".png")
    if not image.is_file():
        raise FramesUnavailable(f"{reference}: its image {image.name} is not beside it")
    width, height = int(values["width"]), int(values["height"])
    return RealFrame(name=reference.stem, image=image, width=width, height=height, ra_deg=values["ra_deg"],
                     dec_deg=values["dec_deg"], fov_deg=exact_fov_deg(width, values["pixel_scale_arcsec"]),
                     time=doc.get("time_approximate"))


def load_frames(folder: Path) -> list[RealFrame]:
    """Every ``NAME.json`` with its ``NAME.png`` in ``folder``, in name order."""
    if not folder.is_dir():
        raise FramesUnavailable(f"no frames folder at {folder}: give --frames DIR or set STARID_REAL_FRAMES")
    frames = [load_frame(p) for p in sorted(folder.glob("*.json")) if p.with_suffix(".png").is_file()]
    if not frames:
        raise FramesUnavailable(f"{folder} holds no NAME.png with its NAME.json")
    return frames


def suite_frames(suite: str, frames_dir: str | Path | None, n: int | None) -> tuple[Path, list[RealFrame]]:
    """The frames folder (``frames_dir``, else :func:`default_frames_dir`) and its first ``n`` frames (all when
    None); FramesUnavailable, said on stderr as the ``suite`` skipped, when there are none."""
    folder = Path(frames_dir) if frames_dir is not None else default_frames_dir()
    try:
        frames = load_frames(folder)
    except FramesUnavailable as exc:
        print(f"{suite}: skipped: {exc}", file=sys.stderr)
        raise
    return folder, frames[:n] if n else frames


def stage(frame: RealFrame, folder: Path, *, time_from_reference: bool) -> Path:
    """The frame's image linked into ``folder`` (so no sidecar of the frames folder is read), with a
    sidecar giving ``time_approximate`` when asked; the path to solve."""
    link = folder / frame.image.name
    if not link.exists():
        link.symlink_to(frame.image.resolve())
    sidecar = folder / f"{frame.name}.frames.json"
    if time_from_reference:
        if frame.time is None:
            raise FramesUnavailable(f"{frame.name}.json has no time_approximate for --time-from-reference")
        sidecar.write_text(json.dumps({"format": SIDECAR_FORMAT,
                                       "frames": [{"file": frame.image.name, "time": frame.time}]}))
    elif sidecar.exists():
        sidecar.unlink()
    return link


# --- ours ----------------------------------------------------------------------------------------

def solve_ours(frame: RealFrame, sky, fov_deg: float | None, folder: Path, *,
               time_from_reference: bool = False) -> dict:
    """Our run on one frame under one optics (``fov_deg`` None: no field of view given), through the
    ``solve`` command's workflow; the record of :func:`summarise` plus ``ra_deg``, ``dec_deg``,
    ``fov_deg`` (fitted, when the answer fits a focal length) and ``notes``."""
    from app.identification import SearchOptions
    from app.workflow.files import invalid_solve_document, solve_document, telemetry_files

    path = str(stage(frame, folder, time_from_reference=time_from_reference))
    t0 = time.perf_counter()
    try:
        docs = [invalid_solve_document(p, str(error)) if error is not None
                else solve_document(p, sequence, sky, options=SearchOptions())
                for p, sequence, error in telemetry_files([path], fov_deg=fov_deg)]
    except Exception as exc:  # noqa: BLE001 - the command reports a bug as that file's error; so does this
        return {**_unanswered("error", time.perf_counter() - t0),
                "notes": [f"could not be processed ({type(exc).__name__}: {exc})"]}
    seconds = time.perf_counter() - t0
    (doc,) = docs
    notes = list(doc.notes)
    if doc.error:
        notes.insert(0, doc.error.removeprefix(f"{path}: "))
    if doc.focal_length_contradiction is not None:
        notes.append(doc.focal_length_contradiction.note)
    if not doc.candidates:
        return {**_unanswered(doc.status, seconds), "notes": notes}
    first = doc.candidates[0]
    fit = first.camera_fit
    # The reference is the image centre pixel's direction: ours is the candidate's centre_ra/dec (the boresight
    # when that is missing, as for a centred lens).
    ra = first.centre_ra_deg if first.centre_ra_deg is not None else first.ra_deg
    dec = first.centre_dec_deg if first.centre_dec_deg is not None else first.dec_deg
    focal = first.focal_length_px or (fit.focal_length_px if fit is not None else None)
    return {"status": doc.status, "claimed": doc.status == "identified", "ra_deg": ra,
            "dec_deg": dec, "error_deg": boresight_error_deg(ra, dec, frame.ra_deg, frame.dec_deg),
            "fov_deg": round(fov_from_focal_deg(frame.width, focal), 4) if focal else None,
            "seconds": round(seconds, 4), "notes": notes}


def half_fit_pulls(body: np.ndarray, stars: np.ndarray, sigma_cross_rad: float, x_px: np.ndarray) -> dict:
    """How honest a stated cross-boresight 1-sigma is, from the answer's own stars: they are fitted in two halves
    (the left and right of the image, and every other star), and the two boresights' separation is divided by
    the separation the stated sigma predicts.

    ``body`` (n, 3) camera-frame directions of the matched points, ``stars`` (n, 3) their stars' directions,
    ``x_px`` their columns. The stated sigma says what each star's error is: ``s`` such that Wahba's covariance
    of all n with sigma ``s`` each gives ``sigma_cross_rad``; each half's covariance is then Wahba's with the same
    ``s`` (its own geometry), and the two boresights' difference (a 2-vector in the first half's camera frame)
    has the sum of the two covariances' cross-boresight blocks. The pull is its length over the square root of
    that block's trace: about 1 in RMS when the stated sigma is honest and the errors independent. Sides (left,
    right) also catch errors that the two halves of the image share (an unmodelled distortion, a centroid bias
    across the field) and the interleaved split does not: a sides pull well above the interleaved one says the
    errors are correlated across the field and a sigma from the residuals alone is too small.
    """
    n = len(body)
    unit = wahba_covariance(body, np.ones(n))
    per_star = sigma_cross_rad / math.sqrt((unit[0, 0] + unit[1, 1]) / 2)
    out = {}
    for split, first in (("sides", x_px < np.median(x_px)), ("alternate", np.arange(n) % 2 == 0)):
        halves = (first, ~first)
        a, b = (solve_wahba(body[h], stars[h]) for h in halves)
        d = (a @ b[2])[:2]  # the second boresight in the first's camera frame: its x, y are the angles apart
        cov = sum(wahba_covariance(body[h], np.full(int(h.sum()), per_star)) for h in halves)
        out[split] = float(np.hypot(*d) / math.sqrt(cov[0, 0] + cov[1, 1]))
    return out


def half_fits_of(frame: RealFrame, sky, folder: Path, *, time_from_reference: bool) -> dict | None:
    """:func:`half_fit_pulls` of the first candidate of ``frame`` solved with its exact field of view, when it is
    identified with :data:`HALF_FIT_MIN_STARS` stars or more and states a sigma; else None."""
    from app.identification import IDENTIFIED, solve_sequence
    from app.workflow.files import telemetry_files

    path = str(stage(frame, folder, time_from_reference=time_from_reference))
    ((_, sequence, error),) = list(telemetry_files([path], fov_deg=frame.fov_deg))
    if error is not None:
        return None
    solved = solve_sequence(sequence, sky)
    best = solved.solution.candidates[0] if solved.solution.candidates else None
    if (solved.solution.status != IDENTIFIED or best.n_matched < HALF_FIT_MIN_STARS
            or best.sigma_cross_boresight_arcsec is None):
        return None
    camera = best.camera or sequence.camera
    xy = solved.pattern.xy[[m.pattern_index for m in best.matches]]
    stars = sky.for_camera(camera).apparent_vectors_of([m.hip for m in best.matches], solved.reference_time,
                                                       sequence.observer)
    return {"n": best.n_matched, "sigma_arcsec": best.sigma_cross_boresight_arcsec,
            **half_fit_pulls(camera.pixels_to_vectors(xy), stars, best.sigma_cross_boresight_arcsec
                             / ARCSEC_PER_RADIAN, xy[:, 0])}


def _unanswered(status: str, seconds: float | None) -> dict:
    return {"status": status, "claimed": False, "ra_deg": None, "dec_deg": None, "error_deg": None,
            "fov_deg": None, "seconds": None if seconds is None else round(seconds, 4)}


# --- the peer ------------------------------------------------------------------------------------

def peer_optics(frame: RealFrame, optics: str) -> dict:
    """The peer's ``fov_estimate`` and ``fov_max_error`` (degrees) under one optics."""
    factor = OPTICS[optics]
    if factor is None:
        return {"fov_estimate": None, "fov_max_error": None}
    estimate = frame.fov_deg * factor
    return {"fov_estimate": estimate, "fov_max_error": None if factor == 1.0 else PEER_FOV_MAX_ERROR * estimate}


def solve_peer(peer, frame: RealFrame, pixels_path: Path, optics: str) -> dict:
    """The peer's run on one frame under one optics, in the record of :func:`solve_ours`."""
    answer = peer.solve({"image": str(pixels_path), "size": [frame.height, frame.width],
                         **peer_optics(frame, optics), "solve_timeout_ms": PEER_SOLVE_TIMEOUT_MS})
    if "error" in answer:  # killed after a time-out, or crashed (RestartingPeer restarts it)
        return {**_unanswered(answer.get("status", "ERROR"), None), "notes": [answer["error"]]}
    seconds = (answer["centroid_ms"] + answer["solve_ms"]) / 1000.0
    notes = [f"{answer['n_centroids']} centroids, {answer.get('matches')} matched"]
    if answer["status"] != "MATCH_FOUND" or answer["ra_deg"] is None:
        return {**_unanswered(answer["status"], seconds), "notes": notes}
    return {"status": answer["status"], "claimed": True, "ra_deg": answer["ra_deg"], "dec_deg": answer["dec_deg"],
            "error_deg": boresight_error_deg(answer["ra_deg"], answer["dec_deg"], frame.ra_deg, frame.dec_deg),
            "fov_deg": None if answer["fov_deg"] is None else round(answer["fov_deg"], 4),
            "seconds": round(seconds, 4), "notes": notes}


def start_peer():
    """``(peer, facts, None)``: the long-lived cedar-solve image runner, its environment made if
    needed; or ``(None, None, why not)``."""
    from app.bench import peer as peer_suite

    try:
        python, facts = peer_suite.ensure_peer_env()
    except peer_suite.PeerUnavailable as exc:
        return None, None, f"cedar-solve environment unavailable: {exc}"
    runner = Path(peer_suite.__file__).with_name("peer_frames_runner.py")
    try:
        peer = peer_suite.RestartingPeer([str(python), "-I", str(runner)], env=peer_suite._clean_env())
    except peer_suite.PeerError as exc:
        return None, None, f"cedar-solve could not be started: {exc}"
    return peer, facts, None


def save_pixels(frame: RealFrame, folder: Path) -> Path:
    """The frame's pixels as the runner reads them (a ``.npy`` of rows from the top)."""
    from app.frames import read_frames

    pixels = next(read_frames(frame.image.read_bytes(), frame.image.name)).pixels
    path = folder / f"{frame.name}.npy"
    np.save(path, pixels)
    return path


# --- the suite -----------------------------------------------------------------------------------

def run(n_sequences: int | None = None, seed: int = 1, frames_dir: str | Path | None = None,
        time_from_reference: bool = False) -> dict:
    """The suite (``seed`` unused: nothing here is drawn); ``{"skipped": REASON}`` without frames."""
    from app.identification import Sky

    try:
        folder, frames = suite_frames("real", frames_dir, n_sequences)
    except FramesUnavailable as exc:
        return {"skipped": str(exc)}
    peer, facts, peer_note = start_peer()
    if peer is None:
        print(f"real: the peer is not measured: {peer_note}", file=sys.stderr)
    load_before = round(os.getloadavg()[0], 2)
    sky = Sky()
    rows = []
    peer_failed = None  # why the peer stopped answering during the run, if it did
    try:
        with tempfile.TemporaryDirectory(prefix="starid-real-") as scratch:
            scratch = Path(scratch)
            warm_up = solve_ours(frames[0], sky, frames[0].fov_deg, scratch, time_from_reference=time_from_reference)
            for frame in frames:
                pixels = save_pixels(frame, scratch) if peer is not None else None
                row = {"name": frame.name, "group": frame.group, "ra_deg": frame.ra_deg, "dec_deg": frame.dec_deg,
                       "fov_exact_deg": round(frame.fov_deg, 4), "ours": {}, "peer": {}}
                for optics, factor in OPTICS.items():
                    fov = None if factor is None else frame.fov_deg * factor
                    row["ours"][optics] = solve_ours(frame, sky, fov, scratch, time_from_reference=time_from_reference)
                    if peer is not None and peer_failed is None:
                        try:
                            row["peer"][optics] = solve_peer(peer, frame, pixels, optics)
                        except PeerError as exc:  # restarted too often: the remaining runs say so
                            peer_failed = f"cedar-solve failed during the run: {exc}"
                            print(f"real: {peer_failed}", file=sys.stderr)
                    if peer is not None and peer_failed is not None:
                        row["peer"][optics] = {**_unanswered("ERROR", None), "notes": [peer_failed]}
                row["half_fits"] = half_fits_of(frame, sky, scratch, time_from_reference=time_from_reference)
                print(f"real: {frame.name}: " + ", ".join(f"{o} {r['status']}" for o, r in row["ours"].items()),
                      file=sys.stderr)
                rows.append(row)
    finally:
        if peer is not None:
            peer.close()
    tools = ("ours", "peer") if peer is not None else ("ours",)
    summary = {tool: {optics: summarise_by_group(rows, tool, optics) for optics in OPTICS} for tool in tools}
    return {"frames_dir": str(folder), "n_frames": len(rows), "time_from_reference": time_from_reference,
            "groups": dict(sorted(Counter(r["group"] for r in rows).items())),
            "peer": ({"measured": True, "package": "cedar-solve", "version": facts.get("version"),
                      "numpy": facts.get("numpy"), "restarts": peer.restarts, "failed": peer_failed,
                      "fov_max_error_fraction": PEER_FOV_MAX_ERROR}
                     if peer is not None else {"measured": False, "note": peer_note}),
            "warm_up_s": warm_up["seconds"], "frames": rows, "summary": summary,
            "invalid_reasons": invalid_reasons(rows), "goals": goals(summary),
            "half_fits": summarise_half_fits(rows),
            "load_average_before": load_before, "load_average_after": round(os.getloadavg()[0], 2)}


def summarise_half_fits(rows: list[dict]) -> dict:
    """The RMS of each split's pulls over the frames that had them (:func:`half_fit_pulls`)."""
    fits = [r["half_fits"] for r in rows if r.get("half_fits")]
    return {"frames": len(fits), **{split: math.sqrt(statistics.fmean([f[split] ** 2 for f in fits])) if fits
                                    else None for split in ("sides", "alternate")}}


def invalid_reasons(rows: list[dict]) -> dict:
    """``{optics: {reason: how many}}``: why ours was refused (the first note of an invalid run, the
    frame's name in it said ``NAME``), each reason once."""
    out = {}
    for optics in OPTICS:
        reasons = Counter((r["ours"][optics]["notes"] or ["(no reason given)"])[0].replace(r["name"], "NAME")
                          for r in rows if r["ours"][optics]["status"] in ("invalid", "error"))
        if reasons:
            out[optics] = dict(reasons.most_common())
    return out


def goals(summary: dict) -> dict:
    """The real-sky goals on ours (and against the peer when it was measured): ``{goal: met}``."""
    ours = summary["ours"]
    out = {}
    for optics, fraction in GOAL_RIGHT_FRACTION.items():
        a = ours[optics]["all"]
        needed = math.ceil(fraction * a["frames"] - 1e-9)
        out[f"{optics}: right >= {needed}/{a['frames']}"] = a["right"] >= needed
    out["0 confidently wrong"] = all(ours[o]["all"]["wrong"] == 0 for o in OPTICS)
    medians = [ours[o]["all"]["median_error_arcsec"] for o in OPTICS]
    out[f"median error <= {GOAL_MEDIAN_ARCSEC:g} arcsec"] = all(m is not None and m <= GOAL_MEDIAN_ARCSEC
                                                               for m in medians)
    out["slowest <= 2 s with a field of view, 10 s without"] = all(
        ours[o]["all"]["slowest_s"] is not None and ours[o]["all"]["slowest_s"] <= GOAL_SLOWEST_S[o] for o in OPTICS)
    if "peer" in summary:
        out["more right than the peer in every group"] = all(
            ours[o][g]["right"] > summary["peer"][o][g]["right"] for o in OPTICS for g in ours[o] if g != "all")
    return out


# --- the table -----------------------------------------------------------------------------------

STATUS_CODES = {"identified": "id", "ambiguous": "amb", "no_match": "nm", "invalid": "inv", "error": "err",
                "MATCH_FOUND": "id", "NO_MATCH": "nm", "TIMEOUT": "t/o", "TOO_FEW": "few", "CANCELLED": "cxl",
                "TIMEOUT_KILLED": "kil", "ERROR": "err"}


def _cell(run: dict) -> str:
    """``id 41" 1.23s``: status, error (arcsec below a degree, else degrees), seconds."""
    code = STATUS_CODES.get(run["status"], run["status"][:4])
    e = run["error_deg"]
    error = "-" if e is None else (f'{e * 3600:.0f}"' if e < 1.0 else f"{e:.0f}d")
    seconds = "-" if run["seconds"] is None else f"{run['seconds']:.2f}s"
    return f"{code:>3} {error:>5} {seconds:>6}"


def format_table(result: dict) -> str:
    if "skipped" in result:
        return f"skipped: {result['skipped']}"

    def f(v, fmt=".1f"):
        return "-" if v is None else format(v, fmt)

    peer = result["peer"]
    groups = ", ".join(f"{g} {n}" for g, n in result["groups"].items())
    lines = [f"{result['n_frames']} real frames in {result['frames_dir']} ({groups}); "
             + ("a sidecar gives the reference's time_approximate" if result["time_from_reference"]
                else "no sidecar, no time") + f"; our warm-up solve {result['warm_up_s']:.2f} s (not counted)",
             ("peer: cedar-solve {version} (numpy {numpy}, default database, its own centroiding), restarts "
              "{restarts}; fov_max_error: default with the exact estimate, 10 % of the estimate when it is off"
              .format(**peer) + (f"; {peer['failed']}" if peer["failed"] else ""))
             if peer["measured"] else f"peer: not measured: {peer['note']}",
             f"load average {result['load_average_before']} before, {result['load_average_after']} after (2 cores)",
             "",
             f"{'tool':<12} {'optics':<11} {'group':<6} {'right':>7} {'wrong':>6} {'claimed':>8} {'invalid':>8} "
             f"{'median as':>10} {'slowest s':>10}"]
    for tool, name in (("ours", "ours"), ("peer", "cedar-solve")):
        for optics, by_group in result["summary"].get(tool, {}).items():
            for group, s in by_group.items():
                lines.append(f"{name:<12} {OPTICS_LABELS[optics]:<11} {group:<6} "
                             f"{s['right']:>3}/{s['frames']:<3} {s['wrong']:>6} {s['claimed']:>8} {s['invalid']:>8} "
                             f"{f(s['median_error_arcsec']):>10} {f(s['slowest_s'], '.2f'):>10}")
    lines.append(f"(right: claimed - ours identified, the peer MATCH_FOUND - within {RIGHT_DEG} deg of the WCS's image "
                 f"centre; wrong: claimed and over {WRONG_DEG} deg off; median as: error of the claimed answers, "
                 "arcsec; slowest: ours reading + detection + identification, the peer its centroiding + solve)")
    for tool, name in (("ours", "ours"), ("peer", "cedar-solve")):
        if tool not in result["summary"]:
            continue
        lines += ["", f"{name} per frame (status, error, seconds):",
                  f"{'frame':<18} " + " ".join(f"{OPTICS_LABELS[o]:>16}" for o in OPTICS)]
        for row in result["frames"]:
            lines.append(f"{row['name']:<18} " + " ".join(f"{_cell(row[tool][o]):>16}" for o in OPTICS))
    for optics, reasons in result["invalid_reasons"].items():
        for reason, count in reasons.items():
            lines.append(f"ours {OPTICS_LABELS[optics]}: {count} invalid: {reason}")
    halves = result.get("half_fits")
    if halves and halves["frames"]:
        lines += ["", f"stated sigma against our own half fits ({halves['frames']} frames identified with their exact "
                      f"field of view and {HALF_FIT_MIN_STARS}+ stars): RMS pull {halves['sides']:.2f} between the "
                      f"image's left and right halves, {halves['alternate']:.2f} between every other star (1 = honest; "
                      "sides above alternate: errors shared across the field)"]
    verdicts = (f"{goal} {'met' if met else 'NOT met'}" for goal, met in result["goals"].items())
    lines += ["", "real-sky goals: " + ", ".join(verdicts)]
    return "\n".join(lines)
