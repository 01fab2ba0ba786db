"""Full frames (issue 15): reading, the pixel convention, detection and centroiding against rendered truth."""

from __future__ import annotations

import io

import numpy as np
import pytest
from astropy.io import fits
from PIL import Image

from app.camera import CAMERAS
from app.frames import DetectionOptions, detect, read_frames
from app.simulate import FrameModel, add_point_sources, frame_png_bytes, simulate_frames
from app.telemetry.errors import TelemetryError

CAMERA = CAMERAS["tubsat-752x582-20deg"]


def _noisy_sky(shape=(120, 160), seed=0, level=100.0, sigma=3.0) -> np.ndarray:
    return np.random.default_rng(seed).normal(level, sigma, shape).astype(np.float32)


# --- the pixel convention -------------------------------------------------------------------------

@pytest.mark.parametrize("x, y", [(37, 21), (100, 80), (5, 110)])
def test_a_single_bright_pixel_comes_back_at_its_own_coordinates(x, y):
    """(0, 0) is the centre of the top-left pixel: column x, row y gives (x, y), with no 0.5 or 1 offset."""
    image = _noisy_sky()
    image[y, x] += 5000.0
    found = detect(image)
    assert len(found) >= 1
    assert found.xy[0] == pytest.approx([x, y], abs=0.02)
    assert "hot_pixel" in found.flags[0]  # a lone sharp pixel is no star...
    assert not found.is_star[0]


def test_a_symmetric_star_is_centred_on_its_pixel_and_is_a_star():
    image = _noisy_sky(seed=1, sigma=1.0)
    add_point_sources(image, [[60.0, 40.0], [90.5, 70.25]], [20000.0, 20000.0], 1.3)
    found = detect(image)
    stars = found.xy[found.is_star]
    assert len(stars) == 2
    for truth in ([60.0, 40.0], [90.5, 70.25]):
        assert np.min(np.hypot(*(stars - truth).T)) < 0.03


def test_photutils_uses_the_same_convention():
    """The benchmark's second detector: a pixel-centred blob at (x, y) is found at (x, y) there too."""
    from photutils.centroids import centroid_2dg, centroid_com

    image = np.zeros((31, 41))
    add_point_sources(image, [[17.0, 12.0]], [1000.0], 1.2)
    assert centroid_com(image) == pytest.approx([17.0, 12.0], abs=1e-6)
    assert centroid_2dg(image) == pytest.approx([17.0, 12.0], abs=1e-3)


def _fits(data: np.ndarray, **header) -> bytes:
    hdu = fits.PrimaryHDU(data)
    for key, value in header.items():
        hdu.header[key.replace("_", "-")] = value
    stream = io.BytesIO()
    hdu.writeto(stream)
    return stream.getvalue()


def test_fits_rows_follow_roworder_and_png_rows_start_at_the_top():
    data = np.zeros((40, 50), dtype=np.uint16)
    data[5, 7] = 1000  # stored row 5
    top_down = next(read_frames(_fits(data, ROWORDER="TOP-DOWN", DATE_OBS="2024-01-01T00:00:00"), "a.fits"))
    bottom_up = next(read_frames(_fits(data, ROWORDER="BOTTOM-UP", DATE_OBS="2024-01-01T00:00:00"), "b.fits"))
    png = next(read_frames(frame_png_bytes(data), "c.png"))
    assert np.argwhere(top_down.pixels == 1000).tolist() == [[5, 7]]
    assert np.argwhere(bottom_up.pixels == 1000).tolist() == [[40 - 1 - 5, 7]]
    assert np.argwhere(png.pixels == 1000).tolist() == [[5, 7]]
    assert png.bits == 16 and png.saturation == 65535.0


def test_fits_time_is_mid_exposure_and_the_header_gives_the_optics():
    data = np.zeros((32, 32), dtype=np.int16)
    frame = next(read_frames(_fits(data, DATE_OBS="2024-05-01T10:00:00.000", EXPTIME=2.0, FOCALLEN=50.0,
                                   XPIXSZ=5.0), "x.fits"))
    assert frame.time.isoformat() == "2024-05-01T10:00:01+00:00"
    assert frame.meta["focal_length_px"] == pytest.approx(10000.0)


