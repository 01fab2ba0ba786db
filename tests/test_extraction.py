"""Extraction against synthetic sequences built here, independently of the simulator.

Stars are real catalogue directions around a random pointing, turned by a
known body rotation per snapshot and projected with the camera; ghosts
(random single spots), hot pixels (fixed pixels) and a missing star are
added with their truth, so every verdict can be checked.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.attitude import rotation_angle_between, solve_wahba
from app.camera import CAMERAS
from app.catalogue import load_catalogue
from app.extraction import GHOST, HOT_PIXEL, build_pattern, extract
from app.workflow.documents import ExtractionDocument
from app.extraction.motion import estimate_pair_rotations
from app.telemetry.model import Sequence, Snapshot

START = datetime(2001, 5, 17, 3, 4, 5, tzinfo=timezone.utc)


@functools.lru_cache(maxsize=1)
def _star_vectors():
    cat = load_catalogue().brighter_than(5.5)
    return cat.mean_vectors(2001.4), cat.hip, cat.mag


@dataclass
class Synthetic:
    sequence: Sequence
    labels: list  # per snapshot per source: ("star", hip) | ("ghost", None) | ("hot", k)
    attitudes: list  # R_i (ICRS -> camera)
    star_vectors: dict  # hip -> ICRS unit vector
    removed: tuple = field(default=())  # (snapshot, hip) of the missing star


def synthetic(seed: int, camera, *, n_snapshots=16, px_per_snapshot=10.0, n_stars=9, n_ghosts=2,
              n_hot=2, noise_px=0.3, missing=True) -> Synthetic:
    """A sequence of ``n_snapshots`` with the brightest stars of a random field."""
    rng = np.random.default_rng(seed)
    vectors, hip, mag = _star_vectors()
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    step = px_per_snapshot / camera.focal_length_px  # radians per snapshot (about) at the centre
    mid = n_snapshots // 2
    for _ in range(200):  # a pointing with enough stars
        r0 = Rotation.random(random_state=rng).as_matrix()
        xy0, front = camera.vectors_to_pixels(vectors @ r0.T)
        seen = np.flatnonzero(front & camera.on_sensor(xy0, margin=60))
        if len(seen) >= n_stars:
            break
    chosen = []
    for k in seen[np.argsort(mag[seen])]:  # brightest first, no two closer than 10 px (double stars)
        if len(chosen) < n_stars and all(np.linalg.norm(xy0[k] - xy0[j]) > 10 for j in chosen):
            chosen.append(k)
    chosen = np.array(chosen)
    attitudes = [Rotation.from_rotvec(axis * step * (i - mid)).as_matrix() @ r0 for i in range(n_snapshots)]
    hot = [rng.integers([0, 0], [camera.width, camera.height]).astype(float) for _ in range(n_hot)]
    removed = ()
    snapshots, labels = [], []
    for i, r in enumerate(attitudes):
        xy, front = camera.vectors_to_pixels(vectors[chosen] @ r.T)
        keep = front & camera.on_sensor(xy)
        rows = [(xy[k] + rng.normal(0, noise_px, 2), ("star", int(hip[chosen[k]])))
                for k in np.flatnonzero(keep)]
        if missing and i == mid + 2:  # one star drops out of one snapshot
            removed = ((i, rows[0][1][1]),)
            rows = rows[1:]
        rows += [(rng.uniform([0, 0], [camera.width - 1, camera.height - 1]), ("ghost", None))
                 for _ in range(n_ghosts)]
        rows += [(h.copy(), ("hot", k)) for k, h in enumerate(hot)]
        order = rng.permutation(len(rows))
        snapshots.append(Snapshot(index=i, time=START + timedelta(seconds=2 * i),
                                  xy=np.array([rows[k][0] for k in order]).reshape(-1, 2),
                                  brightness=rng.uniform(20, 255, len(rows))))
        labels.append([rows[k][1] for k in order])
    seq = Sequence(sequence_id=f"synthetic-{seed}", spacecraft=None, camera=camera, snapshots=tuple(snapshots))
    return Synthetic(seq, labels, attitudes, {int(hip[k]): vectors[k] for k in chosen}, removed)


def _star_tracks(case: Synthetic, extraction) -> dict:
    """hip -> set of track ids its sources got."""
    out = {}
    for s, labels in enumerate(case.labels):
        for k, (kind, what) in enumerate(labels):
            if kind == "star":
                out.setdefault(what, set()).add(int(extraction.track_of_source[s][k]))
    return out


@pytest.mark.parametrize("camera_name", list(CAMERAS))
@pytest.mark.parametrize("seed", [1, 2])
def test_stars_tracked_ghosts_and_hot_pixels_rejected(camera_name, seed):
    case = synthetic(seed, CAMERAS[camera_name])
    ex = extract(case.sequence)
    per_star = _star_tracks(case, ex)
    # every star source is in a track, one track per star, distinct stars distinct tracks
    assert all(ids == {next(iter(ids))} and next(iter(ids)) >= 0 for ids in per_star.values()), per_star
    assert len({next(iter(ids)) for ids in per_star.values()}) == len(per_star)
    for s, labels in enumerate(case.labels):
        for k, (kind, _) in enumerate(labels):
            if kind == "ghost":
                assert ex.track_of_source[s][k] == -1 and ex.rejection[s][k] == GHOST
            if kind == "hot":
                assert ex.track_of_source[s][k] == -1 and ex.rejection[s][k] == HOT_PIXEL
    # tracks are numbered in order of first appearance, their members agree with the per-source ids
    firsts = [(int(t.snapshots[0]), int(t.source_indices[0])) for t in ex.tracks]
    assert firsts == sorted(firsts) and [t.id for t in ex.tracks] == list(range(len(ex.tracks)))
    for t in ex.tracks:
        assert all(ex.track_of_source[s][k] == t.id for s, k in zip(t.snapshots, t.source_indices))
        np.testing.assert_array_equal(t.xy, [case.sequence.snapshots[s].xy[k]
                                             for s, k in zip(t.snapshots, t.source_indices)])


def test_missing_star_rejoins_its_track():
    case = synthetic(5, CAMERAS["tubsat-752x582-20deg"])
    ex = extract(case.sequence)
    (gap, hip), = case.removed
    (track_id,) = _star_tracks(case, ex)[hip]
    track = ex.tracks[track_id]
    assert gap not in track.snapshots
    assert track.snapshots.min() < gap < track.snapshots.max()


def test_motion_matches_the_true_rotation():
    camera = CAMERAS["liebe-576x604-30deg"]
    case = synthetic(3, camera, px_per_snapshot=25.0)
    ex = extract(case.sequence)
    ref = case.attitudes[ex.reference]
    np.testing.assert_allclose(ex.motion[ex.reference], np.eye(3), atol=1e-12)
    stars = np.array(list(case.star_vectors.values()))
    errors = []
    for i, r in enumerate(case.attitudes):
        true = ref @ r.T  # camera frame of snapshot i -> reference camera frame
        xy, _ = camera.vectors_to_pixels(stars @ r.T)
        probe = stars[camera.on_sensor(xy)] @ r.T  # where snapshot i saw stars
        est_xy, _ = camera.vectors_to_pixels(probe @ ex.motion[i].T)
        true_xy, _ = camera.vectors_to_pixels(probe @ true.T)
        errors.extend(np.linalg.norm(est_xy - true_xy, axis=1))
    # motion[i] carries the rotation errors of snapshot i and of the reference,
    # each ~ sigma / sqrt(n stars) = 0.3 / 3 px per axis: ~0.15 px rms in 2D
    assert np.sqrt(np.mean(np.square(errors))) < 0.3 and max(errors) < 0.8


def test_averaged_pattern_is_closer_to_truth_than_single_snapshots():
    camera = CAMERAS["narrow-1024x1024-12deg"]
    errors_avg, errors_seed = [], []
    for seed in (11, 12, 13):
        case = synthetic(seed, camera, noise_px=0.5)
        ex = extract(case.sequence)
        ref = case.attitudes[ex.reference]
        hip_of_track = {next(iter(ids)): hip for hip, ids in _star_tracks(case, ex).items()}
        for pattern, errors in ((ex.pattern, errors_avg), (ex.seed_pattern, errors_seed)):
            truth = np.array([case.star_vectors[hip_of_track[t]] for t in pattern.track_ids]) @ ref.T
            # Both patterns share the reference snapshot's own rotation error
            # (sigma / sqrt(n) of the whole frame); identification absorbs it
            # into the attitude, so compare shapes: align by the best rotation.
            aligned = pattern.vectors @ solve_wahba(truth, pattern.vectors).T
            errors.extend(np.linalg.norm(camera.vectors_to_pixels(aligned)[0]
                                         - camera.vectors_to_pixels(truth)[0], axis=1))
        # sigma_px follows the number of sightings
        np.testing.assert_allclose(ex.pattern.sigma_px, ex.noise_px / np.sqrt(ex.pattern.sightings))
        assert 0.3 < ex.noise_px < 0.75  # the simulated 0.5 px, estimated
    rms_avg, rms_seed = np.sqrt(np.mean(np.square(errors_avg))), np.sqrt(np.mean(np.square(errors_seed)))
    # ~10-16 sightings per track: about a third of the single-sighting error
    assert rms_avg < 0.4 * rms_seed, (rms_avg, rms_seed)
    assert rms_seed > 0.4  # single sightings carry the full noise (~sqrt(2) * 0.5 px expected)


def test_pattern_vectors_and_pixels_agree():
    case = synthetic(4, CAMERAS["tubsat-752x582-20deg"])
    ex = extract(case.sequence)
    xy, _ = case.sequence.camera.vectors_to_pixels(ex.pattern.vectors)
    np.testing.assert_allclose(xy, ex.pattern.xy, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(ex.pattern.vectors, axis=1), 1.0)
    assert len(ex.pattern) == len(ex.tracks)
    in_reference = ex.track_of_source[ex.reference]
    assert set(ex.seed_pattern.track_ids) == set(in_reference[in_reference >= 0])


def test_slow_drift_still_exposes_hot_pixels():
    # 1 px per snapshot: neighbouring snapshots cannot tell, the whole sequence can
    case = synthetic(6, CAMERAS["tubsat-752x582-20deg"], px_per_snapshot=1.0, n_ghosts=0, missing=False)
    ex = extract(case.sequence)
    hot = [ex.rejection[s][k] for s, labels in enumerate(case.labels)
           for k, (kind, _) in enumerate(labels) if kind == "hot"]
    assert hot and all(r == HOT_PIXEL for r in hot)
    assert all(len(ids) == 1 and min(ids) >= 0 for ids in _star_tracks(case, ex).values())


def test_still_sky_keeps_stationary_sources_with_a_note():
    case = synthetic(7, CAMERAS["tubsat-752x582-20deg"], px_per_snapshot=0.0, n_ghosts=1, missing=False)
    ex = extract(case.sequence)
    assert any("hot pixels cannot be told from stars" in n for n in ex.notes)
    for s, labels in enumerate(case.labels):
        for k, (kind, _) in enumerate(labels):
            assert (ex.track_of_source[s][k] >= 0) == (kind in ("star", "hot"))


def test_single_snapshot_makes_every_source_a_pattern_point():
    case = synthetic(8, CAMERAS["tubsat-752x582-20deg"], n_snapshots=1, missing=False)
    ex = extract(case.sequence)
    n = case.sequence.snapshots[0].n_sources
    assert len(ex.tracks) == n and len(ex.pattern) == n and len(ex.seed_pattern) == n
    np.testing.assert_allclose(ex.pattern.xy, case.sequence.snapshots[0].xy)
    assert any("nothing to track against" in note for note in ex.notes)


def test_incoherent_sources_give_no_tracks():
    camera = CAMERAS["tubsat-752x582-20deg"]
    rng = np.random.default_rng(9)
    snaps = tuple(Snapshot(index=i, time=START + timedelta(seconds=i),
                           xy=rng.uniform([0, 0], [camera.width - 1, camera.height - 1], (10, 2)),
                           brightness=np.full(10, 100.0)) for i in range(16))
    ex = extract(Sequence("noise", None, camera, snaps))
    assert ex.tracks == () and len(ex.pattern) == 0
    assert all(r == GHOST for per in ex.rejection for r in per)


def test_empty_snapshots_are_fine():
    camera = CAMERAS["tubsat-752x582-20deg"]
    snaps = tuple(Snapshot(index=i, time=START + timedelta(seconds=i), xy=np.zeros((0, 2)),
                           brightness=np.zeros(0)) for i in range(3))
    ex = extract(Sequence("empty", None, camera, snaps))
    assert ex.tracks == () and [len(t) for t in ex.track_of_source] == [0, 0, 0]
    json.dumps(ExtractionDocument.of(ex).model_dump(mode="json"), allow_nan=False)


def test_a_snapshot_that_links_to_nothing_is_bridged_and_rejected():
    camera = CAMERAS["tubsat-752x582-20deg"]
    case = synthetic(10, camera, n_hot=0, missing=False)
    rng = np.random.default_rng(0)
    snaps = list(case.sequence.snapshots)
    bad = 5
    snaps[bad] = Snapshot(index=bad, time=snaps[bad].time, xy=rng.uniform([0, 0], [700, 500], (9, 2)),
                          brightness=np.full(9, 50.0))
    seq = Sequence("bridged", None, camera, tuple(snaps))
    ex = extract(seq)
    assert np.all(np.isfinite(ex.motion[bad + 1]))  # 4 -> 6 linked over the bad snapshot
    # the lone snapshot's sources are rejected, the others keep one track per star
    assert np.all(ex.track_of_source[bad] == -1)
    if not np.all(np.isnan(ex.motion[bad])):
        pytest.fail("a snapshot with no consistent partner must have no motion")
    with pytest.raises(ValueError, match="could not be estimated"):
        build_pattern(seq, ex, manual_points=[(bad, 100.0, 100.0)])


def test_build_pattern_edits():
    camera = CAMERAS["tubsat-752x582-20deg"]
    case = synthetic(4, camera)
    seq = case.sequence
    ex = extract(seq)
    everything = build_pattern(seq, ex)
    np.testing.assert_allclose(everything.xy, ex.pattern.xy)
    without = build_pattern(seq, ex, exclude_tracks=[0, 2])
    assert list(without.track_ids) == [t.id for t in ex.tracks if t.id not in (0, 2)]
    only = build_pattern(seq, ex, include_tracks=[3, 1])
    assert list(only.track_ids) == [1, 3]
    np.testing.assert_allclose(only.xy, ex.pattern.xy[[1, 3]])

    # a star's position picked by hand in another snapshot lands on its track's averaged point
    other = (ex.reference + 3) % len(seq.snapshots)
    k = int(np.flatnonzero(ex.track_of_source[other] >= 0)[0])
    x, y = seq.snapshots[other].xy[k]
    picked = build_pattern(seq, ex, include_tracks=[], manual_points=[(other, x, y)])
    assert list(picked.track_ids) == [-1] and list(picked.sightings) == [1]
    assert picked.brightness[0] == seq.snapshots[other].brightness[k]
    track_point = ex.pattern.xy[ex.track_of_source[other][k]]
    assert np.linalg.norm(picked.xy[0] - track_point) < 2.0
    # in the reference snapshot a picked point stays where it was picked
    ref_point = build_pattern(seq, ex, include_tracks=[], manual_points=[(ex.reference, 200.0, 150.0)])
    np.testing.assert_allclose(ref_point.xy[0], [200.0, 150.0], atol=1e-9)

    with pytest.raises(ValueError, match="track 999 does not exist"):
        build_pattern(seq, ex, include_tracks=[999])
    with pytest.raises(ValueError, match="snapshot position"):
        build_pattern(seq, ex, manual_points=[(99, 1.0, 1.0)])
    with pytest.raises(ValueError, match="not a pixel"):
        build_pattern(seq, ex, manual_points=[(0, float("nan"), 1.0)])
    with pytest.raises(ValueError, match="expected"):
        build_pattern(seq, ex, manual_points=[(0, 1.0)])


def test_json_form_mirrors_the_extraction():
    case = synthetic(2, CAMERAS["liebe-576x604-30deg"])
    ex = extract(case.sequence)
    doc = json.loads(json.dumps(ExtractionDocument.of(ex).model_dump(mode="json"), allow_nan=False))
    assert doc["reference_snapshot"] == ex.reference
    assert doc["sources"] == [[None if t < 0 else int(t) for t in per] for per in ex.track_of_source]
    assert doc["rejected"] == [list(per) for per in ex.rejection]
    assert [t["id"] for t in doc["tracks"]] == [t.id for t in ex.tracks]
    assert doc["tracks"][0]["snapshots"] == ex.tracks[0].snapshots.tolist()
    assert [p["track"] for p in doc["pattern"]] == ex.pattern.track_ids.tolist()
    assert [p["sightings"] for p in doc["pattern"]] == ex.pattern.sightings.tolist()
    assert [p["track"] for p in doc["seed_pattern"]] == ex.seed_pattern.track_ids.tolist()
    assert abs(doc["pattern"][0]["x"] - ex.pattern.xy[0, 0]) < 1e-3


def test_pair_rotation_recovers_a_known_rotation_among_outliers():
    camera = CAMERAS["tubsat-752x582-20deg"]
    rng = np.random.default_rng(4)
    stars = camera.pixels_to_vectors(rng.uniform([50, 50], [700, 530], (7, 2)))
    true = Rotation.from_rotvec([0.004, -0.006, 0.05]).as_matrix()  # includes ~3 deg of roll
    a = np.vstack([stars, camera.pixels_to_vectors(rng.uniform([0, 0], [751, 581], (3, 2)))])
    b = np.vstack([camera.pixels_to_vectors(rng.uniform([0, 0], [751, 581], (4, 2))), stars @ true.T])
    vectors = np.zeros((2, 11, 3))
    vectors[0, :10], vectors[1, :11] = a, b
    hyp = np.array([list(range(10)) + [-1], list(range(11))])
    c = 1.0 / camera.focal_length_px
    result = estimate_pair_rotations(vectors, hyp, np.array([[0, 1]]), pair_tol=2 * c, min_baseline=40 * c,
                                     score_gate=8 * c, fit_gate=3 * c, min_inliers=3,
                                     field_area=752 * 582 * c**2, min_radius=c)
    assert rotation_angle_between(result.rotation[0], true) < 1e-9
    assert result.n_inliers[0] == 7
    np.testing.assert_array_equal(result.matches[0, :7], np.arange(4, 11))
    assert np.all(result.matches[0, 7:] == -1)


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_cli_json_lines_in_input_order_and_bad_files_do_not_stop_the_batch(tmp_path, capsys):
    from app.cli import main

    case = synthetic(1, CAMERAS["tubsat-752x582-20deg"])
    good = _write(tmp_path, "good.json", json.dumps(case.sequence.to_json_dict()))
    bad = _write(tmp_path, "bad.json", '{"format": "tubsat-snapshots/1", "snapshots": 3}')
    status = main(["extract", good, bad, good, "--json"])
    lines = capsys.readouterr().out.splitlines()
    assert status == 2 and len(lines) == 3
    docs = [json.loads(line) for line in lines]
    assert [d["file"] for d in docs] == [good, bad, good]
    assert [d["status"] for d in docs] == ["ok", "invalid", "ok"]
    assert docs[1]["error"] and docs[1]["tracks"] is None
    expected = ExtractionDocument.of(extract(case.sequence)).model_dump(mode="json")
    for key in ("reference_snapshot", "sources", "rejected", "tracks", "pattern"):
        assert docs[0][key] == json.loads(json.dumps(expected[key]))
    assert docs[0]["sequence_id"] == "synthetic-1"

    assert main(["extract", good]) == 0
    out = capsys.readouterr().out
    assert "tracks" in out and "reference snapshot" in out and "hot_pixel" in out
