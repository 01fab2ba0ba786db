"""The bright-pair hypotheses made where they are checked (app.identification.cells.check_pairs_kernel through
hypotheses.check_pair_hypotheses): the same hypotheses, matches and deviations as making every rotation and
checking it with the KD-tree, and only those that match 3 points or more kept."""

from __future__ import annotations

import numpy as np
import pytest

from app.camera import CAMERAS
from app.extraction import extract
from app.identification.candidates import prepare_pattern
from app.identification.hypotheses import bright_pair_batches, check_pair_hypotheses
from app.identification.options import SearchOptions
from app.identification.verify import chord, chord_to_angle
from app.simulate import simulate_sequence


def _tree_check(rotations, p, tol):
    """Every point of every hypothesis mapped onto the sky, its nearest star by the KD-tree: (matches,
    capped deviations), numpy's plain computation."""
    sky_points = np.matmul(p.vectors[None], rotations).reshape(-1, 3)
    d, _ = p.field.tree.query(sky_points, k=1, distance_upper_bound=float(chord(np.max(tol))))
    ang = chord_to_angle(np.where(np.isfinite(d), d, 2.0)).reshape(len(rotations), -1)
    return (ang <= tol[:, None]).sum(axis=1), np.minimum(ang, tol[:, None]).sum(axis=1)


@pytest.mark.parametrize("seed, name, scenario", [(21, "tubsat-752x582-20deg", "single"),
                                                  (22, "liebe-576x604-30deg", "ghosts3"),
                                                  (23, "narrow-1024x1024-12deg", "sparse")])
def test_the_hypotheses_checked_where_they_are_made_are_those_that_catch_three_points(sky, seed, name, scenario):
    camera = CAMERAS[name]
    sequence, _ = simulate_sequence(np.random.default_rng(seed), camera, scenario)
    extraction = extract(sequence)
    p = prepare_pattern(extraction.pattern, camera, sequence.snapshots[extraction.reference].time, sky)
    assert p.field.cells is not None
    batches = bright_pair_batches(p, sky, SearchOptions())
    kept_some = dropped_some = False
    for _ in range(3):
        hyp, tol, _ = next(batches)
        rows, n_match, dev, rotations = check_pair_hypotheses(hyp, p.field, tol)
        all_match, all_dev = _tree_check(hyp.rotations, p, tol)
        expected = np.flatnonzero(all_match >= 3)
        assert np.array_equal(rows, expected)
        assert np.array_equal(n_match, all_match[expected])
        np.testing.assert_allclose(dev, all_dev[expected], rtol=1e-12)
        assert np.array_equal(rotations, hyp.rotations[expected])  # the very rotations, bit for bit
        kept_some |= n_match.max(initial=0) >= 5  # the true attitude among them
        dropped_some |= len(rows) < len(hyp)
    assert kept_some and dropped_some


def test_a_field_without_a_cell_map_gets_the_same_answer(sky):
    """Where the field has no cell map (an observer too fast for the sky's maps), the tree checks the same
    hypotheses and the same ones are kept."""
    camera = CAMERAS["tubsat-752x582-20deg"]
    sequence, _ = simulate_sequence(np.random.default_rng(24), camera, "single")
    extraction = extract(sequence)
    p = prepare_pattern(extraction.pattern, camera, sequence.snapshots[extraction.reference].time, sky)
    hyp, tol, _ = next(bright_pair_batches(p, sky, SearchOptions()))
    with_map = check_pair_hypotheses(hyp, p.field, tol)
    without = check_pair_hypotheses(hyp, _without_cells(p.field), tol)
    assert len(with_map[0]) > 0
    for a, b in zip(with_map, without):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)


def _without_cells(field):
    import dataclasses

    return dataclasses.replace(field, cells=None)


def test_each_edge_gets_every_visible_pair_of_its_length_both_ways(sky):
    """bright_pair_hypotheses against brute force over the whole index: for each edge, every pair whose
    length lies in its window and whose stars the camera sees, (a, b) then (b, a), in the index's order."""
    from app.attitude import angle_between
    from app.identification.hypotheses import bright_pair_hypotheses, edge_windows

    camera = CAMERAS["tubsat-752x582-20deg"]
    sequence, _ = simulate_sequence(np.random.default_rng(25), camera, "single")
    extraction = extract(sequence)
    p = prepare_pattern(extraction.pattern, camera, sequence.snapshots[extraction.reference].time, sky)
    w = edge_windows(p, SearchOptions())
    index = sky.for_camera(camera).index
    hyp = bright_pair_hypotheses(p.vectors, w.edges[:6], w.tolerance[:6], index, p.star_mask)
    expected_edge, expected_pair = [], []
    for e, (i, j) in enumerate(w.edges[:6]):
        length = float(angle_between(p.vectors[i], p.vectors[j]))
        rows = [r for r in range(index.n_pairs) if abs(index.length_rad[r] - length) <= w.tolerance[e]
                and p.star_mask[index.star_a[r]] and p.star_mask[index.star_b[r]]]
        pairs = [(int(index.star_a[r]), int(index.star_b[r])) for r in rows]
        expected_pair += pairs + [(b, a) for a, b in pairs]
        expected_edge += [(i, j)] * (2 * len(pairs))
    assert len(expected_pair) > 100
    assert [tuple(x) for x in hyp.catalogue_pair.tolist()] == expected_pair
    assert [tuple(x) for x in hyp.pattern_edge.tolist()] == expected_edge


def test_the_windows_of_every_focal_length_at_once_are_each_ones_own(sky):
    """stacked_edge_windows (one set of numpy calls for the pattern at every searched focal length) against
    the plain formulas for each prepared pattern alone: the same numbers, bit for bit (the lookup's windows
    decide which pairs are tried)."""
    from app.attitude import angle_between
    from app.identification.hypotheses import ordered_pattern_edges, stacked_edge_windows
    from app.identification.optics import focal_lengths_to_try, prepared_with_camera

    options = SearchOptions()
    compared = 0
    for seed, name in ((26, "tubsat-752x582-20deg"), (27, "narrow-1024x1024-12deg")):
        camera = CAMERAS[name]
        sequence, _ = simulate_sequence(np.random.default_rng(seed), camera, "single")
        extraction = extract(sequence)
        p = prepare_pattern(extraction.pattern, camera, sequence.snapshots[extraction.reference].time, sky)
        patterns = [p] + [prepared_with_camera(p, camera.with_optics(focal_length_px=f))
                          for f in focal_lengths_to_try(camera, p.xy)[1:]]
        edges = ordered_pattern_edges(p.xy, camera, options.min_pair_separation_px)
        stacked = stacked_edge_windows(patterns, options, edges)
        first, second = np.array(edges).T
        for s, q in enumerate(patterns):
            v = q.vectors
            length = angle_between(v[first], v[second])
            tolerance = ((options.edge_tolerance_px + 4 * np.hypot(q.sigma_px[first], q.sigma_px[second])) * q.scale
                         + 1.1e-4 * length)
            reach = np.arccos(np.clip(v @ v.T, -1, 1)).max(axis=1)[first]
            check_tol = np.minimum(np.max(q.match_tol) + tolerance * np.maximum(1.0, reach / np.maximum(length, 1e-9)),
                                   10 * q.scale)
            for got, want in zip(stacked, (length, tolerance, check_tol)):
                assert np.array_equal(got[s], want)
            compared += 1
    assert compared >= 10
