"""The focal scan (app/identification/focal_scan.py): every searched focal length at once, each catalogue
pair at its nearest, checked against a brute-force computation of the same rule, the stepped search's own
hypotheses, and the simulator's truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from app.attitude import boresight_and_roll_error
from app.camera import CAMERAS
from app.extraction import extract
from app.identification import NO_MATCH, engine, identify
from app.identification.candidates import prepare_pattern
from app.identification.focal_scan import FocalScan
from app.identification.hypotheses import bright_pair_hypotheses, edge_windows, ordered_pattern_edges
from app.identification.methods import METHODS
from app.identification.optics import focal_lengths_to_try, prepared_with_camera
from app.identification.options import SearchOptions
from app.simulate import simulate_sequence, true_optics

CAMERA = CAMERAS["tubsat-752x582-20deg"]
OPTIONS = SearchOptions()


def _simulated(sky, seed: int, focal_error: float):
    sequence, truth = simulate_sequence(np.random.default_rng([seed, 2727]), CAMERA, "single",
                                        true_camera=true_optics(CAMERA, focal_error=focal_error))
    extraction = extract(sequence)
    t = sequence.snapshots[extraction.reference].time
    return extraction.pattern, t, np.asarray(truth["rotation_matrices"][extraction.reference])


def _scan(sky, seed: int) -> FocalScan:
    pattern, t, _ = _simulated(sky, seed, 0.03)
    declared = prepare_pattern(pattern, CAMERA, t, sky.for_camera(CAMERA), options=OPTIONS)
    steps = focal_lengths_to_try(CAMERA, declared.xy)
    return FocalScan([declared] + [prepared_with_camera(declared, CAMERA.with_optics(focal_length_px=f))
                                   for f in steps[1:]], sky.for_camera(CAMERA), OPTIONS)


def _made(groups) -> dict[tuple, tuple[int, np.ndarray]]:
    """{(edge number, star a, star b): (step, rotation)} of scan groups."""
    out = {}
    for g in groups:
        h = g.hypotheses
        for k in range(len(h)):
            key = (int(h.edge_number[k]), int(h.catalogue_pair[k, 0]), int(h.catalogue_pair[k, 1]))
            assert key not in out, "a pair is tried once"
            out[key] = (g.step, h.rotations[k])
    return out


@pytest.mark.parametrize("seed", [1, 2])
def test_each_pair_is_tried_once_at_the_searched_focal_length_nearest_its_length(sky, seed):
    """Brute force over every index pair and every searched focal length: the nearest (not the declared)
    whose window holds the pair, and there the stepped search's very hypothesis (the same rotation)."""
    scan = _scan(sky, seed)
    index = scan.index
    groups, used = next(scan.batches())
    assert used == 1
    made = _made(groups)
    expected = {}
    lengths, windows = scan.lengths[0], scan.tolerance[0]
    for row in range(len(index.length_rad)):
        a, b = int(index.star_a[row]), int(index.star_b[row])
        if not (scan.star_mask[a] and scan.star_mask[b]):
            continue
        gap = np.abs(lengths[1:] - index.length_rad[row])
        k = 1 + int(np.argmin(gap))
        if gap[k - 1] <= windows[k]:
            expected[(0, a, b)] = expected[(0, b, a)] = k
    assert len(expected) > 100 and {key: step for key, (step, _) in made.items()} == expected
    # At its focal length, the hypothesis is the one the stepped search makes there.
    for step in sorted({s for s, _ in made.values()})[:4]:
        p = scan.patterns[step]
        w = edge_windows(p, OPTIONS, scan.edges)
        stepped = bright_pair_hypotheses(p.vectors, scan.edges[:1], w.tolerance[:1], index, p.star_mask)
        for k in range(len(stepped)):
            key = (0, int(stepped.catalogue_pair[k, 0]), int(stepped.catalogue_pair[k, 1]))
            if key in made and made[key][0] == step:
                assert np.array_equal(made[key][1], stepped.rotations[k])


def test_a_pair_elsewhere_is_tried_at_every_other_focal_length_whose_window_holds_it(sky):
    scan = _scan(sky, 1)
    groups, _ = next(scan.batches())
    group = max(groups, key=lambda g: len(g.hypotheses))
    which = np.arange(min(40, len(group.hypotheses)))
    elsewhere = [_made([g]) for g in scan.elsewhere([(group, which)])]  # one focal length each
    for k in which.tolist():
        key = (int(group.hypotheses.edge_number[k]), *map(int, group.hypotheses.catalogue_pair[k]))
        held = np.flatnonzero(np.abs(scan.lengths[key[0]] - group.pair_length[k]) <= scan.tolerance[key[0]])
        got = sorted(made[key][0] for made in elsewhere if key in made)
        assert got == sorted(set(held.tolist()) - {0, group.step})
    assert sum(len(made) for made in elsewhere) > len(which)  # short edges: several other focal lengths each


