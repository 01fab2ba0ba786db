"""Photographs larger than the detection budget (issue 26, "Real skies"): binned, not refused.

A frame with more pixels than ``STARID_FRAMES_MAX_PIXELS`` is read as the means of b x b blocks
(app/frames/binning.py) and its detections are brought back to its own pixels, where block i's centre is
``b*i + (b - 1)/2``.  The budget is lowered through the environment so that rendered frames of 1.5-6 Mpx
stand for 24-50 Mpx photographs and the tests stay fast; the truth is the simulator's (every star's exact
position and flux) or, for a real frame upscaled, astrometry.net's solution of the frame itself.
"""

from __future__ import annotations

import io
import json
import math
import struct
import time
import zlib

import numpy as np
import pytest
from PIL import Image

from app.attitude import angle_between
from app.bench.real import default_frames_dir
from app.camera import Camera
from app.cli import main as cli_main
from app.frames import FrameLimits, frames_to_sequence, read_frames
from app.frames import images as images_module
from app.frames.binning import binning_factor, block_mean, detect_on_blocks, in_block_pixels
from app.frames.detect import DetectionOptions
from app.simulate import FrameModel, frame_png_bytes, simulate_frames
from app.telemetry.errors import TelemetryError
from app.workflow.frames import frame_previews


def _camera(width: int, height: int, fov_deg: float) -> Camera:
    focal = (width / 2) / math.tan(math.radians(fov_deg / 2))
    return Camera(width=width, height=height, focal_length_px=round(focal, 1), cx=(width - 1) / 2,
                  cy=(height - 1) / 2, name=f"photo-{width}x{height}", mag_limit=6.0)


#: An odd-sized frame (1501 x 1001): binned 2 x 2 it leaves one column and one row, 3 x 3 one column, two rows.
ODD = _camera(1501, 1001, 20.0)
#: Budgets that make it b = 2 (750 x 500 = 375,000) and b = 3 (500 x 333 = 166,500).
BUDGET = {2: 400_000, 3: 170_000}


@pytest.fixture(scope="module")
def odd_pass():
    """Four rendered 16-bit frames of the odd camera (6 hot pixels, a sharp PSF of sigma 1.3 px) and the truth."""
    frames, times, truth = simulate_frames(np.random.default_rng(2601), ODD, n_frames=4,
                                           model=FrameModel(psf_sigma_px=1.3))
    return frames, truth


def _stars(truth: dict, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    stars = [s for s in truth["frame_sources"][frame] if s["kind"] == "star"]
    return (np.array([[s["x"], s["y"]] for s in stars]), np.array([s["snr"] for s in stars]),
            np.array([s["flux_e"] for s in stars]))


# --- the arithmetic -----------------------------------------------------------------------------------

def test_the_binning_factor_is_the_smallest_that_brings_the_full_blocks_within_the_budget():
    budget = 16_000_000
    assert binning_factor(4000, 4000, budget) == 1  # exactly the budget
    assert binning_factor(4001, 4000, budget) == 2
    assert binning_factor(6000, 4000, budget) == 2   # a DSLR: 3000 x 2000
    assert binning_factor(8000, 6000, budget) == 2   # a phone's 48 Mpx: 4000 x 3000 = 12 Mpx
    assert binning_factor(12000, 9000, budget) == 3  # 108 Mpx: 6000 x 4500 = 27 Mpx is too many
    assert binning_factor(8001, 6001, budget) == 2
    # Full blocks only: 9 x 9 at a budget of 9 is 3 x 3 (b = 3), although 81 / 4 > 9 would say b = 4.
    assert binning_factor(9, 9, 9) == 3
    assert binning_factor(11, 11, 9) == 3  # 3 x 3 full blocks, the last 2 columns and rows left over
    assert binning_factor(1501, 1001, BUDGET[2]) == 2 and binning_factor(1501, 1001, BUDGET[3]) == 3


def test_block_means_are_the_means_of_the_pixels_of_each_block_the_last_ones_cut_by_the_edge():
    values = np.random.default_rng(1).integers(0, 65536, size=(8, 11)).astype(np.uint16)
    means = block_mean(values, 3)
    assert means.shape == (3, 4) and means.dtype == np.float32
    for i in range(3):
        for j in range(4):
            block = values[3 * i: 3 * i + 3, 3 * j: 3 * j + 3].astype(float)
            assert means[i, j] == pytest.approx(block.mean(), rel=1e-7), (i, j)
    assert means[2, 3] == pytest.approx(values[6:8, 9:11].astype(float).mean(), rel=1e-7)  # a 2 x 2 corner
    assert np.array_equal(block_mean(values, 1), values.astype(np.float32))
    assert in_block_pixels([(5, 7), (4, 6), (0, 0)], 3) == [(0, 0), (1, 2)]


def test_a_large_png_is_read_strip_by_strip_into_the_same_block_means(monkeypatch):
    """Colour and 16-bit images are converted a few rows at a time; the strips change nothing."""
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, size=(301, 202, 3)).astype(np.uint8)
    grey16 = rng.integers(0, 65536, size=(301, 202)).astype(np.uint16)
    monkeypatch.setenv("STARID_FRAMES_MAX_PIXELS", "10000")  # 202 x 301 -> b = 3: 67 x 100 = 6,700
    for array, luminance in ((rgb, np.asarray(Image.fromarray(rgb).convert("L"))), (grey16, grey16)):
        stream = io.BytesIO()
        Image.fromarray(array).save(stream, format="PNG")
        monkeypatch.setattr(images_module, "STRIP_PIXELS", 1000)  # strips of 3 rows
        frame = next(read_frames(stream.getvalue(), "a.png"))
        assert (frame.width, frame.height, frame.binned) == (202, 301, 3)
        assert frame.pixels.shape == (101, 68) and frame.detection_pixels.shape == (100, 67)
        assert np.array_equal(frame.pixels, block_mean(luminance, 3))


