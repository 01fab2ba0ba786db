"""Issue 16's speed work changed how identification computes, never what it answers.

The fixture ``tests/data/identification_equivalence.json`` holds fixed
patterns (simulated with fixed seeds: single snapshots and averaged
sequences of the three cameras, sparse and ghost-ridden ones, a focal length
3 % off, undeclared distortion, random points) and what ``identify`` answered
for each *before* the speed work (the code of commit f36c8cc; written again
when the false-match probability was made honest about chance fits of a
few points, and a point took the brightest star within its tolerance): the
status, the number of hypotheses tried, and every candidate -- its stars,
attitude, false-match probability, deviation, fitted optics.  The answers today must be
the same (floats to rounding: another machine's BLAS may differ in the last
bits).  Regenerate only when identification is meant to change:
``python tests/test_speed_equivalence.py`` writes the fixture from the code
it runs with.

The other tests check the pieces against the plain computations they
replace: the batched refinement against one hypothesis at a time, the cell
map and the edge shortcut of the hypothesis check against the KD-tree.
"""

from __future__ import annotations

import json
import math
import os
from datetime import datetime, timedelta, timezone
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

FIXTURE = Path(__file__).parent / "data" / "identification_equivalence.json"


def _pattern(case: dict) -> SimpleNamespace:
    p = case["pattern"]
    return SimpleNamespace(xy=np.array(p["xy"], dtype=float).reshape(-1, 2),
                           vectors=np.array(p["vectors"], dtype=float).reshape(-1, 3),
                           sigma_px=np.array(p["sigma_px"], dtype=float),
                           brightness=np.array(p["brightness"], dtype=float),
                           track_ids=np.array(p["track_ids"], dtype=int))


def _camera(case: dict):
    from app.camera import Camera

    return Camera(**case["camera"])


def _answer(solution) -> dict:
    """What is compared: everything identification decides, and the numbers it reports."""
    return {"status": solution.status, "notes": list(solution.notes),
            "candidates": [{
                "rank": c.rank, "hips": [m.hip for m in c.matches], "pattern_index": [m.pattern_index for m in c.matches],
                "rotation": np.asarray(c.rotation_matrix).ravel().tolist(),
                "false_match_probability": c.false_match_probability, "deviation_arcsec": c.deviation_arcsec,
                "rms_arcsec": c.rms_arcsec, "n_hypotheses_merged": c.n_hypotheses_merged,
                "generating_edge": list(c.generating_edge), "generating_pair_hip": list(c.generating_pair_hip),
                "sigma_cross_boresight_arcsec": c.sigma_cross_boresight_arcsec,
                "sigma_roll_arcsec": c.sigma_roll_arcsec,
                "camera_focal_length_px": None if c.camera is None else c.camera.focal_length_px,
                "fitted": None if c.camera_fit is None else c.camera_fit.camera.optics(),
            } for c in solution.candidates]}


def _identify(case: dict, sky):
    from app.identification import identify

    t = datetime.fromisoformat(case["time"])
    return identify(_pattern(case), _camera(case), t, sky)


def _close(a, b, rel: float, abs_: float = 0.0) -> bool:
    if a is None or b is None:
        return a is b
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return math.isclose(a, b, rel_tol=rel, abs_tol=abs_)


@pytest.fixture(scope="module")
def cases() -> list[dict]:
    return json.loads(FIXTURE.read_text())["cases"]


def test_the_fixture_covers_every_kind_of_answer(cases):
    statuses = {c["expected"]["status"] for c in cases}
    assert statuses == {"identified", "ambiguous", "no_match"}
    assert len(cases) >= 35
    assert any(c["expected"]["candidates"] and c["expected"]["candidates"][0]["camera_focal_length_px"]
               for c in cases)  # the focal-length search found and adopted other optics somewhere


