"""Liebe's triangle-feature database and initial estimate (app.identification.triangle_features)."""

from __future__ import annotations

import os
import json
import math
from datetime import datetime, timezone
from types import SimpleNamespace

import numpy as np
import pytest

from app.attitude import rotation_from_radec_roll
from app.camera import CAMERAS
from app.identification import IDENTIFIED, identify
from app.identification.triangle_features import (
    N_ANGLE_CLASSES, TFParameters, candidate_assignments, class_keys,
    database_for, load_tf_database, neighbour_constellations, pattern_features, quantised_entries,
    rim_distance, triangle_features)

LIEBE = CAMERAS["liebe-576x604-30deg"]
T = datetime(2025, 1, 1, tzinfo=timezone.utc)
ARCMIN = math.radians(1 / 60)


def at(ra_deg: float, dec_deg: float) -> np.ndarray:
    ra, dec = math.radians(ra_deg), math.radians(dec_deg)
    return np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])


def liebe_params(**kw) -> TFParameters:
    """Liebe's numbers: 3 arcmin largest position error, no extra margin (tolerance exactly 0.1 deg)."""
    base = dict(mag_certain=4.0, mag_faintest=5.0, position_error_rad=3 * ARCMIN, radius_rad=math.radians(15.0),
                min_separation_rad=math.radians(0.01), margin_rad=0.0)
    base.update(kw)
    return TFParameters(**base)


# --------------------------------------------------------------------------
# Features and quantisation
# --------------------------------------------------------------------------
def test_features_of_a_hand_built_triplet():
    pole = np.array([0.0, 0.0, 1.0])
    a = at(0.0, 88.0)  # 2 deg from the pole towards +x
    b = at(90.0, 87.0)  # 3 deg towards +y
    d1, d2, angle = triangle_features(pole, a, b)[0]
    assert math.degrees(d1) == pytest.approx(2.0, abs=1e-9)
    assert math.degrees(d2) == pytest.approx(3.0, abs=1e-9)
    # Seen from inside the sphere towards +z, +x -> +y is a quarter turn: +90 deg;
    # the mirror image (b on -y) is the other sense.
    assert math.degrees(angle) == pytest.approx(90.0, abs=1e-9)
    mirrored = triangle_features(pole, a, at(270.0, 87.0))[0]
    assert math.degrees(mirrored[2]) == pytest.approx(270.0, abs=1e-9)
    # A rotation keeps the feature (it cannot mirror).
    R = rotation_from_radec_roll(123.0, -40.0, 77.0)
    turned = triangle_features(R @ pole, R @ a, R @ b)[0]
    np.testing.assert_allclose(turned, [d1, d2, angle], atol=1e-12)