@pytest.mark.parametrize("orientation", range(1, 9))
def test_an_exif_orientation_is_read_as_pillows_exif_transpose_shows_it(monkeypatch, orientation):
    """EXIF ``Orientation`` 1-8 (turned, upside down, mirrored, transposed): the frame's pixels are the image
    Pillow's own ``exif_transpose`` gives, its width and height that image's (the header's peek too), and a
    binned frame's blocks are that image's whole blocks."""
    from PIL import ImageOps

    from app.frames import peek_frame

    rng = np.random.default_rng(orientation)
    stored = rng.integers(0, 256, size=(61, 101)).astype(np.uint8)
    exif = Image.Exif()
    exif[0x0112] = orientation
    stream = io.BytesIO()
    Image.fromarray(stored).save(stream, format="PNG", exif=exif)
    upright = np.asarray(ImageOps.exif_transpose(Image.open(io.BytesIO(stream.getvalue()))))
    frame = next(read_frames(stream.getvalue(), "a.png"))
    assert np.array_equal(frame.pixels, upright.astype(np.float32))
    assert (frame.width, frame.height) == upright.shape[::-1] == peek_frame(stream.getvalue(), "a.png")[:2]
    assert ("orientation_note" in frame.meta) == (orientation != 1)
    monkeypatch.setenv("STARID_FRAMES_MAX_PIXELS", "1000")  # 101 x 61 -> b = 3: 33 x 20 whole blocks
    binned = next(read_frames(stream.getvalue(), "a.png"))
    rows, cols = (33, 20) if orientation >= 5 else (20, 33)
    whole = block_mean(np.ascontiguousarray(stored[:60, :99]), 3)
    assert binned.binned == 3 and binned.detection_pixels.shape == (rows, cols)
    turn = {2: Image.Transpose.FLIP_LEFT_RIGHT, 3: Image.Transpose.ROTATE_180, 4: Image.Transpose.FLIP_TOP_BOTTOM,
            5: Image.Transpose.TRANSPOSE, 6: Image.Transpose.ROTATE_270, 7: Image.Transpose.TRANSVERSE,
            8: Image.Transpose.ROTATE_90}  # what exif_transpose does for each
    image = Image.fromarray(whole, mode="F")
    assert np.allclose(binned.detection_pixels, np.asarray(image.transpose(turn[orientation]) if orientation > 1
                                                            else image))


# --- detection in the frame's own pixels --------------------------------------------------------------