def test_identification_answers_as_before_the_speed_work(cases, sky):
    differences = []
    for case in cases:
        now, before = _answer(_identify(case, sky)), case["expected"]
        name = case["name"]
        if now["status"] != before["status"] or now["notes"] != before["notes"]:
            differences.append(f"{name}: {before['status']} {before['notes']} -> {now['status']} {now['notes']}")
            continue
        if len(now["candidates"]) != len(before["candidates"]):
            differences.append(f"{name}: {len(before['candidates'])} candidates -> {len(now['candidates'])}")
            continue
        for c, e in zip(now["candidates"], before["candidates"]):
            exact = ("rank", "hips", "pattern_index", "n_hypotheses_merged", "generating_edge", "generating_pair_hip")
            for key in exact:
                if c[key] != e[key]:
                    differences.append(f"{name} rank {e['rank']} {key}: {e[key]} -> {c[key]}")
            if not np.allclose(c["rotation"], e["rotation"], rtol=0, atol=1e-11):
                differences.append(f"{name} rank {e['rank']}: rotation moved by "
                                   f"{np.max(np.abs(np.subtract(c['rotation'], e['rotation']))):.2e}")
            for key in ("false_match_probability", "deviation_arcsec", "rms_arcsec", "sigma_cross_boresight_arcsec",
                        "sigma_roll_arcsec", "camera_focal_length_px"):
                if not _close(c[key], e[key], 1e-7, 1e-300):
                    differences.append(f"{name} rank {e['rank']} {key}: {e[key]} -> {c[key]}")
            if (c["fitted"] is None) != (e["fitted"] is None) or (
                    c["fitted"] and any(not _close(c["fitted"][k], e["fitted"][k], 1e-7, 1e-12) for k in e["fitted"])):
                differences.append(f"{name} rank {e['rank']} fitted optics: {e['fitted']} -> {c['fitted']}")
    assert not differences, "\n".join(differences)


def test_a_batch_of_refinements_is_each_refinement_alone(sky):
    """refine_many gives every hypothesis exactly what refine gives it alone, whatever else is in the batch."""
    from app.camera import CAMERAS
    from app.identification.candidates import prepare_pattern
    from app.identification.hypotheses import bright_pair_batches
    from app.identification.options import SearchOptions
    from app.identification.verify import check_hypotheses, refine, refine_many
    from app.simulate import simulate_sequence
    from app.extraction import extract

    checked, matched = 0, []
    for seed, scenario in ((3, "single"), (4, "ghosts3"), (5, "sparse")):
        camera = CAMERAS["tubsat-752x582-20deg"]
        sequence, _ = simulate_sequence(np.random.default_rng(seed), camera, scenario)
        extraction = extract(sequence)
        p = prepare_pattern(extraction.pattern, camera, sequence.snapshots[extraction.reference].time, sky)
        hyp, tol, _ = next(bright_pair_batches(p, sky, SearchOptions()))
        n_match, dev = check_hypotheses(hyp.rotations, p.vectors, p.field, tol)
        top = np.lexsort((dev, -n_match))[:24]
        batch = refine_many(hyp.rotations[top], p.vectors, p.weights, p.field, p.match_tol, tol[top])
        for k, h in enumerate(top):
            alone = refine(hyp.rotations[h], p.vectors, p.weights, p.field, p.match_tol, float(tol[h]))
            assert np.array_equal(batch[k].rotation, alone.rotation)
            assert np.array_equal(batch[k].star_of_point, alone.star_of_point)
            assert np.array_equal(batch[k].residual_rad, alone.residual_rad, equal_nan=True)
            assert np.array_equal(batch[k].nearest_rad, alone.nearest_rad)
            checked += 1
        matched += [r.n_matched for r in batch]
    assert checked == 72
    assert max(matched) >= 6 and min(matched) <= 4  # true attitudes and chance fits both took part


def test_the_compiled_check_is_checking_every_point_with_the_tree(sky):
    """check_hypotheses (the compiled loop over the cell map) against numpy and the KD-tree: every point of
    every hypothesis mapped onto the sky, its nearest star within the largest tolerance, counted and capped."""
    from app.camera import CAMERAS
    from app.identification.candidates import prepare_pattern
    from app.identification.hypotheses import bright_pair_batches
    from app.identification.options import SearchOptions
    from app.identification.verify import check_hypotheses, chord, chord_to_angle
    from app.simulate import simulate_sequence
    from app.extraction import extract

    for seed, name in ((11, "tubsat-752x582-20deg"), (12, "liebe-576x604-30deg"), (13, "narrow-1024x1024-12deg")):
        camera = CAMERAS[name]
        sequence, _ = simulate_sequence(np.random.default_rng(seed), camera, "single")
        extraction = extract(sequence)
        p = prepare_pattern(extraction.pattern, camera, sequence.snapshots[extraction.reference].time, sky)
        assert p.field.cells is not None
        batches = bright_pair_batches(p, sky, SearchOptions())
        for _ in range(2):
            hyp, tol, _ = next(batches)
            n_match, dev = check_hypotheses(hyp.rotations, p.vectors, p.field, tol)
            sky_points = np.matmul(p.vectors[None], hyp.rotations).reshape(-1, 3)
            d, _ = p.field.tree.query(sky_points, k=1, distance_upper_bound=float(chord(np.max(tol))))
            ang = chord_to_angle(np.where(np.isfinite(d), d, 2.0)).reshape(len(hyp), -1)
            assert np.array_equal(n_match, (ang <= tol[:, None]).sum(axis=1))
            np.testing.assert_allclose(dev, np.minimum(ang, tol[:, None]).sum(axis=1), rtol=1e-12)
            assert np.isfinite(d).mean() > 0.15  # the edges' own stars, and chance neighbours
            assert n_match.max() >= 5 and n_match.min() <= 2  # the true attitude and chance ones both checked


