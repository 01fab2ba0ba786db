"""A photograph's EXIF lens (app/frames/lens.py) as a focal length in its pixels, by hand, and as the hint the
field-of-view search starts from (app/identification/scale_free.py), on a rendered wide-angle photograph."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from PIL import Image

from app.frames import frames_to_sequence
from app.frames.lens import exif_lens
from app.identification import IDENTIFIED, solve_sequence

EXIF_IFD = 0x8769


def _jpeg(image: Image.Image, tags: dict) -> bytes:
    exif = Image.Exif()
    exif.get_ifd(EXIF_IFD).update(tags)
    stream = io.BytesIO()
    image.save(stream, format="JPEG", quality=92, exif=exif)
    return stream.getvalue()


def _lens(tags: dict, size=(300, 200)) -> dict:
    return exif_lens(Image.open(io.BytesIO(_jpeg(Image.new("L", size), tags))), *size, "p.jpg")


def test_the_35mm_equivalent_spans_the_images_diagonal():
    # A 3:2 image is a 36 x 24 mm frame scaled: 36 mm are its 300 px, so 24 mm of focal length are 200 px.
    found = _lens({0xA405: 24})
    assert found["focal_length_hint_px"] == pytest.approx(200.0, rel=1e-12)
    assert "EXIF FocalLengthIn35mmFilm 24 mm" in found["optics_from"]
    # A 4:3 image (a phone's): its diagonal of 500 px is the film's 43.27 mm.
    assert _lens({0xA405: 26}, (400, 300))["focal_length_hint_px"] == pytest.approx(26 * 500 / math.hypot(36, 24))


def test_a_focal_length_and_the_sensors_resolution_give_pixels_of_the_image_as_stored():
    # 50 mm at 5000 px per inch on a sensor 6000 px across, the image resized to 300 px: 50 / 25.4 * 5000 / 20.
    tags = {0x920A: 50.0, 0xA20E: 5000.0, 0xA210: 2, 0xA002: 6000}
    assert _lens(tags)["focal_length_hint_px"] == pytest.approx(50 / 25.4 * 5000 * 300 / 6000)
    # Per centimetre, and without the pixel dimension (the image as the sensor gave it).
    assert _lens({0x920A: 4.0, 0xA20E: 500.0, 0xA210: 3})["focal_length_hint_px"] == pytest.approx(4.0 * 50.0)


@pytest.mark.parametrize("tags", [{}, {0xA405: 0}, {0x920A: 50.0}, {0x920A: 0.0, 0xA20E: 5000.0},
                                  {0x920A: 50.0, 0xA20E: 5000.0, 0xA210: 1}, {0xA405: "wide"}])
def test_no_lens_or_an_unusable_one_is_no_hint(tags):
    assert _lens(tags) == {}


@pytest.fixture(scope="module")
def photograph():
    """A 75 deg photograph (app.bench.wide), its true camera and rotation, and its lens's 35 mm equivalent."""
    from app.bench import wide

    pixels, true, rotation, _ = wide.photograph(75.0, np.random.default_rng([1, 74, 75, 0]))
    f35 = round(true.focal_length_px * math.hypot(36, 24) / math.hypot(true.width, true.height))
    return Image.fromarray(pixels), true, rotation, f35


def _solved(data: bytes, sky):
    sequence = frames_to_sequence([("p.jpg", data)]).sequence
    return sequence, solve_sequence(sequence, sky).solution


def _boresight_error_deg(solution, rotation) -> float:
    return math.degrees(math.acos(min(1.0, float(solution.candidates[0].rotation_matrix[2] @ rotation[2]))))


def test_a_photographs_exif_lens_is_searched_first_and_settles_the_search(photograph, sky):
    image, true, rotation, f35 = photograph
    sequence, solution = _solved(_jpeg(image, {0xA405: f35}), sky)
    assert sequence.camera.focal_length_unknown
    assert sequence.camera.focal_length_px == pytest.approx(f35 * math.hypot(3000, 2000) / math.hypot(36, 24))
    assert solution.status == IDENTIFIED, solution.notes
    assert _boresight_error_deg(solution, rotation) < 0.02
    assert "searched first around its hint" in solution.notes[0] and "bright triangles" not in solution.notes[0]
    _, without = _solved(_jpeg(image, {}), sky)
    assert without.status == IDENTIFIED
    assert solution.n_hypotheses < without.n_hypotheses


def test_a_cropped_photographs_exif_lens_is_wrong_and_the_field_of_view_is_searched_after_it(photograph, sky):
    """The centre half of the photograph keeps its EXIF: the hint says 76 deg where the crop spans 42."""
    image, true, rotation, f35 = photograph
    crop = image.crop((750, 500, 2250, 1500))
    _, solution = _solved(_jpeg(crop, {0xA405: f35}), sky)
    assert solution.status == IDENTIFIED, solution.notes
    assert "around its hint" in solution.notes[0] and "no_match; then searched 2-110 deg" in solution.notes[0]
    assert _boresight_error_deg(solution, rotation) < 0.02  # the crop's centre is the photograph's
    assert solution.candidates[0].camera.focal_length_px == pytest.approx(true.focal_length_px, rel=0.01)


def test_a_hint_outside_the_fields_of_view_searched_is_set_aside_and_said_to_be(photograph, sky):
    """FocalLengthIn35mmFilm 2000 mm: 1.0 deg across the photograph, narrower than the search's 2 deg."""
    image, _, rotation, _ = photograph
    _, solution = _solved(_jpeg(image, {0xA405: 2000}), sky)
    assert solution.status == IDENTIFIED, solution.notes
    assert "its hint (a photograph's lens), 1.0 deg, lies outside the fields of view searched" in solution.notes[0]
    assert _boresight_error_deg(solution, rotation) < 0.02
