"""The real frames' copies (app/bench/variants.py): each copy's geometry against a spot placed by hand,
and one frame's copies solved end to end against astrometry.net's centre."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.bench import variants
from app.bench.real import RealFrame, default_frames_dir


def _spot(width=200, height=150, x=140, y=40):
    """An 8-bit frame, dark but for a 3 x 3 spot centred on pixel (x, y)."""
    pixels = np.zeros((height, width), dtype=np.uint8)
    pixels[y - 1:y + 2, x - 1:x + 2] = 200
    return pixels


def _centroid(pixels) -> tuple[float, float]:
    values = pixels.astype(float)
    values[values < 20] = 0.0
    rows, cols = np.mgrid[:values.shape[0], :values.shape[1]]
    return float((cols * values).sum() / values.sum()), float((rows * values).sum() / values.sum())


def test_each_copy_keeps_the_spot_where_its_geometry_puts_it():
    """Pixel centres, (0, 0) the centre of the top-left pixel: 2x puts x at 2x + 0.5, half at (x + 0.5)/2 - 0.5;
    a turn of 37 deg counter-clockwise as seen (y down) takes the offset (dx, dy) from the centre to
    (dx cos + dy sin, dy cos - dx sin); a crop keeps pixels where they were; the foreground darkens only
    the bottom."""
    pixels = _spot()
    cx, cy = (200 - 1) / 2, (150 - 1) / 2
    assert _centroid(variants.make_copy("2x", pixels)) == pytest.approx((2 * 140 + 0.5, 2 * 40 + 0.5), abs=0.2)
    assert _centroid(variants.make_copy("half", pixels)) == pytest.approx(((140 + 0.5) / 2 - 0.5, (40 + 0.5) / 2 - 0.5), abs=0.2)
    a = math.radians(variants.TURN_DEG)
    dx, dy = 140 - cx, 40 - cy
    turned = (cx + dx * math.cos(a) + dy * math.sin(a), cy + dy * math.cos(a) - dx * math.sin(a))
    assert _centroid(variants.make_copy("turned", pixels)) == pytest.approx(turned, abs=0.3)
    cropped = variants.make_copy("cropped", _spot(x=60, y=140))
    assert cropped.shape == (150, 133) and _centroid(cropped) == pytest.approx((60, 140), abs=0.01)
    assert _centroid(variants.make_copy("foreground", pixels)) == pytest.approx((140, 40), abs=0.01)
    dark = variants.make_copy("foreground", np.full((150, 200), 100, dtype=np.uint8))
    assert np.all(dark[-int(0.15 * 150):] == 3) and np.all(dark[:int(0.75 * 150)] == 100)


def test_sizes_centres_and_fields_of_view_of_the_copies():
    assert variants.copy_size("2x", 1392, 1040) == (2784, 2080)
    assert variants.copy_size("half", 1392, 1040) == (696, 520)
    assert variants.copy_size("cropped", 1392, 1040) == (928, 1040)
    assert variants.centre_in_frame("turned", 1392, 1040) == (695.5, 519.5)
    assert variants.centre_in_frame("cropped", 1392, 1040) == (463.5, 519.5)
    frame = RealFrame(name="x", image=None, width=1392, height=1040, ra_deg=0.0, dec_deg=0.0, fov_deg=27.4, time=None)
    focal = 696 / math.tan(math.radians(13.7))
    assert variants.copy_fov_deg("cropped", frame) == pytest.approx(math.degrees(2 * math.atan(464 / focal)))
    assert variants.copy_fov_deg("half", frame) == 27.4


def test_one_frames_copies_are_identified_at_astrometry_nets_centre():
    """feb16-2 (13 deg, its bright stars clear of the borders) copied five ways, each solved with its
    exact field of view: every copy right, none wrong - the crop's centre through the frame's WCS."""
    if not (default_frames_dir() / "README.md").is_file():
        pytest.fail(f"the real frames are missing: expected them in {default_frames_dir()}")
    result = variants.run(n_sequences=1)
    assert [row["frame"] for row in result["rows"]] == ["feb16-2"] * len(variants.VARIANTS)
    for variant in variants.VARIANTS:
        exact = result["summary"][variant]["exact"]
        assert (exact["right"], exact["wrong"]) == (1, 0), (variant, result["rows"])