@pytest.mark.parametrize("year", [1905, 2000, 2097])
def test_the_cell_map_answers_as_a_bounded_tree_query_at_any_epoch(sky, year):
    """One map, made from the index's epoch, serves any observation time within a century of it."""
    from app.identification.verify import chord

    t = datetime(year, 7, 1, 13, tzinfo=timezone.utc)
    field = sky.field(t, 6.25, velocity_km_s=[6.0, -3.0, 4.0])
    rng = np.random.default_rng(year)
    anywhere = rng.normal(size=(40000, 3))
    near_stars = field.vectors[rng.integers(0, len(field.vectors), 40000)] + rng.normal(scale=0.003, size=(40000, 3))
    points = np.vstack([anywhere, near_stars])
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    for radius in (0.0021, 0.0047):
        cells = field.cells(radius)
        assert cells.radius_rad >= radius
        bound = float(chord(radius))
        d, _ = field.tree.query(points, k=1, distance_upper_bound=bound)
        assert np.array_equal(cells.nearest_within(points, field.vectors, bound), d)
        assert not (np.isfinite(d) & ~cells.maybe_near(points)).any()
    # The nearest star however far: the tree's chords, from the far map within its radius and through the stars'
    # places at the index epoch beyond it (the five points farthest from any star are there).
    assert field.epoch_places is not None
    everywhere = field.tree.query(points, k=1)[0]
    some = np.vstack([points[::40], points[np.argsort(everywhere)[-5:]]])
    expected = field.tree.query(some, k=1)[0]
    assert (expected > chord(field.far_radius())).any() and (expected <= chord(field.far_radius())).any()
    assert np.array_equal(field.nearest_chords(some), expected)
    # Each edge star is the nearest star of every point closer to it than alone_within.
    stars = rng.integers(0, len(field.vectors), 3000)
    offset = rng.normal(size=(3000, 3))
    offset -= (offset * field.vectors[stars]).sum(axis=1, keepdims=True) * field.vectors[stars]
    offset *= (field.alone_within[stars] * 0.999 / np.linalg.norm(offset, axis=1))[:, None]
    _, nearest = field.tree.query(field.vectors[stars] + offset, k=1)
    assert np.array_equal(nearest, stars)


def test_the_brightest_star_within_reach_is_the_trees_from_any_larger_cell_map(sky):
    """``brightest_within`` on a cell map of a larger radius (the one a search made already) names the star the
    KD-tree's four nearest within the tolerance name: the brightest of them, the nearest of equals."""
    from app.identification.verify import NEIGHBOURS_LOOKED_AT, StarField, brightest_within, chord

    t = datetime(2026, 3, 1, 5, tzinfo=timezone.utc)
    field = sky.field(t, 6.5)
    rng = np.random.default_rng(11)
    # Points near stars, and near the tight groups where four nearest and the magnitudes both matter.
    near = field.vectors[rng.integers(0, len(field.vectors), 20000)] + rng.normal(scale=0.002, size=(20000, 3))
    points = near / np.linalg.norm(near, axis=1, keepdims=True)
    field.cells(0.0047)  # a search's map, larger than the tolerances below
    tree_only = StarField(vectors=field.vectors, rows=field.rows, mag=field.mag)
    for tolerance in (0.0007, 0.0021, 0.0047):
        assert field.cells(tolerance, make=False) is not None
        by_cells = brightest_within(points, field, tolerance)
        by_tree = brightest_within(points, tree_only, tolerance)
        assert np.array_equal(by_cells, by_tree)
        assert (by_cells >= 0).sum() > 1000
        # ... and the tree's answer is what it says: within reach, the brightest of the nearest four.
        named = np.flatnonzero(by_tree >= 0)[:200]
        d, rows = field.tree.query(points[named], k=NEIGHBOURS_LOOKED_AT, distance_upper_bound=float(chord(tolerance)))
        for i, row in zip(named, rows):
            reach = row[row < len(field.vectors)]
            assert field.mag[by_tree[i]] == field.mag[reach].min()