@pytest.mark.parametrize("mode, dtype, bits", [("L", np.uint8, 8), ("I;16", np.uint16, 16)])
def test_tiff_and_jpeg_8_and_16_bit_are_read(mode, dtype, bits):
    data = (np.arange(64 * 48).reshape(48, 64) % 200).astype(dtype)
    stream = io.BytesIO()
    Image.fromarray(data).save(stream, format="TIFF")
    frame = next(read_frames(stream.getvalue(), "t.tiff"))
    assert frame.bits == bits and np.array_equal(frame.pixels, data.astype(np.float32))
    if bits == 8:
        stream = io.BytesIO()
        Image.fromarray(np.stack([data] * 3, axis=-1)).save(stream, format="JPEG", quality=95)
        jpeg = next(read_frames(stream.getvalue(), "t.jpg"))
        assert jpeg.pixels.shape == (48, 64) and abs(float(jpeg.pixels.mean()) - float(data.mean())) < 2


@pytest.mark.parametrize("data, name, where, words", [
    (b"", "e.png", "e.png", "empty"),
    (b"this is no image at all", "n.png", "n.png", "not a readable image"),
    (b"\x89PNG\r\n\x1a\n" + b"\0" * 40, "t.png", "t.png", "not a readable image"),
    (b"SIMPLE  = garbage", "g.fits", "g.fits", "FITS"),
])
def test_bad_files_give_located_errors(data, name, where, words):
    with pytest.raises(TelemetryError) as err:
        list(read_frames(data, name))
    assert err.value.problems[0].location.startswith(where)
    assert words in err.value.problems[0].message


