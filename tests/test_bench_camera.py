"""The camera benchmark's rows (``bench --suite camera``), on a few simulated frames against the simulator's
true optics."""

from __future__ import annotations

from app.bench import camera as bench


def test_a_focal_length_beyond_the_tolerance_is_named_right_and_never_identified(sky):
    row = bench.run_row(sky, "beyond", "tubsat-752x582-20deg", bench.BEYOND_TOLERANCE[-1], 0.0, "single", n=4, seed=1)
    assert row["wrong_identified"] == 0 and row["top1_correct"] is None
    assert row["focal_named"] == row["focal_named_right"] >= 3
    within = bench.run_row(sky, "within", "tubsat-752x582-20deg", 0.03, 0.0, "single", n=2, seed=1)
    assert within["focal_named"] == 0 and within["top1_correct"] == 1.0
    table = bench.format_table({"rows": [row, within], "calibration": []}).splitlines()
    assert table[1].split()[-3] == f"{row['focal_named_right']}/{row['focal_named']}"
    assert table[2].split()[-3] == "-"
