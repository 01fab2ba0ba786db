"""Full-frame benchmark: ``python -m app bench --suite frames [--n N] [--seed S] [--json]``.

Every figure comes from frames rendered now by :func:`app.simulate.simulate_frames` (Gaussian PSF
sigma 1.2 px, sky 200 e-, read noise 10 e-, 16 bit, six hot pixels per camera, a satellite trail in
every fourth frame; the detection limit is where a star's SNR is 5), with the exact position of
every drawn star.

1. **Detectors** on ``N`` frames (default 24) of the 752 x 582 20 deg camera at random pointings:
   ``sep`` (this project's :func:`app.frames.detect`, windowed centroids) against photutils'
   ``DAOStarFinder`` and ``IRAFStarFinder`` (told the true PSF width, on photutils' own
   ``Background2D`` mesh of the same 64 px boxes, threshold 5 sigma).  Per detector:

   * completeness: star-like detections within 1 px of stars 2 magnitudes brighter than the
     detection limit (at least 3 px inside the frame);
   * false detections per frame: star-like detections within 1.5 px of no drawn star (hot
     pixels and trails count as false here; they are also counted on their own);
   * hot pixels taken as stars (must be 0) and trail pieces taken as stars;
   * centroid error at SNR 50: 300 stars at random sub-pixel positions, each with the flux
     whose SNR is 50, on a separate frame (median and RMS distance to the truth, px);
   * ms per Mpx: the median time per frame, background estimation included, over the frame's
     megapixels.

2. **The pipeline** (:func:`app.frames.frames_to_sequence`) on ``N/4`` passes of 4 frames of one
   camera, the hot-pixel map carried from pass to pass: hot pixels among the reported sources
   (must be 0) and completeness of the reported sources for stars 2 mag above the limit.

3. **A 2 Mpx frame** (1632 x 1224, 20 deg): detection + identification
   (:func:`app.frames.frames_to_sequence` from the decoded image, then
   :func:`app.identification.solve_sequence`), correct = boresight within 0.1 deg of the truth,
   over ``max(4, N/4)`` frames; one warm-up frame first.

4. **The peer** on the same 2 Mpx frames: cedar-solve's ``get_centroids_from_image`` +
   ``solve_from_centroids`` in its own environment, reused from the peer suite
   (:mod:`app.bench.peer`: ``~/.cache/starid/peer-venv`` or ``$STARID_PEER_VENV``) through one
   long-lived runner (:mod:`app.bench.peer_frames_runner`), interleaved frame by frame with ours.
   When that environment does not exist the row says "not measured" (``bench --suite peer``
   makes it once).
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from app.attitude import angle_between
from app.camera import CAMERAS, Camera
from app.frames import DetectionOptions, detect, frames_to_sequence
from app.frames.images import Frame
from app.simulate import FrameModel, render_frame, simulate_frames

CAMERA_NAME = "tubsat-752x582-20deg"
MODEL = FrameModel()
#: The 2 Mpx camera: 1632 x 1224 pixels, 20 deg across.
BIG_CAMERA = Camera(width=1632, height=1224, focal_length_px=round(816 / math.tan(math.radians(10.0)), 1),
                    cx=815.5, cy=611.5, name="bench-1632x1224-20deg")
MATCH_PX = 1.0
FALSE_PX = 1.5


# --- detectors ---------------------------------------------------------------------------------

def _sep(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(xy of star-like detections, xy of everything) with this project's detector."""
    found = detect(image, DetectionOptions(), saturation=MODEL.saturation_adu())
    return found.xy[found.is_star], found.xy