def test_a_3d_fits_and_a_truncated_png_are_refused_where_they_are_wrong():
    with pytest.raises(TelemetryError) as err:
        list(read_frames(_fits(np.zeros((3, 20, 20), np.int16)), "cube.fits"))
    assert err.value.problems[0].location == "cube.fits[0]" and "3-D" in err.value.problems[0].message
    png = frame_png_bytes(np.random.default_rng(0).integers(0, 60000, (200, 200)).astype(np.uint16))
    with pytest.raises(TelemetryError) as err:
        list(read_frames(png[: len(png) // 2], "half.png"))
    assert err.value.problems[0].location == "half.png"


# --- detection against rendered truth -------------------------------------------------------------

@pytest.fixture(scope="module")
def rendered():
    # Orion: many bright stars in one 20 deg field.
    frames, times, truth = simulate_frames(np.random.default_rng(21), CAMERA, n_frames=3, trail=True,
                                           pointing=(83.8, -1.2, 10.0))
    return frames, truth


def _stars(truth, i):
    return [s for s in truth["frame_sources"][i] if s["kind"] == "star"]


def test_bright_stars_are_found_within_a_tenth_of_a_pixel(rendered):
    frames, truth = rendered
    errors = []
    for i, frame in enumerate(frames):
        found = detect(frame, DetectionOptions(), saturation=65535)
        stars = found.xy[found.is_star]
        for s in _stars(truth, i):
            if s["snr"] >= 30 and 3 < s["x"] < CAMERA.width - 4 and 3 < s["y"] < CAMERA.height - 4:
                errors.append(np.min(np.hypot(stars[:, 0] - s["x"], stars[:, 1] - s["y"])))
    assert len(errors) >= 5
    assert max(errors) < 0.2 and np.median(errors) < 0.1, errors


def test_hot_pixels_and_trails_are_flagged_not_stars(rendered):
    frames, truth = rendered
    for i, frame in enumerate(frames):
        found = detect(frame, saturation=65535)
        hot = [(s["x"], s["y"]) for s in truth["frame_sources"][i] if s["kind"] == "hot_pixel"]
        stars = found.xy[found.is_star]
        for x, y in hot:
            assert not np.any(np.hypot(stars[:, 0] - x, stars[:, 1] - y) < 1.5), (i, x, y)
        assert set(hot) <= set(found.hot_pixel_candidates())
        trails = [s for s in truth["frame_sources"][i] if s["kind"] == "trail"]
        if trails:
            assert any("elongated" in flags for flags in found.flags)
            start, end = np.array(trails[0]["start"]), np.array(trails[0]["end"])
            direction = (end - start) / np.linalg.norm(end - start)
            for x, y in stars:  # no "star" sits on the trail unless a catalogue star is there
                offset = np.array([x, y]) - start
                along = offset @ direction
                across = abs(offset[0] * direction[1] - offset[1] * direction[0])
                if 5 < along < np.linalg.norm(end - start) - 5 and across < 1.0:
                    assert np.min([np.hypot(x - s["x"], y - s["y"]) for s in _stars(truth, i)]) < 1.0


def test_saturated_round_stars_stay_flagged():
    image = _noisy_sky((100, 100), seed=2)
    add_point_sources(image, [[50.2, 49.7]], [4.0e6], 1.5)
    np.minimum(image, 65535.0, out=image)
    found = detect(image, saturation=65535.0)
    assert found.is_star[0] and "saturated" in found.flags[0]
    assert found.xy[0] == pytest.approx([50.2, 49.7], abs=0.1)


def test_eight_bit_frames_are_detected_too():
    model = FrameModel(bits=8, gain_e_per_adu=60.0, bias_adu=10.0, sky_e=600.0, n_hot_pixels=0)
    frames, _, truth = simulate_frames(np.random.default_rng(4), CAMERA, n_frames=1, model=model)
    assert frames[0].dtype == np.uint8
    found = detect(frames[0], saturation=255)
    bright = [s for s in _stars(truth, 0) if s["snr"] > 30]
    stars = found.xy[found.is_star]
    hits = [np.min(np.hypot(stars[:, 0] - s["x"], stars[:, 1] - s["y"])) < 0.5 for s in bright]
    assert bright and all(hits)


def test_a_close_pair_is_split_into_its_two_stars():
    """4 px apart (1.4 FWHM): the detection filter merges them, the unfiltered second look splits them."""
    image = _noisy_sky((100, 100), seed=3)
    pair = np.array([[40.3, 50.1], [44.3, 50.4]])
    add_point_sources(image, pair, [30000.0, 18000.0], 1.2)
    found = detect(image)
    stars = found.xy[found.is_star]
    assert len(stars) == 2
    for truth in pair:
        assert np.min(np.hypot(*(stars - truth).T)) < 0.25
    assert DetectionOptions(max_split_per_frame=0) and detect(image, DetectionOptions(max_split_per_frame=0)).is_star.sum() == 1


@pytest.mark.parametrize("offset_px", [0.0, 2.5])
def test_a_star_a_trail_ran_over_is_found_again_where_it_is(offset_px):
    """A trail merges every star it touches into its own (rejected) blob; modelled and subtracted,
    the star comes back within 0.2 px, once, and the trail leaves no "stars" behind (its pieces
    cut apart by deblending are modelled as one line)."""
    from app.simulate import add_trail

    image = _noisy_sky((200, 300), seed=5, level=200.0, sigma=15.0) - 200.0
    start, end = np.array([20.0, 40.0]), np.array([280.0, 160.0])
    add_trail(image, start, end, flux=400_000.0, sigma=1.2)
    direction = (end - start) / np.linalg.norm(end - start)
    normal = np.array([-direction[1], direction[0]])
    star = start + 0.45 * (end - start) + offset_px * normal
    beside = np.array([[60.0, 150.0]])  # a star well away from the trail: found once, as before
    add_point_sources(image, np.vstack([star, beside]), [20_000.0, 20_000.0], 1.2)
    found = detect(image + 200.0)
    assert any("elongated" in flags for flags in found.flags)
    stars = found.xy[found.is_star]
    assert len(stars) == 2, stars
    assert np.min(np.hypot(*(stars - star).T)) < 0.2
    assert np.min(np.hypot(*(stars - beside[0]).T)) < 0.2