@pytest.mark.parametrize("seed,focal_error", [(3, 0.04), (4, -0.045), (5, 0.03)])
def test_a_focal_length_off_is_found_by_the_scan_where_the_triangles_say_nothing(sky, monkeypatch, seed,
                                                                                 focal_error):
    """Without the bright triangles' estimate: the attitude (the simulator's truth) and the true focal length
    (the optics fitted on its stars), and the same stars as the stepped search (the triangle features' search
    of the other focal lengths)."""
    monkeypatch.setattr(engine, "focal_estimate", lambda *args, **kwargs: None)
    pattern, t, R_true = _simulated(sky, seed, focal_error)
    solution = identify(pattern, CAMERA, t, sky)
    best = solution.candidates[0]
    bore, roll = boresight_and_roll_error(best.rotation_matrix, R_true)
    assert solution.status == "identified" and np.degrees(bore) < 0.1 and np.degrees(roll) < 0.5
    truth = true_optics(CAMERA, focal_error=focal_error).focal_length_px
    assert best.camera.focal_length_px == pytest.approx(truth, rel=0.003)
    assert "focal lengths within 5.0% of the declared one" in solution.notes[0]
    monkeypatch.setitem(METHODS, "bright_pair", dataclasses.replace(METHODS["bright_pair"], focal_scan=False))
    stepped = identify(pattern, CAMERA, t, sky)
    assert stepped.status == "identified"
    assert [m.hip for m in stepped.candidates[0].matches] == [m.hip for m in best.matches]


def test_random_points_are_no_match_from_fewer_hypotheses_and_the_notes_say_what_was_searched(sky, monkeypatch):
    """Where nothing matches, every focal length is searched: the scan tries each pair once (or, when a third
    star caught earns it, at the other focal lengths of its window), the stepped search at each step."""
    rng = np.random.default_rng(99)
    pattern, t, _ = _simulated(sky, 1, 0.0)
    stepped_method = dataclasses.replace(METHODS["bright_pair"], focal_scan=False)
    for _ in range(3):
        xy = np.column_stack([rng.uniform(0, CAMERA.width - 1, 10), rng.uniform(0, CAMERA.height - 1, 10)])
        noise = dataclasses.replace(pattern, xy=xy, vectors=CAMERA.pixels_to_vectors(xy),
                                    sigma_px=np.full(10, 0.3), brightness=rng.uniform(50, 250, 10),
                                    track_ids=np.arange(10))
        solution = identify(noise, CAMERA, t, sky)
        assert solution.status == NO_MATCH
        steps = len(focal_lengths_to_try(CAMERA, xy))
        words = solution.notes[0].split()
        edges = ordered_pattern_edges(xy, CAMERA)
        assert int(words[4]) == len(edges) < 45  # every Delaunay edge at the declared focal length, no other pair
        assert f"at {steps} focal lengths within 5.0% of the declared one" in solution.notes[0]
        said = solution.notes[-1]
        assert said.startswith(f"nothing found: searched {len(edges)} of the pattern's {len(edges)} Delaunay edges")
        assert f"not its other {45 - len(edges)} point pairs" in said and f"the {steps - 1} other focal lengths" in said
        with monkeypatch.context() as stepped:
            stepped.setitem(METHODS, "bright_pair", stepped_method)
            before = identify(noise, CAMERA, t, sky)
        declared_only = identify(noise, CAMERA, t, sky, options=dataclasses.replace(OPTIONS, search_focal_length=False))
        tried = lambda s: int(s.notes[0].split()[0]) - int(declared_only.notes[0].split()[0])  # noqa: E731
        assert before.status == NO_MATCH and 0 < tried(solution) < 0.6 * tried(before)


def test_a_focal_length_known_roughly_has_its_neighbours_searched_as_far_as_itself_first(sky):
    """A calibrated camera (a tolerance within DEFAULT_FOCAL_LENGTH_TOLERANCE) has the other focal lengths
    searched with focal_search_features pattern edges; a focal length known only roughly (a field of view given
    by hand: 10 % and more) with rough_focal_search_features, as many as the declared one gets first. The notes
    of random points, which search everything there is, say how far each went."""
    from app.camera import DEFAULT_FOCAL_LENGTH_TOLERANCE

    rng = np.random.default_rng(7)
    pattern, t, _ = _simulated(sky, 1, 0.0)
    xy = np.column_stack([rng.uniform(0, CAMERA.width - 1, 10), rng.uniform(0, CAMERA.height - 1, 10)])
    noise = dataclasses.replace(pattern, xy=xy, vectors=CAMERA.pixels_to_vectors(xy), sigma_px=np.full(10, 0.3),
                                brightness=rng.uniform(50, 250, 10), track_ids=np.arange(10))
    searched = {}
    for tolerance in (DEFAULT_FOCAL_LENGTH_TOLERANCE, 0.12):
        camera = dataclasses.replace(CAMERA, focal_length_tolerance=tolerance)
        solution = identify(noise, camera, t, sky)
        assert solution.status == NO_MATCH
        steps = len(focal_lengths_to_try(camera, xy))
        said = solution.notes[-1]
        assert f"at the {steps - 1} other focal lengths within {tolerance:.1%}" in said
        searched[tolerance] = int(said.split(", and its first ")[1].split()[0])
    assert searched == {DEFAULT_FOCAL_LENGTH_TOLERANCE: OPTIONS.focal_search_features,
                        0.12: OPTIONS.rough_focal_search_features}
    assert OPTIONS.rough_focal_search_features == OPTIONS.declared_features_first > OPTIONS.focal_search_features