def test_cell_maps_are_kept_on_disk_and_a_damaged_one_is_made_again(sky, tmp_path, monkeypatch):
    from app.identification import Sky
    from app.identification.cells import NearStarCells

    monkeypatch.setenv("STARID_CACHE_DIR", str(tmp_path))
    fresh = Sky(index=sky.index, catalogue=sky.catalogue)
    made = fresh.near_star_cells(2000, 0.004)
    files = list(tmp_path.glob("near-star-cells-*.npz"))
    assert len(files) == 1
    assert fresh.near_star_cells(2000, 0.0035) is made  # within twice the radius: the same map
    loaded = Sky(index=sky.index, catalogue=sky.catalogue).near_star_cells(2000, 0.004)
    for key, value in made.arrays().items():
        assert np.array_equal(loaded.arrays()[key], value)
    files[0].write_bytes(b"not a cell map")
    again = Sky(index=sky.index, catalogue=sky.catalogue).near_star_cells(2000, 0.004)
    assert isinstance(again, NearStarCells) and np.array_equal(again.arrays()["stars"], made.arrays()["stars"])
    # At most MAX_CACHED_FILES maps stay on disk, the newest.
    from app.identification.sky import MAX_CACHED_FILES

    for k in range(MAX_CACHED_FILES + 3):
        stale = tmp_path / f"near-star-cells-stale{k:02d}.npz"
        stale.write_bytes(b"old")
        os.utime(stale, (1e9 + k, 1e9 + k))
    Sky(index=sky.index, catalogue=sky.catalogue).near_star_cells(1500, 0.004)  # a new map: written, then pruned
    left = sorted(f.name for f in tmp_path.glob("near-star-cells-*.npz"))
    assert len(left) == MAX_CACHED_FILES and not any("stale00" in f or "stale03" in f for f in left)


# --- writing the fixture -------------------------------------------------------------------------------

def _cases_to_record() -> list[tuple[str, object, object, object]]:
    """(name, camera, time, pattern) of every fixture case, simulated with fixed seeds."""
    from app.camera import CAMERAS
    from app.extraction import extract
    from app.simulate import simulate_sequence, true_optics

    out = []
    plan = [("tubsat-752x582-20deg", "single", 8), ("tubsat-752x582-20deg", "nominal", 4),
            ("tubsat-752x582-20deg", "sparse", 3), ("tubsat-752x582-20deg", "ghosts3", 2),
            ("liebe-576x604-30deg", "single", 3), ("liebe-576x604-30deg", "nominal", 2),
            ("narrow-1024x1024-12deg", "single", 3), ("narrow-1024x1024-12deg", "sparse", 2),
            ("tubsat-752x582-20deg", "earth", 4), ("liebe-576x604-30deg", "earth", 2)]
    for name, scenario, count in plan:
        rng = np.random.default_rng([16, len(name), len(scenario)])
        for i in range(count):
            sequence, _ = simulate_sequence(rng, CAMERAS[name], scenario)
            extraction = extract(sequence)
            out.append((f"{name}/{scenario}/{i}", sequence.camera, sequence.snapshots[extraction.reference].time,
                        extraction.pattern))
    camera = CAMERAS["tubsat-752x582-20deg"]
    rng = np.random.default_rng([16, 3])
    for i, (focal, k1) in enumerate(((0.03, None), (-0.03, None), (0.0, 0.01 / camera.corner_radius ** 2))):
        sequence, _ = simulate_sequence(rng, camera, "single", true_camera=true_optics(camera, focal_error=focal, k1=k1))
        extraction = extract(sequence)
        out.append((f"optics/{i}", sequence.camera, sequence.snapshots[extraction.reference].time, extraction.pattern))
    for i in range(4):  # points where no stars are
        xy = np.column_stack([rng.uniform(0, camera.width - 1, 8), rng.uniform(0, camera.height - 1, 8)])
        pattern = SimpleNamespace(xy=xy, vectors=camera.pixels_to_vectors(xy), sigma_px=np.full(8, 0.3),
                                  brightness=np.linspace(200, 100, 8), track_ids=np.arange(8))
        out.append((f"random/{i}", camera, datetime(2004, 5, 6, 7, tzinfo=timezone.utc) + timedelta(days=40 * i),
                    pattern))
    return out


def write_fixture(path: Path = FIXTURE) -> None:
    from app.identification import Sky

    sky = Sky()
    cases = []
    for name, camera, t, pattern in _cases_to_record():
        case = {"name": name, "camera": {k: v for k, v in camera.to_dict().items() if v is not None},
                "time": t.isoformat(),
                "pattern": {"xy": np.asarray(pattern.xy).tolist(), "vectors": np.asarray(pattern.vectors).tolist(),
                            "sigma_px": np.asarray(pattern.sigma_px, dtype=float).tolist(),
                            "brightness": np.asarray(pattern.brightness, dtype=float).tolist(),
                            "track_ids": np.asarray(pattern.track_ids).astype(int).tolist()}}
        case["expected"] = _answer(_identify(case, sky))
        cases.append(case)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"made_by": "tests/test_speed_equivalence.py:write_fixture", "cases": cases}) + "\n")


if __name__ == "__main__":
    write_fixture()
    print(f"wrote {FIXTURE}")
