"""Liebe's tables bench (app.bench.seeds): the trial generator against truth, and the result's shape."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from app.bench import seeds
from app.camera import CAMERAS

CAMERA = CAMERAS[seeds.CAMERA_NAME]


@pytest.fixture(scope="module")
def star_sky():
    return seeds.StarSky.at(seeds.OBSERVATION_TIME)


def nearest_star_offsets_arcmin(pattern, R, star_sky):
    """Angle from each pattern point to the nearest catalogue star (to Hp 4.5) under the true attitude."""
    sky_dirs = pattern.vectors @ R
    ang = np.arccos(np.clip(sky_dirs @ star_sky.vectors.T, -1, 1))
    return np.degrees(ang.min(axis=1)) * 60


def test_trials_have_the_situations_errors(star_sky):
    scale_arcmin = CAMERA.pixel_scale_arcsec / 60
    rng = np.random.default_rng(8)
    for situation in seeds.SITUATIONS:
        for _ in range(15):
            pattern, R, n_field = seeds.make_trial(rng, star_sky, CAMERA, situation)
            off = nearest_star_offsets_arcmin(pattern, R, star_sky)
            # Blended doubles sit up to a pixel from either star; 1/5-pixel noise stays within 1 px.
            good = off <= 1.5 * scale_arcmin
            displaced = (off >= 3.5) & (off <= 8.5)
            n_false = situation.false_stars
            # A false star may land near a star by chance; a displaced one may leave the sensor.
            assert (~good).sum() <= situation.out_of_tolerance + n_false
            assert displaced.sum() + n_false >= (~good).sum()
            assert len(pattern.xy) <= n_field + n_false - situation.missing
            assert np.all(CAMERA.on_sensor(pattern.xy))
            np.testing.assert_allclose(pattern.sigma_px, seeds.CENTROID_SIGMA_PX)


def test_all_in_tolerance_trials_match_the_true_attitude(star_sky):
    """With no errors, every point is a catalogue star within a pixel, and the count is the stars in view."""
    rng = np.random.default_rng(9)
    counts = []
    for _ in range(20):
        pattern, R, n_field = seeds.make_trial(rng, star_sky, CAMERA, seeds.SITUATIONS[0])
        off = nearest_star_offsets_arcmin(pattern, R, star_sky)
        assert np.all(off <= CAMERA.pixel_scale_arcsec / 60)
        # Only blending can merge stars.
        assert n_field - 2 <= len(pattern.xy) <= n_field
        counts.append(n_field)
    assert min(counts) >= 3


def test_mean_stars_in_field_is_the_solid_angle_share(star_sky):
    """Fig. 2: over uniform random attitudes the mean count is N * Omega / 4 pi (pinhole rectangle)."""
    rng = np.random.default_rng(10)
    counts = [len(seeds.stars_on_sensor(star_sky, seeds.random_rotation(rng), CAMERA)[0]) for _ in range(1500)]
    w, h, f = CAMERA.width / 2, CAMERA.height / 2, CAMERA.focal_length_px
    omega = 4 * math.atan(w * h / (f * math.sqrt(f * f + w * w + h * h)))
    expected = len(star_sky.mag) * omega / (4 * math.pi)
    assert np.mean(counts) == pytest.approx(expected, rel=0.04)
    cone = seeds.stars_in_cone_mean(star_sky, 15.0, 4000, rng)
    assert cone == pytest.approx(len(star_sky.mag) * (1 - math.cos(math.radians(15))) / 2, rel=0.04)


def test_blend_close_merges_at_the_flux_weighted_centroid():
    xy = np.array([[10.0, 10.0], [11.0, 10.0], [50.0, 50.0]])
    flux = np.array([3.0, 1.0, 2.0])
    merged, total = seeds.blend_close(xy, flux, 2.0)
    order = np.argsort(merged[:, 0])
    np.testing.assert_allclose(merged[order], [[10.25, 10.0], [50.0, 50.0]])
    np.testing.assert_allclose(total[order], [4.0, 2.0])


def test_seeds_bench_returns_the_documented_shape():
    result = seeds.run(n_sequences=2, seed=3)
    assert [r["situation"] for r in result["table2"]] == [s.name for s in seeds.SITUATIONS]
    assert [r["paper"] for r in result["table2"]] == [0.946, 0.852, 0.852, 0.786, 0.720, 0.884]
    assert [r["paper"] for r in result["table3"]] == [14.6, 15.4, 14.7, 16.7, 19.4, 14.6]
    for row in result["table2"]:
        assert set(row) == {"situation", "paper", "bright_pair", "tf"}
        assert row["bright_pair"] in (0.0, 0.5, 1.0) and row["tf"] in (0.0, 0.5, 1.0)
    for row in result["table3"]:
        assert set(row) == {"situation", "paper", "pe_arcsec", "pe_rms_arcsec"}
        assert row["pe_arcsec"] is None or 0 < row["pe_arcsec"] <= row["pe_rms_arcsec"] < 360
    assert 3 <= result["stars_in_field_mean"] <= 60
    assert result["pe_method"] in ("track", "ie_refined")
    json.dumps(result, allow_nan=False)
    text = seeds.format_table(result)
    assert all(s.name in text for s in seeds.SITUATIONS)
    with pytest.raises(ValueError):
        seeds.run(n_sequences=0)


def test_bench_cli_seeds_flag(capsys):
    from app.cli import bench

    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(["--seeds", "--n", "1", "--json"])
    assert args.suite == "seeds"
    assert bench.run(args) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) == {"seeds"}
    assert {"table2", "table3", "stars_in_field_mean"} <= set(doc["seeds"])
    assert len(doc["seeds"]["table2"]) == 6
