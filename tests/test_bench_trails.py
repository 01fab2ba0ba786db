"""Trailed stars (``bench --suite trails``): the simulator's smear against its geometry, and a photograph from a
fixed tripod identified through the ``solve`` workflow against its truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.bench import trails
from app.bench.real import solve_ours
from app.bench.wide import jpeg, photograph, photographed_frame


def test_a_smeared_star_is_a_trail_of_its_length_centred_on_its_place_with_all_its_light():
    """FrameModel.smear_px: light spread evenly over L px along the angle, so its second moment along the trail
    is the PSF's plus L^2 / 12 (a uniform segment's), across it the PSF's alone, and its mean the place."""
    from app import simulate
    from app.camera import Camera

    camera = Camera(200, 200, 500.0, 99.5, 99.5)
    model = simulate.FrameModel(psf_sigma_px=1.2, sky_e=0.0, read_noise_e=0.0, gain_e_per_adu=1.0, bias_adu=0.0,
                                smear_px=30.0, smear_angle_deg=30.0)
    electrons = np.zeros((200, 200))
    half = 15.0 * np.array([math.cos(math.radians(30.0)), math.sin(math.radians(30.0))])
    simulate.add_trail(electrons, np.array([100.3, 90.7]) - half, np.array([100.3, 90.7]) + half, 1e6, 1.2)
    assert electrons.sum() == pytest.approx(1e6, rel=1e-3)
    rows, cols = np.mgrid[:200, :200]
    mean = np.array([(electrons * cols).sum(), (electrons * rows).sum()]) / electrons.sum()
    assert mean == pytest.approx([100.3, 90.7], abs=0.01)
    along = ((cols - mean[0]) * math.cos(math.radians(30.0)) + (rows - mean[1]) * math.sin(math.radians(30.0)))
    across = (-(cols - mean[0]) * math.sin(math.radians(30.0)) + (rows - mean[1]) * math.cos(math.radians(30.0)))
    pixel = 1.2 ** 2 + 1 / 12  # the PSF integrated over a pixel
    assert (electrons * along ** 2).sum() / electrons.sum() == pytest.approx(pixel + 30.0 ** 2 / 12, rel=0.02)
    assert (electrons * across ** 2).sum() / electrons.sum() == pytest.approx(pixel, rel=0.05)
    # ... and render_frame draws every star so.
    frame = simulate.render_frame(np.random.default_rng(1), camera, np.array([[100.3, 90.7]]), np.array([1e6]), model)
    assert np.abs(frame.astype(float) - np.clip(np.round(electrons), 0, 65535)).max() <= 1.0 + 4 * math.sqrt(
        electrons.max())  # shot noise only


def test_a_photograph_from_a_fixed_tripod_trailed_14_px_is_identified(tmp_path, sky):
    """A 40 deg photograph (landscape, a town's glow) whose stars are trailed 14 px: every trailed star was
    called elongated, nothing was left to identify (no_match); now the frame is seen to be trailed."""
    pixels, true, rotation, _ = photograph(40.0, np.random.default_rng([1, 75, 40, 1]), smear_px=14.0,
                                           milky_way=False)
    path = tmp_path / "trailed.jpg"
    path.write_bytes(jpeg(pixels))
    frame = photographed_frame("trailed", path, true, rotation)
    answer = solve_ours(frame, sky, frame.fov_deg, tmp_path)
    assert answer["status"] == "identified", answer["notes"]
    assert answer["error_deg"] < 0.02
    (said,) = [note for note in answer["notes"] if "trailed" in note]
    assert said.startswith("trailed.jpg: the stars are trailed (a / b ")


def test_the_trails_table_counts_right_and_wrong_per_trail_length():
    rows = [{"trail_px": t, "ours": {"status": s, "claimed": s == "identified", "error_deg": e, "seconds": 0.5}}
            for t, s, e in ((0.0, "identified", 0.01), (0.0, "identified", 2.0), (8.0, "no_match", None))]
    summary = {f"{t:g}": trails.summarise([r["ours"] for r in rows if r["trail_px"] == t]) for t in (0.0, 8.0)}
    text = trails.format_table({"n_per_cell": 1, "seed": 1, "fields_deg": [40.0], "summary": summary,
                                "load_average_before": 0.1, "load_average_after": 0.2})
    assert "0           1/2        1        2" in text and "8           0/1        0        0" in text