def _photutils(finder_name: str):
    def run(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import warnings

        from photutils.background import Background2D, MedianBackground
        from photutils.detection import DAOStarFinder, IRAFStarFinder

        data = image.astype(np.float32)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            background = Background2D(data, (64, 64), filter_size=(3, 3), bkg_estimator=MedianBackground())
            sub = data - background.background
            threshold = 5.0 * float(background.background_rms_median)
            fwhm = 2.3548 * MODEL.psf_sigma_px
            finder = (DAOStarFinder if finder_name == "DAOStarFinder" else IRAFStarFinder)(fwhm=fwhm,
                                                                                        threshold=threshold)
            table = finder.find_stars(sub)
        if table is None:
            return np.zeros((0, 2)), np.zeros((0, 2))
        names = ("x_centroid", "y_centroid") if "x_centroid" in table.colnames else ("xcentroid", "ycentroid")
        xy = np.column_stack([np.asarray(table[names[0]], float), np.asarray(table[names[1]], float)])
        return xy, xy  # photutils' finders reject sharp and elongated blobs themselves
    return run


DETECTORS = {"sep": _sep, "photutils DAOStarFinder": _photutils("DAOStarFinder"),
             "photutils IRAFStarFinder": _photutils("IRAFStarFinder")}


def _nearest(points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Distance from each target to the nearest point (inf when there is none)."""
    if not len(targets):
        return np.zeros(0)
    if not len(points):
        return np.full(len(targets), np.inf)
    return cKDTree(points).query(targets)[0]


def _score_frame(stars_xy, all_xy, truth_sources, camera, limit) -> dict:
    drawn = np.array([[s["x"], s["y"]] for s in truth_sources if s["kind"] == "star"]).reshape(-1, 2)
    bright = np.array([[s["x"], s["y"]] for s in truth_sources if s["kind"] == "star" and s["mag"] <= limit - 2
                       and 3 <= s["x"] <= camera.width - 4 and 3 <= s["y"] <= camera.height - 4]).reshape(-1, 2)
    hot = np.array([[s["x"], s["y"]] for s in truth_sources if s["kind"] == "hot_pixel"]).reshape(-1, 2)
    found = _nearest(stars_xy, bright)
    to_drawn = _nearest(drawn, stars_xy)
    on_hot = _nearest(hot, stars_xy) <= MATCH_PX
    on_trail = np.zeros(len(stars_xy), dtype=bool)
    for s in truth_sources:
        if s["kind"] == "trail" and len(stars_xy):
            a, b = np.array(s["start"]), np.array(s["end"])
            d = (b - a) / np.linalg.norm(b - a)
            rel = stars_xy - a
            along = rel @ d
            across = np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0])
            on_trail |= (along > -2) & (along < np.linalg.norm(b - a) + 2) & (across < 3) & (to_drawn > FALSE_PX)
    return {"bright": len(bright), "bright_found": int(np.sum(found <= MATCH_PX)),
            "false": int(np.sum(to_drawn > FALSE_PX)), "hot_as_stars": int(on_hot.sum()),
            "trail_as_stars": int(on_trail.sum())}


def _centroid_frame(rng: np.random.Generator, n: int = 300):
    """A frame of ``n`` stars of SNR 50 at random sub-pixel positions on a grid (no blends)."""
    camera = CAMERAS[CAMERA_NAME]
    step = 30
    cols, rows = (camera.width - 40) // step, (camera.height - 40) // step
    cells = rng.permutation(cols * rows)[:n]
    xy = np.column_stack([20 + (cells % cols) * step, 20 + (cells // cols) * step]).astype(float)
    xy += rng.uniform(-0.5, 0.5, xy.shape)
    flux = np.full(len(xy), MODEL.flux_for_snr(50.0))
    return render_frame(rng, camera, xy, flux, MODEL, hot_pixels=[]), xy


def detector_figures(n_frames: int, seed: int) -> dict:
    camera = CAMERAS[CAMERA_NAME]
    rng = np.random.default_rng([seed, 15, 1])
    frames = []
    for k in range(n_frames):
        rendered, _, truth = simulate_frames(np.random.default_rng([seed, 15, 2, k]), camera, n_frames=1,
                                             trail=(k % 4 == 3))
        frames.append((rendered[0], truth["frame_sources"][0], truth["detection_limit_mag"]))
    grids = [_centroid_frame(rng) for _ in range(2)]
    out = {}
    for name, run in DETECTORS.items():
        run(frames[0][0])  # warm-up: imports, first allocations
        totals = {"bright": 0, "bright_found": 0, "false": 0, "hot_as_stars": 0, "trail_as_stars": 0}
        ms = []
        for image, sources, limit in frames:
            t0 = time.perf_counter()
            stars, everything = run(image)
            ms.append((time.perf_counter() - t0) * 1000.0)
            for key, value in _score_frame(stars, everything, sources, camera, limit).items():
                totals[key] += value
        errors = []
        for image, truth_xy in grids:
            stars, _ = run(image)
            d = _nearest(stars, truth_xy)
            errors += list(d[d <= MATCH_PX])
            totals.setdefault("snr50_missed", 0)
            totals["snr50_missed"] += int(np.sum(d > MATCH_PX))
        mpx = camera.width * camera.height / 1e6
        errors = np.array(errors)
        out[name] = {
            "frames": len(frames),
            "bright_stars": totals["bright"],
            "completeness_2mag_above_limit": round(totals["bright_found"] / max(1, totals["bright"]), 4),
            "false_per_frame": round(totals["false"] / len(frames), 2),
            "hot_pixels_as_stars": totals["hot_as_stars"],
            "trail_pieces_as_stars": totals["trail_as_stars"],
            "snr50_stars": int(len(errors) + totals["snr50_missed"]),
            "snr50_missed": totals["snr50_missed"],
            "centroid_error_snr50_median_px": round(float(np.median(errors)), 4) if len(errors) else None,
            "centroid_error_snr50_rms_px": round(float(np.sqrt(np.mean(errors ** 2))), 4) if len(errors) else None,
            "ms_per_mpx": round(float(np.median(ms)) / mpx, 1),
        }
    return out


# --- the pipeline ---------------------------------------------------------------------------------

def pipeline_figures(n_passes: int, seed: int) -> dict:
    camera = CAMERAS[CAMERA_NAME]
    hot_map = None
    sources = hot_as_sources = bright = bright_found = 0
    for k in range(n_passes):
        rendered, times, truth = simulate_frames(np.random.default_rng([seed, 15, 3, k]), camera, n_frames=4,
                                                 trail=(k % 2 == 1))
        frames = [Frame(pixels=f.astype(np.float32), location=f"p{k}[{i}]", file=f"p{k}", part=i, time=t,
                        saturation=float(MODEL.saturation_adu()), bits=16)
                  for i, (f, t) in enumerate(zip(rendered, times))]
        result = _pass_from_frames(frames, camera, hot_map)
        hot_map = result.hot_map
        limit = truth["detection_limit_mag"]
        for snapshot, truth_sources in zip(result.sequence.snapshots, truth["frame_sources"]):
            hot = np.array([[s["x"], s["y"]] for s in truth_sources if s["kind"] == "hot_pixel"]).reshape(-1, 2)
            sources += snapshot.n_sources
            hot_as_sources += int(np.sum(_nearest(hot, snapshot.xy) <= MATCH_PX))
            brightest = sorted((s for s in truth_sources if s["kind"] == "star"
                                and 3 <= s["x"] <= camera.width - 4 and 3 <= s["y"] <= camera.height - 4),
                               key=lambda s: s["mag"])[:10]
            wanted = np.array([[s["x"], s["y"]] for s in brightest if s["mag"] <= limit - 2]).reshape(-1, 2)
            bright += len(wanted)
            bright_found += int(np.sum(_nearest(snapshot.xy, wanted) <= MATCH_PX))
    return {"passes": n_passes, "frames": 4 * n_passes, "sources_reported": sources,
            "hot_pixels_among_sources": hot_as_sources, "mapped_hot_pixels": len(hot_map.hot) if hot_map else 0,
            "brightest_stars_reported": round(bright_found / max(1, bright), 4), "brightest_stars": bright}


def _pass_from_frames(frames: list[Frame], camera: Camera, hot_map):
    """frames_to_sequence on frames already decoded (the benchmark skips encoding and decoding files)."""
    return frames_to_sequence([], decoded=frames, fov_deg=camera.fov_deg[0], hot_map=hot_map)


# --- 2 Mpx frames and the peer -------------------------------------------------------------------------

def big_frame_figures(n_frames: int, seed: int) -> dict:
    from app.bench import peer as peer_suite
    from app.identification import Sky, solve_sequence

    sky = Sky()
    cases = []
    for k in range(n_frames + 1):
        rendered, times, truth = simulate_frames(np.random.default_rng([seed, 15, 4, k]), BIG_CAMERA, n_frames=1)
        cases.append((rendered[0], times[0], np.asarray(truth["rotation_matrices"][0])))
    peer, peer_note = _start_peer(peer_suite)
    ours_ms, ours_detect_ms, ours_ok = [], [], 0
    theirs_ms, theirs_centroid_ms, theirs_ok, theirs_claimed = [], [], 0, 0
    with tempfile.TemporaryDirectory() as folder:
        for k, (image, t, R_true) in enumerate(cases):
            frame = Frame(pixels=image.astype(np.float32), location=f"big{k}", file=f"big{k}", part=0, time=t,
                          saturation=float(MODEL.saturation_adu()), bits=16)
            t0 = time.perf_counter()
            result = _pass_from_frames([frame], BIG_CAMERA, None)
            t1 = time.perf_counter()
            solved = solve_sequence(result.sequence, sky)
            t2 = time.perf_counter()
            answer = None
            if peer is not None:
                path = Path(folder) / f"big{k}.npy"
                np.save(path, image)
                fov = float(BIG_CAMERA.fov_deg[0])
                answer = peer.solve({"image": str(path), "size": [BIG_CAMERA.height, BIG_CAMERA.width],
                                     "fov_estimate": fov, "fov_max_error": 0.05 * fov, "solve_timeout_ms": 5000})
            if k == 0:
                continue  # warm-up
            ours_ms.append((t2 - t0) * 1000.0)
            ours_detect_ms.append((t1 - t0) * 1000.0)
            candidates = solved.solution.candidates
            if solved.solution.status == "identified" and candidates:
                ours_ok += _boresight_deg(np.asarray(candidates[0].rotation_matrix), R_true) <= 0.1
            if answer is not None and "centroid_ms" in answer:
                theirs_ms.append(answer["centroid_ms"] + answer["solve_ms"])
                theirs_centroid_ms.append(answer["centroid_ms"])
                if answer.get("status") == "MATCH_FOUND":
                    theirs_claimed += 1
                    R = peer_suite.rotation_from_tetra3(answer["ra_deg"], answer["dec_deg"], answer["roll_deg"])
                    theirs_ok += _boresight_deg(R, R_true) <= 0.1
    if peer is not None:
        peer.close()
    out = {"frames": n_frames, "pixels": BIG_CAMERA.width * BIG_CAMERA.height,
           "ours": {"correct": ours_ok, "median_ms": _median(ours_ms), "detection_median_ms": _median(ours_detect_ms)}}
    if peer is None:
        out["peer"] = {"measured": False, "note": peer_note}
    else:
        out["peer"] = {"measured": True, "correct": theirs_ok, "claimed": theirs_claimed,
                       "median_ms": _median(theirs_ms), "centroid_median_ms": _median(theirs_centroid_ms)}
    return out


def _start_peer(peer_suite):
    """The long-lived cedar-solve image runner in the peer suite's environment, or (None, why not)."""
    try:  # the peer suite's helpers (its environment check is private there; a rename must not break this suite)
        path = peer_suite.peer_venv_dir()
        facts = peer_suite._check_env(path)
    except AttributeError as exc:
        return None, f"not measured: the peer suite changed ({exc})"
    if facts is None:
        return None, (f"not measured: no cedar-solve environment at {path} "
                      "(python -m app bench --suite peer makes it once)")
    runner = Path(__file__).with_name("peer_frames_runner.py")
    try:
        process = peer_suite.PeerProcess([str(peer_suite._venv_python(path)), "-I", str(runner)],
                                         env=peer_suite._clean_env())
        process.start()
    except peer_suite.PeerError as exc:
        return None, f"not measured: the cedar-solve runner did not start ({exc})"
    return process, f"cedar-solve {facts.get('version')}"


def _boresight_deg(R: np.ndarray, R_true: np.ndarray) -> float:
    return float(np.degrees(angle_between(np.asarray(R)[2], R_true[2])))


def _median(values) -> float | None:
    return round(float(np.median(values)), 1) if len(values) else None


# --- the suite ----------------------------------------------------------------------------------------

def run(n_sequences: int = 24, seed: int = 1) -> dict:
    n = max(4, int(n_sequences))
    return {"detectors": detector_figures(n, seed), "pipeline": pipeline_figures(max(2, n // 4), seed),
            "big_frame": big_frame_figures(max(4, n // 4), seed), "frame_model": {
                "psf_sigma_px": MODEL.psf_sigma_px, "sky_e": MODEL.sky_e, "read_noise_e": MODEL.read_noise_e,
                "bits": MODEL.bits, "hot_pixels": MODEL.n_hot_pixels}}


def format_table(result: dict) -> str:
    def f(value, fmt="{:.3f}"):
        return "-" if value is None else fmt.format(value)

    lines = ["detector | completeness (2 mag above limit) | false / frame | hot px as stars | trail pieces as stars "
             "| SNR 50 centroid error median / RMS px | ms per Mpx",
             "--- | --- | --- | --- | --- | --- | ---"]
    for name, d in result["detectors"].items():
        lines.append(f"{name} | {100 * d['completeness_2mag_above_limit']:.1f} % of {d['bright_stars']} | "
                     f"{d['false_per_frame']:.2f} | {d['hot_pixels_as_stars']} | {d['trail_pieces_as_stars']} | "
                     f"{f(d['centroid_error_snr50_median_px'])} / {f(d['centroid_error_snr50_rms_px'])} "
                     f"({d['snr50_missed']} of {d['snr50_stars']} missed) | {d['ms_per_mpx']:.1f}")
    p = result["pipeline"]
    lines += ["", f"pipeline, {p['passes']} passes of 4 frames (hot-pixel map carried over): "
                  f"{p['hot_pixels_among_sources']} hot pixels among {p['sources_reported']} reported sources; "
                  f"{p['mapped_hot_pixels']} pixels mapped hot; {100 * p['brightest_stars_reported']:.1f} % of the "
                  f"{p['brightest_stars']} brightest stars 2 mag above the limit reported"]
    b = result["big_frame"]
    ours = b["ours"]
    lines += ["", f"2 Mpx frames ({b['frames']}, 1632 x 1224, 20 deg): ours detection + identification median "
                  f"{f(ours['median_ms'], '{:.1f}')} ms (detection {f(ours['detection_median_ms'], '{:.1f}')} ms), "
                  f"{ours['correct']}/{b['frames']} correct"]
    peer = b["peer"]
    if peer.get("measured"):
        lines.append(f"cedar-solve get_centroids_from_image + solve_from_centroids median {f(peer['median_ms'], '{:.1f}')} "
                     f"ms (centroids {f(peer['centroid_median_ms'], '{:.1f}')} ms), {peer['correct']}/{b['frames']} "
                     f"correct, {peer['claimed']} claimed")
    else:
        lines.append(f"cedar-solve: {peer['note']}")
    return "\n".join(lines)
