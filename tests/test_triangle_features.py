"""Liebe's triangle-feature database and initial estimate (app.identification.triangle_features)."""

from __future__ import annotations

import os
import json
import math
from dataclasses import replace
from datetime import datetime, timezone
from types import SimpleNamespace

import numpy as np
import pytest

from app.attitude import rotation_from_radec_roll
from app.camera import CAMERAS
from app.identification import IDENTIFIED, SearchOptions, identify
from app.identification.candidates import prepare_pattern
from app.identification.triangle_features import (
    MIN_FIELD_STARS, N_ANGLE_CLASSES, TFParameters, build_tf_database, candidate_assignments, class_keys,
    database_for, detection_thresholds, field_solid_angle, load_tf_database, neighbour_constellations,
    pattern_features, quantised_entries, rim_distance, swept_bounds, tf_batches, triangle_features)

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


def test_rim_distance_is_negative_off_the_sensor_and_the_sweep_covers_tracked_points():
    """A tracked sequence's pattern holds points off the reference sensor.  The rim distance was
    ``arcsin |v . n|``, positive on either side of an edge: a point 20 px below the sensor was taken for
    one 20 px inside.  Now it is signed, and the rim is the sensor stretched to the pattern's points."""
    # On the central column the distance to the bottom side's great circle is the difference of the
    # elevations (a pinhole: atan of the offsets from the axis over the focal length).
    h, f, cy = LIEBE.height, LIEBE.focal_length_px, LIEBE.cy
    below = LIEBE.pixels_to_vectors([[LIEBE.cx, h - 0.5 + 20]])
    expected = math.atan2(h - 0.5 - cy, f) - math.atan2(h - 0.5 + 20 - cy, f)
    assert rim_distance(below, LIEBE)[0] == pytest.approx(expected, rel=1e-6)
    # Three close points just below the sensor (seen in other snapshots) and one far below them.
    xy = np.array([[300.0, h + 5], [330.0, h + 5], [300.0, h + 40], [300.0, h + 200]])
    v = LIEBE.pixels_to_vectors(xy)
    assert swept_bounds(v, LIEBE) == pytest.approx((-0.5, -0.5, LIEBE.width - 0.5, h + 200))
    # Inside the swept rectangle: 195 px from its bottom side (300.5 px from the left one).
    to_bottom = math.atan2(h + 200 - cy, f) - math.atan2(h + 5 - cy, f)
    assert rim_distance(v[:1], LIEBE, swept_bounds(v, LIEBE))[0] == pytest.approx(to_bottom, rel=0.02)
    params = TFParameters.for_camera(LIEBE)
    pf = pattern_features(v, LIEBE, params)
    assert 0 in pf.points.tolist()  # its two neighbours (30 and 35 px) lie where the sensor looked
    # The reference sensor alone knows nothing around it.
    assert rim_distance(v[:1], LIEBE)[0] < 0


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


def test_database_covers_a_sensor_that_reports_only_its_brightest_stars():
    """Around the pole (mag 2.0): five mag 3.8 stars within 1-2.5 deg, then A (mag 2.2) at 3 deg and B (mag
    2.5) at 4 deg.  A sensor of limit 4.5 sees the faint ones ("certain" at mag <= 4.0), so Liebe's single
    band enters no (A, B) constellation: five certain neighbours would be missing.  A sensor reporting only
    its three brightest sources sees exactly the pole, A and B; the band of that threshold has (A, B)."""
    faint = [at(ra, 90.0 - d) for ra, d in zip((20, 95, 160, 230, 300), (1.0, 1.4, 1.8, 2.2, 2.5))]
    vectors = np.array([[0.0, 0.0, 1.0], at(0.0, 87.0), at(120.0, 86.0), *faint])
    mag = np.array([2.0, 2.2, 2.5, 3.8, 3.8, 3.8, 3.8, 3.8])
    params = liebe_params(mag_certain=4.0, mag_faintest=5.0, field_fraction=1.0)  # the whole sky in view
    # Bands half a magnitude apart while the field holds >= 3 stars brighter than the band's middle:
    # the pole, A and B are the 3 stars brighter than 2.5, none is brighter than 2.0.
    assert detection_thresholds(mag, params) == [(4.0, 5.0), (3.5, 4.5), (3.0, 4.0), (2.5, 3.5), (2.0, 3.0)]
    db = build_tf_database(vectors, mag, params)
    feature = triangle_features(vectors[0], vectors[1], vectors[2])
    _, nbc = db.lookup(class_keys(feature, params))
    assert (0, 1, 2) in set(zip(db.nbc_star[nbc].tolist(), db.nbc_first[nbc].tolist(), db.nbc_second[nbc].tolist()))
    # Liebe's single threshold (no field given): not entered.
    liebe = build_tf_database(vectors, mag, liebe_params(mag_certain=4.0, mag_faintest=5.0))
    assert not np.any((liebe.nbc_star == 0) & (liebe.nbc_first == 1) & (liebe.nbc_second == 2))