def test_liebe_example_star_gets_his_eighteen_entries():
    """Liebe's worked example: 5.596, 8.191 deg, 164.204 deg -> d1 54-56, d2 80-82, angle 32-33."""
    params = liebe_params()
    assert math.degrees(params.distance_class_rad) == pytest.approx(0.1)
    feature = np.radians([[5.596, 8.191, 164.204]])
    keys, rows = quantised_entries(feature, params)
    assert set(rows) == {0}
    nd = params.n_distance_classes
    classes = {(int(k // N_ANGLE_CLASSES // nd), int(k // N_ANGLE_CLASSES % nd), int(k % N_ANGLE_CLASSES))
               for k in keys}
    expected = {(c1, c2, c3) for c1 in (54, 55, 56) for c2 in (80, 81, 82) for c3 in (32, 33)}
    assert classes == expected
    assert len(keys) == 18
    # The star's own measured class is one of them: a measurement within the uncertainty finds it.
    assert class_keys(feature, params)[0] in set(keys)


def test_quantised_box_covers_every_measurement_within_tolerance():
    params = liebe_params()
    rng = np.random.default_rng(3)
    n = 300
    d1 = rng.uniform(0.5, 6.0, n)
    feats = np.radians(np.column_stack([d1, d1 + rng.uniform(0.0, 6.0, n), rng.uniform(0.0, 360.0, n)]))
    keys, rows = quantised_entries(feats, params)
    tol = params.distance_tolerance_rad
    # Perturb each feature to the corners of its tolerance box (slightly inside).
    tol_a = tol / np.sin(feats[:, 0]) + tol / np.sin(feats[:, 1])
    for s1 in (-1, 1):
        for s2 in (-1, 1):
            for s3 in (-1, 1):
                meas = feats + 0.999 * np.column_stack([s1 * tol * np.ones(n), s2 * tol * np.ones(n), s3 * tol_a])
                meas[:, 2] %= 2 * np.pi
                mk = class_keys(meas, params)
                for i in range(n):
                    assert mk[i] in set(keys[rows == i])
    # Far outside the box: a different class.
    far = feats.copy()
    far[:, 0] += 3 * tol
    mk = class_keys(far, params)
    assert all(mk[i] not in set(keys[rows == i]) for i in range(n))


def test_neighbour_constellations_certain_maybe_and_exchange():
    """Hand-built: around the pole, A 2 deg (maybe), B 3 deg, D 3.05 deg (within 2 tol of B), C 4 deg."""
    params = liebe_params(position_error_rad=1 * ARCMIN)  # tol = 2 arcmin = 0.033 deg, 2 tol = 0.067 deg
    vectors = np.array([[0.0, 0.0, 1.0], at(0, 88.0), at(100, 87.0), at(200, 86.0), at(300, 86.95)])
    mag = np.array([1.0, 4.8, 3.0, 3.0, 3.0])  # A is "maybe", B C D "certain"
    star, first, second = neighbour_constellations(vectors, mag, params)
    A, B, C, D = 1, 2, 3, 4
    got = {(int(f), int(s)) for st, f, s in zip(star, first, second) if st == 0}
    # (A, C) needs B and D missing - both certain; (B, C) needs D missing.
    # (B, D) needs A missing (maybe): fine, and B/D may swap.  (A, D): B may be measured beyond D.
    assert got == {(A, B), (A, D), (B, D), (D, B)}
    assert not any(C in pair for pair in got)
    # With no missing neighbour allowed, (B, D) and (D, B) go.
    star, first, second = neighbour_constellations(vectors, mag, liebe_params(position_error_rad=ARCMIN,
                                                                               max_missing=0))
    assert {(int(f), int(s)) for st, f, s in zip(star, first, second) if st == 0} == {(A, B), (A, D)}
    # When A is certain too, only it and its true second neighbours remain.
    star, first, second = neighbour_constellations(vectors, np.array([1.0, 3.0, 3.0, 3.0, 3.0]),
                                                   liebe_params(position_error_rad=ARCMIN))
    assert {(int(f), int(s)) for st, f, s in zip(star, first, second) if st == 0} == {(A, B), (A, D)}


def test_rim_distance():
    centre = LIEBE.pixels_to_vectors([[LIEBE.cx, LIEBE.cy]])
    # The 576 px side spans 30 deg: 15 deg from the centre to the nearer edges.
    assert math.degrees(rim_distance(centre, LIEBE)[0]) == pytest.approx(15.0, abs=0.01)
    edge = LIEBE.pixels_to_vectors([[-0.5, LIEBE.cy], [LIEBE.cx, LIEBE.height - 0.5]])
    np.testing.assert_allclose(rim_distance(edge, LIEBE), 0.0, atol=1e-9)
    # 10 px inside the left edge, half way down: on the central row the nearest rim point is straight left.
    v = LIEBE.pixels_to_vectors([[9.5, LIEBE.cy]])
    to_edge_px = LIEBE.cx + 0.5  # the rim is the outer side of pixel column 0
    expected = (math.atan(to_edge_px / LIEBE.focal_length_px)
                - math.atan((to_edge_px - 10) / LIEBE.focal_length_px))
    assert rim_distance(v, LIEBE)[0] == pytest.approx(expected, rel=1e-6)


# --------------------------------------------------------------------------
# The catalogue database
# --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def liebe_db(sky):
    params = TFParameters.for_camera(LIEBE, catalogue_mag_limit=sky.index.mag_limit)
    return database_for(params, sky.index)


def brute_force_triplets(vectors, mag, params, rows):
    """Each given star's true first and second neighbour among all detectable stars (numpy, no tree)."""
    out = []
    for s in rows:
        ang = np.arccos(np.clip(vectors @ vectors[s], -1, 1))
        ang[s] = np.inf
        ang[ang < params.min_separation_rad] = np.inf
        a, b = np.argsort(ang)[:2]
        if ang[b] <= params.radius_rad:
            out.append((s, a, b))
    return out


def test_database_finds_stars_from_exact_and_perturbed_features(liebe_db, sky):
    params = liebe_db.params
    v, mag = sky.index.vectors[:liebe_db.n_stars], sky.index.mag[:liebe_db.n_stars]
    assert mag.max() <= params.mag_faintest
    rng = np.random.default_rng(11)
    rows = rng.choice(liebe_db.n_stars, 150, replace=False)
    triplets = brute_force_triplets(v, mag, params, rows)
    assert len(triplets) > 100
    e = params.position_error_rad
    for trial in range(3):
        found = 0
        for s, a, b in triplets:
            pts = v[[s, a, b]]
            if trial:  # each position moved by up to the largest error, in a random direction
                step = rng.normal(size=(3, 3))
                step -= np.sum(step * pts, axis=1, keepdims=True) * pts
                step *= (rng.uniform(0.2, 0.99, 3) * e / np.linalg.norm(step, axis=1))[:, None]
                pts = pts + step
                pts /= np.linalg.norm(pts, axis=1, keepdims=True)
            feature = triangle_features(pts[0], pts[1], pts[2])
            want = (s, a, b)
            if feature[0, 0] > feature[0, 1]:  # nearly equal distances swapped by the errors:
                feature = triangle_features(pts[0], pts[2], pts[1])  # the exchange entry must cover it
                want = (s, b, a)
            _, nbc = liebe_db.lookup(class_keys(feature, params))
            hits = set(zip(liebe_db.nbc_star[nbc].tolist(), liebe_db.nbc_first[nbc].tolist(),
                           liebe_db.nbc_second[nbc].tolist()))
            found += want in hits
        assert found == len(triplets), f"trial {trial}: {found} of {len(triplets)}"


def test_database_is_cached_on_disk_and_rebuilt_when_damaged(sky, tmp_path):
    params = TFParameters.for_camera(CAMERAS["narrow-1024x1024-12deg"], catalogue_mag_limit=sky.index.mag_limit)
    built = load_tf_database(params, sky.index, cache_dir=tmp_path)
    files = list(tmp_path.glob("triangle-features-*.npz"))
    assert len(files) == 1
    again = load_tf_database(params, sky.index, cache_dir=tmp_path)
    np.testing.assert_array_equal(built.keys, again.keys)
    np.testing.assert_array_equal(built.entry_nbc, again.entry_nbc)
    assert np.all(np.diff(built.keys) >= 0)
    files[0].write_bytes(b"not a zip file")
    rebuilt = load_tf_database(params, sky.index, cache_dir=tmp_path)
    np.testing.assert_array_equal(built.keys, rebuilt.keys)
    # Other parameters, another file.
    load_tf_database(TFParameters(**{**params.__dict__, "max_missing": 1}), sky.index, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("triangle-features-*.npz"))) == 2


# --------------------------------------------------------------------------
# The initial estimate
# --------------------------------------------------------------------------
def test_initial_estimate_identifies_random_snapshots(sky):
    from app.bench.seeds import SITUATIONS, StarSky, boresight_error_deg, make_trial
    from app.identification import SearchOptions

    star_sky = StarSky.at(T)
    rng = np.random.default_rng(2024)
    options = SearchOptions(max_points=40)
    params = TFParameters.for_camera(LIEBE, catalogue_mag_limit=sky.index.mag_limit)
    db = database_for(params, sky.index)
    n, correct, wrong_identified, lookups, true_found = 30, 0, 0, 0, 0
    field = sky.field(T, 5.25)
    for _ in range(n):
        pattern, R, _ = make_trial(rng, star_sky, LIEBE, SITUATIONS[0])
        sol = identify(pattern, LIEBE, T, sky, options=options, method="tf")
        ok = boresight_error_deg(sol, R) <= 0.1
        correct += ok
        wrong_identified += sol.status == IDENTIFIED and not ok
        # Independently: each usable point's true star is among its looked-up candidates.
        pf = pattern_features(pattern.vectors, LIEBE, params)
        asg = candidate_assignments(pf, db, sky.index.vectors)
        _, nearest = field.tree.query(pattern.vectors[pf.points] @ R)
        truth = field.rows[nearest]
        for point, star in zip(pf.points, truth):
            lookups += 1
            true_found += star in set(asg.star[asg.point == point].tolist())
    assert correct >= 0.85 * n
    assert wrong_identified == 0
    assert lookups > 3 * n
    assert true_found >= 0.9 * lookups


def test_random_points_are_not_identified(sky):
    rng = np.random.default_rng(5)
    for _ in range(10):
        xy = np.column_stack([rng.uniform(0, LIEBE.width - 1, 15), rng.uniform(0, LIEBE.height - 1, 15)])
        pattern = SimpleNamespace(xy=xy, vectors=LIEBE.pixels_to_vectors(xy), sigma_px=np.full(15, 0.2),
                                  brightness=np.ones(15), track_ids=np.arange(15))
        assert identify(pattern, LIEBE, T, sky, method="tf").status != IDENTIFIED


def test_pattern_features_rim_rule():
    # Three points near the left edge and one far away: only points whose second neighbour is
    # nearer than the rim are used.
    xy = np.array([[300.0, 300.0], [330.0, 300.0], [300.0, 340.0], [5.0, 300.0]])
    params = TFParameters.for_camera(LIEBE)
    pf = pattern_features(LIEBE.pixels_to_vectors(xy), LIEBE, params)
    assert sorted(pf.points.tolist()) == [0, 1, 2]
    assert dict(zip(pf.points.tolist(), pf.first.tolist()))[0] == 1
    assert dict(zip(pf.points.tolist(), pf.second.tolist()))[0] == 2
    assert pattern_features(LIEBE.pixels_to_vectors(xy[:2]), LIEBE, params).points.size == 0


def test_solve_cli_methods(sample_dir, capsys):
    from app.cli import build_parser, solve

    def parsed(*argv):  # the command line's own parser, so every option has its default
        return build_parser().parse_args(["solve", *argv])

    path = str(sample_dir / "01-clean.json")
    args = parsed(path, "--json", "--method", "both")
    assert solve.run(args) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("file", "sequence_id", "status", "error", "reference_snapshot", "sources", "candidates"):
        assert key in doc
    assert doc["methods_agree"] is True
    assert doc["tf_candidates"] and doc["candidates"]
    args = parsed(path, "--json", "--method", "tf")
    assert solve.run(args) == 0
    tf_doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert tf_doc["tf_candidates"] is None and tf_doc["methods_agree"] is None
    # The Earth: neither method finds a match, so they agree (the bright-pair method keeps a few chance fits
    # for the operator to see, which once read as a disagreement).
    args = parsed(str(sample_dir / "05-earth.json"), "--json", "--method", "both")
    assert solve.run(args) == 0
    earth = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (earth["status"], earth["tf_status"], earth["methods_agree"]) == ("no_match", "no_match", True)
    assert earth["candidates"]
    # Both answers are the simulated truth (the sample's reference snapshot).
    truth = json.loads((sample_dir / "01-clean.truth.json").read_text())
    ra, dec, _ = truth["radec_roll_deg"][doc["reference_snapshot"]]
    for c in (doc["candidates"][0], doc["tf_candidates"][0], tf_doc["candidates"][0]):
        assert math.degrees(math.acos(min(1.0, at(ra, dec) @ at(c["ra_deg"], c["dec_deg"])))) < 0.1


def test_the_disk_cache_keeps_a_bounded_number_of_databases(tmp_path):
    from app.identification.triangle_features import MAX_CACHED_DATABASES, prune_tf_cache

    paths = []
    for k in range(MAX_CACHED_DATABASES + 5):
        path = tmp_path / f"triangle-features-{k:04d}.npz"
        path.write_bytes(b"x")
        os.utime(path, (1_000_000 + k, 1_000_000 + k))
        paths.append(path)
    oldest = paths[0]
    prune_tf_cache(tmp_path, keep=oldest)
    left = sorted(tmp_path.glob("triangle-features-*.npz"))
    assert oldest in left and len(left) == MAX_CACHED_DATABASES + 1
    assert set(paths[-MAX_CACHED_DATABASES:]) <= set(left)


def test_a_pattern_too_sparse_for_triangle_features_says_so(sky, sample_dir):
    """06-sparse: no point has both nearest neighbours nearer than the sensor's edge (Liebe's rim rule), so
    the method has no feature at all; the search said only "0 tf hypotheses from 0 pattern features", which
    reads as a sky that fits nothing.  Its notes now say why, and what needs no such neighbours."""
    from app.identification import solve_sequence
    from app.telemetry import load_telemetry_file

    def notes(name):
        solved = solve_sequence(load_telemetry_file(sample_dir / name), sky, method="tf")
        return solved.solution.status, solved.solution.notes

    status, sparse = notes("06-sparse.json")
    assert status == "no_match"
    assert any("too sparse for this method; bright pairs need no such neighbours" in n for n in sparse)
    status, dense = notes("01-clean.json")
    assert status == "identified" and not any("too sparse" in n for n in dense)
