"""Copies of real frames that keep their sky (:mod:`app.bench.variants`) are identified as the frames
themselves are.

The reference is astrometry.net's image centre of the development set (``../shared/real-frames``, its
README; a crop's: its own centre pixel through the frame's WCS).  The frames are ones that solve as
they are and that, copied,

* at twice their sampling (a finer sensor behind the same lens, or a photograph binned to the
  detection budget), lost their brightest stars to a fixed limit of 2,000 px on a star's blob, and
  then were judged with the tolerances of a 0.7 px sighting noise where their lens's own distortion
  spans twice as many pixels (the shapes of their bright triangles checked within 5 px);
* at twice their sampling without a field of view, were searched only at the focal length of the first
  shape that fitted, 1 % short, and the better fit of all its stars (3 % longer) was reported as a
  declaration contradicted, when nothing was declared;
* cropped to a narrow field (6 deg to 4 deg) without a field of view, found no shape match among the
  deep catalogue's thousands before each band's bound, and were not searched by bright pairs.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from PIL import Image, ImageOps

from app.bench import variants
from app.bench.real import RIGHT_DEG, default_frames_dir, load_frame
from app.camera import Camera
from app.extraction import DEFAULT_SIGHTING_SIGMA_PX, assumed_sighting_noise_px
from app.frames import frames_to_sequence
from app.identification import IDENTIFIED, NO_MATCH, Sky, solve_sequence

def _copy_png(frame, variant: str) -> bytes:
    stream = io.BytesIO()
    Image.fromarray(variants.make_copy(variant, np.asarray(Image.open(frame.image).convert("L")))).save(stream, format="PNG")
    return stream.getvalue()


def _separation_deg(a, b) -> float:
    (ra1, de1), (ra2, de2) = np.radians(a), np.radians(b)
    cosine = math.sin(de1) * math.sin(de2) + math.cos(de1) * math.cos(de2) * math.cos(ra1 - ra2)
    return math.degrees(math.acos(min(1.0, cosine)))


def test_the_assumed_sighting_noise_grows_with_the_sampling_beyond_1400_px():
    """0.7 px to 1,400 px across (the sensors it was checked on keep it); 0.05 % of the larger side beyond."""
    def camera(width, height):
        return Camera(width=width, height=height, focal_length_px=1000.0, cx=(width - 1) / 2, cy=(height - 1) / 2)

    assert assumed_sighting_noise_px(camera(752, 582)) == DEFAULT_SIGHTING_SIGMA_PX
    assert assumed_sighting_noise_px(camera(1392, 1040)) == DEFAULT_SIGHTING_SIGMA_PX
    assert assumed_sighting_noise_px(camera(2784, 2080)) == pytest.approx(1.392)
    assert assumed_sighting_noise_px(camera(1000, 4000)) == pytest.approx(2.0)


@pytest.mark.parametrize("name, variant, field_of_view_given", [
    ("xmas-image5", "2x", True), ("feb16-6", "2x", True), ("feb16-6", "2x", False), ("xmas-image0", "2x", False),
    ("may8-gain40-img0", "cropped", False)])
def test_a_copy_of_a_real_frame_is_identified(name, variant, field_of_view_given):
    """With its field of view, and without (the scale from the shapes of its bright triangles, whose check
    radius follows the sighting noise; searched again where all the stars the first shape caught fit a
    focal length beyond its 2 %; when no shape fits, from bright pairs band by band). Without a field of
    view nothing was declared, so no declaration is said to be contradicted."""
    folder = default_frames_dir()
    if not (folder / "README.md").is_file():
        pytest.fail(f"the real frames are missing: expected them in {folder} (../shared/real-frames beside the "
                    "repository, or $STARID_REAL_FRAMES)")
    frame = load_frame(folder / f"{name}.json")
    frame_pass = frames_to_sequence([(f"{name}-{variant}.png", _copy_png(frame, variant))],
                                    fov_deg=variants.copy_fov_deg(variant, frame) if field_of_view_given else None)
    solved = solve_sequence(frame_pass.sequence, Sky())
    assert solved.solution.status == IDENTIFIED, solved.solution.notes
    assert field_of_view_given or solved.solution.focal_length_contradiction is None
    centre = solved.solution.candidates[0].centre_radec_deg
    assert _separation_deg(centre, variants.copy_reference(variant, frame)) < RIGHT_DEG


@pytest.mark.parametrize("name, field_of_view_given", [("xmas-image4", True), ("feb16-2", False)])
def test_a_mirrored_real_frame_is_no_match_and_said_to_match_mirrored_where_the_frame_is(name, field_of_view_given):
    """A rotation cannot mirror: the frame flipped left to right (a FITS file stored bottom-up with no ROWORDER,
    a flip in processing) matches no sky, and said nothing of why.  Its mirror image, searched once more, is
    identified, and the note gives its boresight: that of the frame as it is, to 0.05 deg."""
    folder = default_frames_dir()
    if not (folder / "README.md").is_file():
        pytest.fail(f"the real frames are missing: expected them in {folder} (../shared/real-frames beside the "
                    "repository, or $STARID_REAL_FRAMES)")
    frame = load_frame(folder / f"{name}.json")
    pixels = np.asarray(Image.open(frame.image).convert("L"))
    fov = frame.fov_deg if field_of_view_given else None
    results = []
    for image in (pixels, pixels[:, ::-1]):
        stream = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(image)).save(stream, format="PNG")
        results.append(solve_sequence(frames_to_sequence([(f"{name}.png", stream.getvalue())], fov_deg=fov).sequence,
                                      Sky()).solution)
    as_it_is, flipped = results
    assert as_it_is.status == IDENTIFIED and not any("mirrored" in note for note in as_it_is.notes)
    assert flipped.status == NO_MATCH
    (said,) = [note for note in flipped.notes if note.startswith("mirrored left to right, the sources are identified")]
    ra, dec = (float(said.split("RA ")[1].split(" deg")[0]), float(said.split("Dec ")[1].split(" deg")[0]))
    boresight = as_it_is.candidates[0].radec_roll_deg[:2]
    assert _separation_deg((ra, dec), boresight) < 0.05


@pytest.mark.parametrize("orientation, stored", [(6, lambda a: np.rot90(a, 1)), (3, lambda a: a[::-1, ::-1]),
                                                 (5, lambda a: a.T)], ids=["quarter", "upside-down", "transposed"])
def test_a_real_frame_stored_turned_with_its_exif_orientation_is_read_upright(orientation, stored):
    """A phone or camera held upright stores its image turned and says so in EXIF ``Orientation`` (6: turn a
    quarter clockwise to see it; 3: upside down; 5: transposed).  The frame stored so is read as the upright
    image, as Pillow's own ``exif_transpose`` shows it: the same sources at the same pixels, the same sky, and
    a note saying so.  It was read as stored: its pixel positions were not those of the picture the operator
    sees."""
    folder = default_frames_dir()
    if not (folder / "README.md").is_file():
        pytest.fail(f"the real frames are missing: expected them in {folder} (../shared/real-frames beside the "
                    "repository, or $STARID_REAL_FRAMES)")
    frame = load_frame(folder / "xmas-image4.json")
    upright = np.asarray(Image.open(frame.image).convert("L"))
    passes = []
    for pixels, tag in ((upright, None), (stored(upright), orientation)):
        exif = Image.Exif()
        if tag is not None:
            exif[0x0112] = tag
        stream = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(pixels)).save(stream, format="PNG", exif=exif)
        passes.append(frames_to_sequence([("xmas-image4.png", stream.getvalue())], fov_deg=frame.fov_deg))
    as_it_is, turned = passes
    assert ImageOps.exif_transpose(Image.open(io.BytesIO(stream.getvalue()))).size == (frame.width, frame.height)
    (first,), (second,) = as_it_is.sequence.snapshots, turned.sequence.snapshots
    assert np.allclose(first.xy, second.xy, atol=1e-3) and len(first.xy) >= 10
    assert any("EXIF Orientation" in note for note in turned.sequence.extra["frames"].get("notes", []))
    assert not as_it_is.sequence.extra["frames"].get("notes")
    solutions = [solve_sequence(p.sequence, Sky()).solution for p in passes]
    assert [s.status for s in solutions] == [IDENTIFIED, IDENTIFIED]
    assert _separation_deg(solutions[0].candidates[0].radec_roll_deg[:2],
                           solutions[1].candidates[0].radec_roll_deg[:2]) < 1e-6