def test_detection_thresholds_of_the_30_deg_camera(sky):
    params = TFParameters.for_camera(LIEBE, catalogue_mag_limit=sky.index.mag_limit)
    # The field's share of the sky, integrated pixel by pixel: dOmega = f dx dy / (f^2 + x^2 + y^2)^(3/2).
    f = LIEBE.focal_length_px
    x = np.arange(LIEBE.width) - (LIEBE.width - 1) / 2
    y = np.arange(LIEBE.height) - (LIEBE.height - 1) / 2
    omega = np.sum(f / (f ** 2 + x[None, :] ** 2 + y[:, None] ** 2) ** 1.5)
    assert field_solid_angle(LIEBE) == pytest.approx(omega, rel=1e-4)
    assert params.field_fraction == pytest.approx(omega / (4 * math.pi), rel=1e-4)
    bands = detection_thresholds(sky.index.mag, params)
    assert bands[0] == (4.0, 5.0)  # the camera's own: limit 4.5 -+ 0.5
    assert all(b == pytest.approx((a[0] - 0.5, a[1] - 0.5)) for a, b in zip(bands, bands[1:]))

    def field_stars(band):  # stars brighter than the band's middle in an average field
        return np.sum(sky.index.mag <= (band[0] + band[1]) / 2) * params.field_fraction

    assert field_stars(bands[-1]) >= MIN_FIELD_STARS > field_stars((bands[-1][0] - 0.5, bands[-1][1] - 0.5))
    assert len(bands) >= 3


def test_sequences_of_a_rich_field_are_identified(sky):
    """Canis Major: the sensor's 10 brightest sources per snapshot reach only mag ~3 of the 30 deg camera's
    4.5, so every point has more unreported "certain" neighbours than a band allows; with Liebe's single
    band none of these sequences was identified (no feature found its constellation)."""
    from app.bench.identification import is_correct
    from app.identification import solve_sequence
    from app.simulate import simulate_sequence

    rng = np.random.default_rng(28)
    for roll in (0.0, 120.0, 240.0):
        sequence, truth = simulate_sequence(rng, LIEBE, "nominal", pointing=(97.0, -29.0, roll))
        solved = solve_sequence(sequence, sky, method="tf")
        R_true = np.asarray(truth["rotation_matrices"][solved.extraction.reference])
        assert solved.solution.status == IDENTIFIED, solved.solution.notes
        assert is_correct(solved.solution.candidates[0].rotation_matrix, R_true)[0]


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
    """A pattern where no point has both nearest neighbours nearer than the sensor's edge (Liebe's rim rule)
    gives the method no feature at all, and its notes say why, and what needs no such neighbours.  A
    pattern whose features fit no constellation says that instead: 06-sparse (the 5 brightest stars of the
    view) was said to be too sparse, but its centre point has a feature, whose faint neighbours the sensor
    did not report; the bands of brighter thresholds hold it, and the method identifies the sequence."""
    from app.bench.identification import is_correct
    from app.identification import solve_sequence
    from app.telemetry import load_telemetry_file

    corners = np.array([[20.0, 20.0], [555.0, 20.0], [20.0, 583.0], [555.0, 583.0]])
    pattern = SimpleNamespace(xy=corners, vectors=LIEBE.pixels_to_vectors(corners), sigma_px=np.full(4, 0.2),
                              brightness=np.ones(4), track_ids=np.arange(4))
    sol = identify(pattern, LIEBE, T, sky, method="tf")
    assert sol.status == "no_match"
    assert any("too sparse for this method; bright pairs need no such neighbours" in n for n in sol.notes)
    # A triangle in the middle gives features; when none fits a visible constellation (here: no star
    # visible at all), the generator still counts them, so the search does not call the pattern too sparse.
    centre = np.array([[LIEBE.cx, LIEBE.cy], [LIEBE.cx + 30, LIEBE.cy], [LIEBE.cx, LIEBE.cy + 40]])
    xy = np.vstack([corners, centre])
    pattern = SimpleNamespace(xy=xy, vectors=LIEBE.pixels_to_vectors(xy), sigma_px=np.full(7, 0.2),
                              brightness=np.ones(7), track_ids=np.arange(7))
    params = TFParameters.for_camera(LIEBE, catalogue_mag_limit=sky.index.mag_limit)
    n_features = pattern_features(pattern.vectors, LIEBE, params).points.size
    assert n_features == 3
    prepared = prepare_pattern(pattern, LIEBE, T, sky)
    blind = replace(prepared, star_mask=np.zeros_like(prepared.star_mask))
    batches = list(tf_batches(blind, sky, SearchOptions()))
    assert [(len(hyp), used) for hyp, _, used in batches] == [(0, n_features)]

    sequence = load_telemetry_file(sample_dir / "06-sparse.json")
    solved = solve_sequence(sequence, sky, method="tf")
    truth = json.loads((sample_dir / "06-sparse.truth.json").read_text())
    R_true = np.asarray(truth["rotation_matrices"][solved.extraction.reference])
    assert solved.solution.status == IDENTIFIED
    assert is_correct(solved.solution.candidates[0].rotation_matrix, R_true)[0]
    assert not any("too sparse" in n for n in solved.solution.notes)
