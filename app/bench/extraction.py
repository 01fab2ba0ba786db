"""Extraction benchmark: stars kept, ghosts and hot pixels rejected, speed.

One table per simulator scenario: "ghosts" (1-3 ghosts per snapshot, 0-2
hot pixels) and "ghosts3" (exactly 3 ghosts in every snapshot of 10
sources, 0-2 hot pixels: the worst case benchmarked), each with
``n_sequences`` sequences (300: 100 per camera) cycling through the cameras
of :data:`app.camera.CAMERAS`, drawn from ``[seed, i]``; the truth says what
every source is.  A scenario's sequences are simulated first, then
extracted in one process, each timed alone with ``time.perf_counter``
(after one warm-up call).

Figures:

* ``star_sources_kept``: fraction of star sources that got a track;
  ``trackable_star_sources_kept``: the same over stars the sensor reported
  in at least two snapshots (a star reported once is indistinguishable
  from a ghost by any tracking method);
* ``ghosts_hot_pixels_rejected``: fraction of ghost and hot-pixel sources
  with no track (also per kind, and how often the reason was the right one);
* ``track_purity``: fraction of tracks whose sources are all one object,
  and ``tracked_sources_pure``: fraction of tracked sources belonging to
  their track's majority object;
* ``median_ms``/``p95_ms``: extraction time per sequence.
"""

from __future__ import annotations

import time
from collections import Counter

import numpy as np

from app.camera import CAMERAS
from app.extraction import extract


def _score(truth: dict, extraction) -> Counter:
    """Counts for one sequence against its truth."""
    c = Counter()
    sightings = Counter(label["object"] for labels in truth["sources"] for label in labels)
    members: dict[int, list[str]] = {}
    for s, labels in enumerate(truth["sources"]):
        for k, label in enumerate(labels):
            track = int(extraction.track_of_source[s][k])
            kind = label["kind"]
            if track >= 0:
                members.setdefault(track, []).append(label["object"])
            if kind == "star":
                c["stars"] += 1
                c["stars_kept"] += track >= 0
                if sightings[label["object"]] >= 2:
                    c["trackable_stars"] += 1
                    c["trackable_stars_kept"] += track >= 0
            elif kind in ("ghost", "hot_pixel"):
                c[kind] += 1
                c[f"{kind}_rejected"] += track < 0
                c[f"{kind}_reason_right"] += extraction.rejection[s][k] == kind
    for objects in members.values():
        c["tracks"] += 1
        c["pure_tracks"] += len(set(objects)) == 1
        c["tracked_sources"] += len(objects)
        c["tracked_sources_pure"] += Counter(objects).most_common(1)[0][1]
    return c


def _ratio(numerator: int, denominator: int) -> float | None:
    return round(numerator / denominator, 5) if denominator else None


def _figures(c: Counter, times_s: list[float]) -> dict:
    rejected = c["ghost_rejected"] + c["hot_pixel_rejected"]
    return {
        "sequences": len(times_s),
        "star_sources": c["stars"],
        "star_sources_kept": _ratio(c["stars_kept"], c["stars"]),
        "trackable_star_sources_kept": _ratio(c["trackable_stars_kept"], c["trackable_stars"]),
        "ghost_and_hot_pixel_sources": c["ghost"] + c["hot_pixel"],
        "ghosts_hot_pixels_rejected": _ratio(rejected, c["ghost"] + c["hot_pixel"]),
        "ghosts_rejected": _ratio(c["ghost_rejected"], c["ghost"]),
        "hot_pixels_rejected": _ratio(c["hot_pixel_rejected"], c["hot_pixel"]),
        "ghost_reason_right": _ratio(c["ghost_reason_right"], c["ghost"]),
        "hot_pixel_reason_right": _ratio(c["hot_pixel_reason_right"], c["hot_pixel"]),
        "track_purity": _ratio(c["pure_tracks"], c["tracks"]),
        "tracked_sources_pure": _ratio(c["tracked_sources_pure"], c["tracked_sources"]),
        "median_ms": round(1000 * float(np.median(times_s)), 3) if times_s else None,
        "p95_ms": round(1000 * float(np.percentile(times_s, 95)), 3) if times_s else None,
    }


