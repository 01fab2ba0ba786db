"""The wide-angle photographs suite (app/bench/wide.py): the photographs are what they say, the reference is the
centre pixel's true direction, and a photograph is solved right under each optics."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from PIL import Image

from app.bench import wide
from app.camera import Camera
from app.identification.scale_free import fov_for_focal_length


def test_the_centre_pixels_direction_is_the_boresight_of_a_centred_lens_and_off_it_by_its_offset():
    # Rows of R: the camera axes in ICRS. Boresight (third row) at RA 90, Dec 0 (the ICRS +y axis).
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    centred = Camera(3000, 2000, 1000.0, 1499.5, 999.5)
    ra, dec = wide.centre_radec_deg(centred, R)
    assert (ra, dec) == pytest.approx((90.0, 0.0), abs=1e-9)
    # The principal point 1000 px (one focal length) left of the centre pixel: the centre pixel lies 45 deg
    # along +x of the camera, the ICRS +x axis, i.e. towards RA 0.
    shifted = Camera(3000, 2000, 1000.0, 499.5, 999.5)
    ra, dec = wide.centre_radec_deg(shifted, R)
    assert (ra, dec) == pytest.approx((45.0, 0.0), abs=1e-9)


def test_a_photograph_is_an_8_bit_jpeg_of_its_field_through_a_distorting_lens():
    pixels, true, rotation, described = wide.photograph(90.0, np.random.default_rng(5))
    image = Image.open(io.BytesIO(wide.jpeg(pixels)))
    assert image.format == "JPEG" and image.mode == "L" and image.size == wide.SIZE_PX
    assert fov_for_focal_length(true.width, true.focal_length_px) == pytest.approx(90.0, rel=1e-9)
    corner = true.k1 * true.corner_radius ** 2
    low, high = (90.0 / 105.0 * c for c in wide.CORNER_DISTORTION_AT_105_DEG)
    assert low <= corner <= high
    assert f"{100 * corner:+.1f} %" in described
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)


def test_a_wide_photograph_is_solved_right_under_each_optics(monkeypatch):
    monkeypatch.setattr(wide, "FIELDS_DEG", (90.0,))
    result = wide.run(n_sequences=1, seed=2)
    (row,) = result["rows"]
    for optics in wide.OPTICS:
        assert row["ours"][optics]["status"] == "identified", (optics, row["ours"][optics]["notes"])
        assert row["ours"][optics]["error_deg"] < 0.05
    assert result["summary"]["all"]["none"]["right"] == 1
    assert "90 deg" in wide.format_table(result)
    # The field of view a solve reports is the true lens's, within the distortion's pull on the pinhole.
    assert math.isclose(row["ours"]["none"]["fov_deg"], 90.0, rel_tol=0.02)



def test_a_photographs_lens_exif_is_its_35mm_equivalent_and_changes_no_pixel():
    from app.frames.lens import exif_lens

    pixels, true, _, _ = wide.photograph(75.0, np.random.default_rng(6))
    f35 = wide.focal_length_35mm(true)
    # By hand: 75 deg across 3000 px is f = 1500 / tan 37.5 = 1954.8 px; the diagonal 3605.6 px is 43.27 mm.
    assert f35 == round(1500 / math.tan(math.radians(37.5)) * math.hypot(36, 24) / math.hypot(3000, 2000)) == 23
    with_lens, without = wide.jpeg(pixels, f35), wide.jpeg(pixels)
    np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(with_lens))),
                                  np.asarray(Image.open(io.BytesIO(without))))
    image = Image.open(io.BytesIO(with_lens))
    assert exif_lens(image, 3000, 2000, "p.jpg")["focal_length_hint_px"] == pytest.approx(23 * 3605.55 / 43.2666, rel=1e-5)
    assert exif_lens(Image.open(io.BytesIO(without)), 3000, 2000, "p.jpg") == {}


def test_a_milky_way_is_a_band_through_the_centre_as_bright_as_asked_and_none_when_zero():
    dark = np.zeros((2000, 3000), dtype=np.uint8)
    assert wide.with_milky_way(dark, 0.0, np.random.default_rng(1)) is dark
    lit = wide.with_milky_way(dark, 40.0, np.random.default_rng(1)).astype(float)
    assert 40.0 * 0.6 < lit[990:1010, 1490:1510].mean() < 40.0 * 1.4  # its middle, clouds of +-40 % over 25 px
    # A Gaussian band of sigma 350 px: beyond 3 sigma (1,050 px) under 0.5 DN, rounded to 0 nearly everywhere.
    assert np.mean(lit > 0) < 0.95 and lit.max() <= 255
