"""The floor suite (app/bench/floor.py): the stripped searches answer as the default does, and leave out
what they say they leave out."""

from __future__ import annotations

import numpy as np

from app.bench import floor
from app.camera import CAMERAS
from app.identification import IDENTIFIED, SearchOptions, Sky, solve_sequence
from app.simulate import simulate_sequence


def test_each_stripped_search_names_the_defaults_answer_and_the_stages_account_for_the_time():
    import importlib

    before = {(m, f): getattr(importlib.import_module(m), f) for m, f, _ in floor.STAGES}
    result = floor.run(n_sequences=5, seed=3)
    for scenario, rows in result["rows"].items():
        assert [r["search"] for r in rows] == [label for label, _ in floor.SEARCHES]
        for r in rows:
            assert r["same_answer"] == r["n"], (scenario, r)
        assert rows[0]["of_default"] == 1.0
    # Where the default's time goes: every stage timed (the sequence's fits in sequences only), the search's own
    # Python what is left, and all of it within the frames' whole time.
    for scenario, split in result["stage_split"].items():
        ms = {s["function"]: s["ms"] for s in split["stages"]}
        assert len(ms) == len(floor.STAGES) and all(v >= 0 for v in ms.values())
        assert ms["engine.check_pair_hypotheses"] > 0 and ms["engine.build_candidate"] > 0
        assert (ms["identification.fit_sequence"] > 0) == (scenario == "nominal")
        assert 0 < sum(ms.values()) + split["search_python_ms"] <= split["total_ms"] * 1.01
    # ... and the timers are gone afterwards: the functions are the search's own again.
    assert {(m, f): getattr(importlib.import_module(m), f) for m, f, _ in floor.STAGES} == before
    table = floor.format_table(result)
    assert "(engine.build_candidate)" in table and "the search's own Python (identify less its stages)" in table


def test_the_image_centre_is_left_out_only_when_asked():
    sequence, _ = simulate_sequence(np.random.default_rng([7, 2626]), CAMERAS["tubsat-752x582-20deg"], "single")
    sky = Sky()
    with_centre = solve_sequence(sequence, sky).solution
    without = solve_sequence(sequence, sky, options=SearchOptions(image_centre=False)).solution
    assert with_centre.status == without.status == IDENTIFIED
    assert with_centre.candidates[0].centre_radec_deg is not None
    assert without.candidates[0].centre_radec_deg is None
    np.testing.assert_allclose(without.candidates[0].rotation_matrix, with_centre.candidates[0].rotation_matrix)