#: The simulator's scenarios benchmarked, each a table.
SCENARIOS = ("ghosts", "ghosts3")


def run(n_sequences: int = 300, seed: int = 1, scenarios: tuple[str, ...] = SCENARIOS) -> dict:
    """:func:`run_scenario` for every scenario of ``scenarios``."""
    return {"seed": seed, "scenarios": {name: run_scenario(n_sequences, seed, name) for name in scenarios}}


def run_scenario(n_sequences: int = 300, seed: int = 1, scenario: str = "ghosts") -> dict:
    """Simulate ``n_sequences`` sequences (cameras in turn), extract them, and score."""
    from app.simulate import simulate_sequence

    cameras = list(CAMERAS.values())
    cases = []
    for i in range(n_sequences):
        camera = cameras[i % len(cameras)]
        sequence, truth = simulate_sequence(np.random.default_rng([seed, i]), camera, scenario=scenario)
        cases.append((camera.name, sequence, truth))
    if cases:
        extract(cases[0][1])  # warm-up: first-call costs are not per-sequence costs

    totals, per_camera = Counter(), {name: Counter() for name in CAMERAS}
    times, camera_times = [], {name: [] for name in CAMERAS}
    for name, sequence, truth in cases:
        t0 = time.perf_counter()
        extraction = extract(sequence)
        elapsed = time.perf_counter() - t0
        counts = _score(truth, extraction)
        totals += counts
        per_camera[name] += counts
        times.append(elapsed)
        camera_times[name].append(elapsed)
    return {
        "scenario": scenario,
        "seed": seed,
        "overall": _figures(totals, times),
        "per_camera": {name: _figures(per_camera[name], camera_times[name])
                       for name in CAMERAS if camera_times[name]},
    }


_ROWS = (
    ("sequences", "sequences", "{}"),
    ("star sources kept", "star_sources_kept", "{:.2%}"),
    ("  of stars seen >= 2 times", "trackable_star_sources_kept", "{:.2%}"),
    ("ghosts + hot pixels rejected", "ghosts_hot_pixels_rejected", "{:.2%}"),
    ("  ghosts rejected", "ghosts_rejected", "{:.2%}"),
    ("  hot pixels rejected", "hot_pixels_rejected", "{:.2%}"),
    ("  reason 'ghost' right", "ghost_reason_right", "{:.2%}"),
    ("  reason 'hot_pixel' right", "hot_pixel_reason_right", "{:.2%}"),
    ("track purity (tracks)", "track_purity", "{:.2%}"),
    ("track purity (sources)", "tracked_sources_pure", "{:.2%}"),
    ("median ms / sequence", "median_ms", "{:.2f}"),
    ("p95 ms / sequence", "p95_ms", "{:.2f}"),
)


def format_table(result: dict) -> str:
    """One table per scenario of :func:`run`'s result."""
    return "\n\n".join(format_scenario(figures) for figures in result["scenarios"].values())


def format_scenario(result: dict) -> str:
    """A plain-text table of one scenario: one column for all sequences, one per camera."""
    columns = [("all", result["overall"])] + list(result["per_camera"].items())
    width = max(12, *(len(name) for name, _ in columns))
    lines = [f"scenario {result['scenario']!r}, seed {result['seed']}",
             f"{'':30}" + "".join(f"{name:>{width + 2}}" for name, _ in columns)]
    for title, key, fmt in _ROWS:
        cells = [("-" if figures.get(key) is None else fmt.format(figures[key])) for _, figures in columns]
        lines.append(f"{title:30}" + "".join(f"{cell:>{width + 2}}" for cell in cells))
    return "\n".join(lines)