@pytest.mark.parametrize("b", [2, 3])
def test_stars_come_back_at_their_true_positions_and_fluxes_in_the_frames_own_pixels(odd_pass, monkeypatch, b):
    """The bright stars (SNR >= 20) of the four frames.  Unbinned, they land within 0.22 px of the truth;
    binned 3 x 3 a PSF of sigma 1.3 px is 0.5 block wide, undersampled, and centroids are pulled towards
    the blocks' centres by up to about a fifth of a block (0.65 px seen), by as much one way as the other."""
    frames, truth = odd_pass
    monkeypatch.setenv("STARID_FRAMES_MAX_PIXELS", str(BUDGET[b]))
    offsets, ratios = [], []
    for k, image in enumerate(frames):
        frame = next(read_frames(frame_png_bytes(image), "odd.png"))
        assert (frame.width, frame.height, frame.binned) == (1501, 1001, b)
        found = detect_on_blocks(frame.detection_pixels, b, DetectionOptions(), integer_values=True,
                                 saturation=frame.saturation, hot_pixels=[])
        true_xy, snr, flux_e = _stars(truth, k)
        kept = found.kept(32)
        reported = found.xy[kept]
        # Within the full blocks: the last 1501 mod b columns and 1001 mod b rows were not searched.
        assert np.all(reported <= [b * (1501 // b) - 0.5, b * (1001 // b) - 0.5])
        nearest = np.array([np.argmin(np.hypot(*(true_xy - p).T)) for p in reported])
        bright = snr[nearest] >= 20
        offsets.append(reported[bright] - true_xy[nearest[bright]])
        # Fluxes in the frame's own ADU (electrons / gain 2): the block means' flux times b^2.
        ratios.append(found.flux[kept][bright] * FrameModel().gain_e_per_adu / flux_e[nearest[bright]])
        assert found.psf is not None and 1.0 < found.psf.sigma_px < 1.3 + b, found.psf  # in frame pixels
    offset = np.concatenate(offsets)
    assert len(offset) >= 20
    assert np.all(np.hypot(*offset.T) < 0.25 * b), offset
    # No offset common to all: a wrong block centre (b*i, or b*i + b/2) would move every star by (b - 1)/2
    # or 1/2 px in x and y alike.
    assert np.all(np.abs(offset.mean(axis=0)) < 0.1 * b), offset.mean(axis=0)
    assert 0.85 < np.median(np.concatenate(ratios)) < 1.15


@pytest.mark.parametrize("b", [2, 3])
def test_a_pass_over_the_budget_is_a_sequence_in_the_frames_own_pixels_with_its_binning_recorded(
        odd_pass, monkeypatch, b):
    frames, truth = odd_pass
    monkeypatch.setenv("STARID_FRAMES_MAX_PIXELS", str(BUDGET[b]))
    files = [(f"odd-{k}.png", frame_png_bytes(frame)) for k, frame in enumerate(frames)]
    frame_pass = frames_to_sequence(files, fov_deg=20.0)
    sequence = frame_pass.sequence
    camera = sequence.camera
    assert (camera.width, camera.height) == (1501, 1001) and camera.cx == 750.0 and camera.cy == 500.0
    block = sequence.extra["frames"]
    assert [report["binned"] for report in block["frames"]] == [b] * 4
    assert [(report["width"], report["height"]) for report in block["frames"]] == [(1501, 1001)] * 4
    note, = block["notes"]
    assert note.startswith(f"odd-0.png and the 3 other frame(s): 1501 x 1001 pixels, more than the {BUDGET[b]} ")
    assert f"means of {b} x {b} blocks ({1501 // b} x {1001 // b})" in note
    assert f"its last {1501 % b} column(s) and {1001 % b} row(s)" in note
    # The sources are the stars where the simulator drew them; none is a hot pixel.
    hot_truth = np.array([[s["x"], s["y"]] for s in truth["frame_sources"][0] if s["kind"] == "hot_pixel"])
    for k, shot in enumerate(sequence.snapshots):
        true_xy, snr, _ = _stars(truth, k)
        distance = np.array([np.min(np.hypot(*(true_xy - p).T)) for p in shot.xy])
        assert shot.n_sources >= 12 and np.mean(distance < 0.5 * b) >= 0.9, distance
        assert np.min(np.hypot(*(hot_truth[:, None, :] - shot.xy[None]).T)) > b
    # The camera's hot pixels are counted into its map in the frame's pixels, within the block that holds them.
    mapped = np.array(frame_pass.hot_map.hot)
    assert len(mapped) == len(hot_truth)
    for x, y in hot_truth:
        assert np.min(np.max(np.abs(mapped - [x, y]), axis=1)) <= b - 1
    # A next pass with the map applied (in blocks, before detection) reports the same stars and no hot pixel.
    again = frames_to_sequence(files[:2], fov_deg=20.0, hot_map=frame_pass.hot_map)
    for shot in again.sequence.snapshots:
        assert np.min(np.hypot(*(hot_truth[:, None, :] - shot.xy[None]).T)) > b
    assert again.hot_map.hot == frame_pass.hot_map.hot


def test_the_preview_of_a_binned_frame_covers_it_and_shows_each_star_where_the_overlay_puts_it(odd_pass,
                                                                                                monkeypatch):
    frames, _ = odd_pass
    monkeypatch.setenv("STARID_FRAMES_MAX_PIXELS", str(BUDGET[3]))
    files = [("odd-0.png", frame_png_bytes(frames[0]))]
    frame_pass = frames_to_sequence(files, fov_deg=20.0)
    preview, = frame_previews(files, frame_pass, FrameLimits())
    # 500 x 333 full blocks + the cut ones = 501 x 334 block means, shown whole: scale 3, 501 x 334.
    assert (preview.width, preview.height, preview.scale) == (1501, 1001, 3)
    assert (preview.image_width, preview.image_height) == (501, 334)
    image = np.asarray(Image.open(io.BytesIO(preview.png)))
    assert image.shape == (334, 501)
    shot = frame_pass.sequence.snapshots[0]
    for x, y in shot.xy[:6]:  # the brightest: their light peaks in the preview pixel the overlay names
        u, v = (x + 0.5) / preview.scale - 0.5, (y + 0.5) / preview.scale - 0.5
        iu, iv = int(round(u)), int(round(v))
        window = image[iv - 2: iv + 3, iu - 2: iu + 3].astype(float)
        jv, ju = np.unravel_index(np.argmax(window), window.shape)
        assert abs(iu - 2 + ju - u) <= 1.0 and abs(iv - 2 + jv - v) <= 1.0, (x, y)
        assert window.max() >= 200


# --- limits -------------------------------------------------------------------------------------------

def _png_header_only(width: int, height: int) -> bytes:
    """A PNG that claims a size and holds no pixel data: only its header can be read."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IEND", b""))


def test_a_frame_over_the_decoding_limit_is_refused_from_its_header_at_its_file():
    limits = FrameLimits()
    assert limits.max_decoded_pixels_per_frame == 120_000_000
    with pytest.raises(TelemetryError) as error:  # 121 Mpx: refused before any pixel is decoded (there are none)
        next(read_frames(_png_header_only(11000, 11000), "huge.png"))
    problem, = error.value.problems
    assert problem.location == "huge.png"
    assert problem.message == ("11000 x 11000 = 121000000 pixels; at most 120000000 per frame "
                               "(STARID_FRAMES_MAX_DECODED_PIXELS)")
    with pytest.raises(TelemetryError) as error:  # beyond Pillow's own guard (179 Mpx): said as a size too
        next(read_frames(_png_header_only(20000, 20000), "bomb.png"))
    problem, = error.value.problems
    assert problem.location == "bomb.png" and "too large to decode: at most 120000000 pixels" in problem.message
    # 108 Mpx, a phone's 12000 x 9000: accepted (its header read; the missing data is what fails).
    with pytest.raises(TelemetryError) as error:
        next(read_frames(_png_header_only(12000, 9000), "phone.png"))
    assert "cannot be decoded" in error.value.problems[0].message


def test_the_limits_are_the_environments_and_a_frame_binned_too_small_is_refused(monkeypatch):
    frames, _, _ = simulate_frames(np.random.default_rng(7), ODD, n_frames=1, hot_pixels=False)
    png = frame_png_bytes(frames[0])
    monkeypatch.setenv("STARID_FRAMES_MAX_DECODED_PIXELS", "1500000")
    with pytest.raises(TelemetryError) as error:
        frames_to_sequence([("odd.png", png)], fov_deg=20.0)
    problem, = error.value.problems
    assert problem.location == "odd.png"
    assert problem.message == "1501 x 1001 = 1502501 pixels; at most 1500000 per frame (STARID_FRAMES_MAX_DECODED_PIXELS)"
    monkeypatch.delenv("STARID_FRAMES_MAX_DECODED_PIXELS")
    monkeypatch.setenv("STARID_FRAMES_MAX_PIXELS", "100")  # b = 115 leaves 13 x 8 = 104 blocks, b = 116 12 x 8
    with pytest.raises(TelemetryError) as error:
        frames_to_sequence([("odd.png", png)], fov_deg=20.0)
    assert error.value.problems[0].location == "odd.png"
    assert error.value.problems[0].message == ("1501 x 1001 pixels binned 116 x 116 to fit 100 pixels "
                                               "(STARID_FRAMES_MAX_PIXELS) leaves 12 x 8, too small to search "
                                               "(at least 16 x 16)")


# --- photographs solved as they come ---------------------------------------------------------------------

@pytest.fixture
def session_sky(monkeypatch, sky):
    """`solve` builds its Sky(); hand it the session's."""
    monkeypatch.setattr("app.identification.Sky", lambda: sky)
    return sky


def _colour_jpeg(grey: np.ndarray) -> bytes:
    """An 8-bit frame as a colour JPEG (slightly different channels, as a camera's are), quality 92."""
    rgb = np.stack([grey, np.clip(grey * 0.93, 0, 255), np.clip(grey * 1.06, 0, 255)], axis=-1).astype(np.uint8)
    stream = io.BytesIO()
    Image.fromarray(rgb).save(stream, format="JPEG", quality=92)
    return stream.getvalue()


def test_a_large_colour_jpeg_with_no_time_and_no_field_of_view_solves_to_its_true_attitude(
        tmp_path, session_sky, monkeypatch, capsys):
    """3001 x 2001 at 30 deg, a photograph's 8-bit sky (25 ADU, 1.25 ADU noise), over a budget of 1.5 Mpx:
    binned 2 x 2 (1500 x 1000, the last column and row left out)."""
    camera = _camera(3001, 2001, 30.0)
    model = FrameModel(psf_sigma_px=1.6, read_noise_e=5.0, gain_e_per_adu=12.0, bias_adu=8.0, bits=8)
    frames, _, truth = simulate_frames(np.random.default_rng(2602), camera, n_frames=1, model=model,
                                       hot_pixels=False)
    photo = tmp_path / "night.jpg"
    photo.write_bytes(_colour_jpeg(frames[0]))
    monkeypatch.setenv("STARID_FRAMES_MAX_PIXELS", "1500000")
    frame = next(read_frames(photo.read_bytes(), photo.name))
    assert (frame.width, frame.height, frame.binned, frame.integer_values) == (3001, 2001, 2, True)
    started = time.perf_counter()  # read, bin and detect: the goal is 100 ms per Mpx, a test allows ten times
    frame = next(read_frames(photo.read_bytes(), photo.name))
    detect_on_blocks(frame.detection_pixels, frame.binned, DetectionOptions(), integer_values=True,
                     saturation=frame.saturation, hot_pixels=[])
    assert (time.perf_counter() - started) * 1000.0 / 6.005 < 1000.0

    annotated = tmp_path / "night-annotated.png"
    assert cli_main(["solve", "--json", "--annotate", str(annotated), str(photo)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["status"] == "identified", doc["notes"]
    best = doc["candidates"][0]
    assert abs(best["fov_deg"] / 30.0 - 1) < 0.005, best["fov_deg"]
    R = np.asarray(truth["rotation_matrices"][0])
    # Solved at J2000 (no time): the truth's apparent places are up to 20.5" away.
    assert np.degrees(angle_between(np.asarray(best["rotation_matrix"])[2], R[2])) < 0.02
    assert any("searched as the means of 2 x 2 blocks (1500 x 1000)" in note for note in doc["notes"])
    # The annotated frame is drawn on the block means, 1501 x 1001 (not enlarged: 2048 px at most).
    assert Image.open(annotated).size == (1501, 1001)


def test_a_real_frame_upscaled_twice_as_a_colour_jpeg_solves_to_astrometry_nets_centre(tmp_path, session_sky,
                                                                                       monkeypatch, capsys):
    """xmas-image4 (1392 x 1040, 27 deg) resized to 2784 x 2080 by Pillow (bicubic) and saved as a colour
    JPEG: a photograph's size over a budget of 2 Mpx, binned 2 x 2, with no time and no field of view."""
    folder = default_frames_dir()
    reference = json.loads((folder / "xmas-image4.json").read_text())
    grey = Image.open(folder / "xmas-image4.png").resize((2784, 2080))
    photo = tmp_path / "xmas-image4-2x.jpg"
    grey.convert("RGB").save(photo, format="JPEG", quality=92)
    monkeypatch.setenv("STARID_FRAMES_MAX_PIXELS", "2000000")
    assert cli_main(["solve", "--json", str(photo)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["status"] == "identified", doc["notes"]
    assert any("searched as the means of 2 x 2 blocks (1392 x 1040)" in note for note in doc["notes"])
    best = doc["candidates"][0]
    ra, dec = np.radians([best["ra_deg"], best["dec_deg"]])
    ra0, dec0 = np.radians([reference["ra_deg"], reference["dec_deg"]])
    cosine = math.sin(dec) * math.sin(dec0) + math.cos(dec) * math.cos(dec0) * math.cos(ra - ra0)
    assert math.degrees(math.acos(min(1.0, cosine))) < 0.1
