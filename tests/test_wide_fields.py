"""Wide fields of view (a photograph through a 14-24 mm lens spans 74-104 deg): rectilinear lenses with a barrel
distortion, rendered by the simulator, solved with their field of view given roughly and with none, against the
simulator's truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.attitude import angle_between
from app.identification import IDENTIFIED
from app.identification.scale_free import focal_length_for_fov


def _wide_photograph(fov_deg: float, corner_distortion: float, seed: int):
    """A 3000 x 2000 photograph through a rectilinear wide-angle lens with barrel distortion moving the sensor
    corner by ``corner_distortion`` of its radius (k1 < 0), stars to Hp 6 (a city-edge sky), as a PNG, with
    the simulator's truth and the true camera."""
    from app import simulate
    from app.camera import Camera

    width, height = 3000, 2000
    camera = Camera(width, height, focal_length_for_fov(width, fov_deg), (width - 1) / 2, (height - 1) / 2)
    true = simulate.true_optics(camera, k1=simulate.k1_for_corner_distortion(camera, corner_distortion))
    model = simulate.FrameModel(psf_sigma_px=1.5, detection_limit_mag=6.0, n_hot_pixels=0)
    frames, _, truth = simulate.simulate_frames(np.random.default_rng(seed), camera, n_frames=1, true_camera=true,
                                                model=model, hot_pixels=False)
    return simulate.frame_png_bytes(frames[0]), truth, true


@pytest.mark.parametrize("fov_deg", [75.0, 100.0])
def test_a_wide_angle_photograph_of_unknown_optics_is_identified_with_its_lens(sky, fov_deg):
    """Fields wider than 60 deg: a 24 mm lens on a full-frame camera spans 74 deg, a 15 mm one 100 deg. A
    rectilinear lens is a pinhole with a barrel distortion, which the optics fit (focal length and k1)
    recovers."""
    from app.frames import frames_to_sequence
    from app.identification import solve_sequence

    png, truth, true = _wide_photograph(fov_deg, -0.04, 1)
    solution = solve_sequence(frames_to_sequence([("wide.png", png)]).sequence, sky).solution
    assert solution.status == IDENTIFIED, solution.notes
    best = solution.candidates[0]
    R = np.asarray(truth["rotation_matrices"][0])
    assert math.degrees(angle_between(best.rotation_matrix[2], R[2])) < 0.02
    assert best.camera.focal_length_px == pytest.approx(true.focal_length_px, rel=0.005)
    assert best.camera.k1 == pytest.approx(true.k1, rel=0.1)


def test_a_focal_length_the_optics_fit_beyond_the_shapes_estimate_is_searched_there(sky):
    """At 70 deg with 5 % barrel distortion the bright triangles put the focal length 3.4 % short, beyond the
    2 % a found focal length is searched within. The right stars are caught there, and the optics fitted
    with them (the true focal length and k1) are then excluded by that 2 %: they are searched once more."""
    from app.frames import frames_to_sequence
    from app.identification import solve_sequence

    png, truth, true = _wide_photograph(70.0, -0.05, 3)
    solution = solve_sequence(frames_to_sequence([("wide.png", png)]).sequence, sky).solution
    assert solution.status == IDENTIFIED, solution.notes
    assert "no_match; the stars then fit 70.0" in solution.notes[0]  # the shapes' 71.85 deg, then the fit's
    R = np.asarray(truth["rotation_matrices"][0])
    assert math.degrees(angle_between(solution.candidates[0].rotation_matrix[2], R[2])) < 0.02
    assert solution.candidates[0].camera.focal_length_px == pytest.approx(true.focal_length_px, rel=0.005)


def test_a_field_of_views_focal_tolerance_is_its_five_per_cent_in_focal_length_plus_the_distortions_share():
    from app.frames.assemble import fov_focal_tolerance

    # By hand: f = w / 2 / tan(fov / 2). At 105 deg, 99.75 deg gives tan 49.875 = 1.18649 against tan 52.5 =
    # 1.30323 (f 9.84 % longer) and 110.25 deg tan 55.125 = 1.43480 (9.17 % shorter): 9.84 % + 5 %.
    assert fov_focal_tolerance(105.0) == pytest.approx(1.30323 / 1.18649 - 1 + 0.05, abs=2e-5)
    # A narrow field: 5 % of the angle is 5 % of the focal length (1 / 0.95 on the short side), plus 5 %.
    assert fov_focal_tolerance(2.0) == pytest.approx(1 / 0.95 - 1 + 0.05, abs=1e-4)
    assert fov_focal_tolerance(119.0) <= 0.2  # a camera model's bound



def test_a_wide_photographs_field_of_view_given_five_per_cent_short_is_searched_far_enough(sky):
    """105 deg given as 99.75 deg through a lens with a 6 % barrel at the corner: the focal length given is 9.8 %
    longer than the true one, and the pinhole that fits the stars best is shorter still, beyond a flat 10 %."""
    from app.frames import frames_to_sequence
    from app.identification import solve_sequence

    png, truth, true = _wide_photograph(105.0, -0.06, 1)
    solution = solve_sequence(frames_to_sequence([("wide.png", png)], fov_deg=105.0 * 0.95).sequence, sky).solution
    assert solution.status == IDENTIFIED, solution.notes
    R = np.asarray(truth["rotation_matrices"][0])
    assert math.degrees(angle_between(solution.candidates[0].rotation_matrix[2], R[2])) < 0.02


def _solve_photograph(tmp_path, sky, name: str, pixels: np.ndarray, true, rotation, fov_deg: float | None) -> dict:
    """A rendered photograph saved as a JPEG and solved as the wide bench solves it (``fov_deg`` None: none given)."""
    from app.bench.real import solve_ours
    from app.bench.wide import jpeg, photographed_frame

    path = tmp_path / f"{name}.jpg"
    path.write_bytes(jpeg(pixels))
    return solve_ours(photographed_frame(name, path, true, rotation), sky, fov_deg, tmp_path)


def test_a_photograph_with_its_date_and_settings_stamped_on_it_is_identified(tmp_path, sky):
    """A camera's stamp across the top ("2024-08-12 23:14:07  ISO 1600  f/2.8  30 s", saturated white, 40 px
    high) and a caption in a corner: 26 to 32 of the 32 sources reported were their characters, and the
    60 deg photograph was no match.  The characters stand in rows and are no stars now."""
    from PIL import Image, ImageDraw, ImageFont

    from app.bench.wide import photograph

    pixels, true, rotation, _ = photograph(60.0, np.random.default_rng([1, 75, 60, 1]), milky_way=False)
    image = Image.fromarray(pixels)
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default(size=40)
    draw.text((60, 60), "2024-08-12 23:14:07  ISO 1600  f/2.8  30 s", fill=255, font=font)
    draw.text((2200, 1900), "(c) J. Smith", fill=230, font=font)
    answer = _solve_photograph(tmp_path, sky, "stamped", np.asarray(image), true, rotation, None)
    assert answer["status"] == IDENTIFIED, answer["notes"]
    assert answer["error_deg"] < 0.02


@pytest.mark.parametrize("fov_deg, seed, options, said", [
    (40.0, [1, 74, 40, 4], {}, "a Milky Way"),
    (60.0, [1, 76, 60, 2], {"milky_way": False, "sky_limit_hp": 3.5}, "stars to Hp 3.5"),
    (90.0, [1, 74, 90, 1], {}, "a Milky Way"),
], ids=["milky-way", "towns-sky", "milky-way-and-glow"])
def test_a_photograph_over_a_treeline_is_identified(tmp_path, sky, fov_deg, seed, options, said):
    """Where a bright sky meets trees the mesh's level lies between the two, and the edge stood up as stars:

    * the Milky Way (52 DN at its middle, its clouds +-40 %) setting behind a ragged treeline, 40 deg: knots
      and spikes whose rings are part sky, part trees, their median the sky's: 21 of the 32 sources
      reported, and no match.  Their rings' quartiles span the step: uneven, set aside;
    * a town's sky (stars to Hp 3.5, 8 of them found) over trees, 60 deg: the sky between the branches, 8
      blobs reported after the stars, broke the pattern's triangles (no match).  Their apertures take in the
      dark beside them: no light above the sky (``no_flux``);
    * the Milky Way over a town's glow at 90 deg: a star and two knots of the glow were the only candidates
      bright enough to measure the PSF on, and it came out 1,900 px^2, which made the clouds' knots
      star-sized and the apertures 50 px wide (no match).  Candidates whose areas do not agree within a
      factor of 10 make no PSF; the frame's stars at 6 sigma make one."""
    from app.bench.wide import photograph

    pixels, true, rotation, described = photograph(fov_deg, np.random.default_rng(seed), **options)
    assert said in described and "landscape" in described
    answer = _solve_photograph(tmp_path, sky, "treeline", pixels, true, rotation, float(true.fov_deg[0]))
    assert answer["status"] == IDENTIFIED, answer["notes"]
    assert answer["error_deg"] < 0.02


@pytest.mark.parametrize("case, given", [("the lens's angle for the left half", 60.0), ("another lens's", 40.0)])
def test_a_field_of_view_given_by_hand_that_fits_nothing_is_set_aside_and_said_to(tmp_path, sky, case, given):
    """A photograph's owner gives the angle of the lens (or of another lens) for a crop: nothing is identified within
    that field of view's tolerance, and the stars alone would be. The photograph is searched again without it, its
    first search's hypotheses counted, and identified where the stars put it, with a note that the field of view
    given did not fit and what they fit. (Before: no match, with nothing said of the field of view.)"""
    from app.bench.wide import photograph
    from app.camera import Camera

    pixels, true, rotation, _ = photograph(60.0, np.random.default_rng([1, 75, 60, 2]), milky_way=False)
    if case.endswith("left half"):
        width = true.width // 2
        pixels = np.ascontiguousarray(pixels[:, :width])
        true = Camera(width, true.height, true.focal_length_px, true.cx, true.cy, k1=true.k1, k2=true.k2)
    answer = _solve_photograph(tmp_path, sky, "given-wrong", pixels, true, rotation, given)
    assert answer["status"] == IDENTIFIED, answer["notes"]
    assert answer["error_deg"] < 0.1  # right (app.bench.real.RIGHT_DEG); the crop's axis is a quarter off its centre
    assert answer["fov_deg"] == pytest.approx(true.fov_deg[0], rel=0.05)
    at = next(k for k, n in enumerate(answer["notes"]) if n.startswith(f"the field of view given, {given:.1f} deg, "
                                                                          "fits nothing"))
    said, how = answer["notes"][at:at + 2]
    assert f"the stars fit {answer['fov_deg']:.2f} deg" in said and len(said) < 200  # read first, whole
    assert how.startswith("searched again without it: searched 2-110 deg by the shapes")
    assert abs(focal_length_for_fov(true.width, given) / true.focal_length_px - 1) > 0.2  # far outside its tolerance


def test_a_calibrated_cameras_focal_length_is_never_set_aside(sky):
    """A camera declared to 5 % (a calibration, not a hand's guess) whose focal length is 15 % wrong: the search
    never leaves the declaration (a wrong camera model must not turn into an identification elsewhere), and says
    what the stars fit instead."""
    import json

    from app.camera import CAMERAS
    from app.frames import frames_to_sequence, parse_sidecar
    from app.identification import solve_sequence
    from app.identification.scale_free import NOT_GIVEN
    from app.simulate import frame_png_bytes, simulate_frames, true_optics

    camera = CAMERAS["tubsat-752x582-20deg"]
    frames, times, _ = simulate_frames(np.random.default_rng(31), camera, n_frames=1,
                                       true_camera=true_optics(camera, focal_error=0.15))
    sidecar = {"format": "tubsat-frames/1",
               "camera": {"focal_length_px": camera.focal_length_px, "cx": camera.cx, "cy": camera.cy,
                          "focal_length_tolerance": 0.05},
               "frames": [{"file": "f.png", "time": times[0].isoformat().replace("+00:00", "Z")}]}
    sequence = frames_to_sequence([("f.png", frame_png_bytes(frames[0]))],
                                  sidecar=parse_sidecar(json.dumps(sidecar))).sequence
    assert sequence.camera.focal_tolerance == pytest.approx(0.05)
    solved = solve_sequence(sequence, sky)
    assert solved.solution.status != IDENTIFIED
    assert not any("searched again without it" in n or n.startswith(NOT_GIVEN) for n in solved.solution.notes)
    assert solved.solution.focal_length_contradiction is not None


def test_random_points_given_a_field_of_view_are_searched_without_it_too_and_say_so(sky):
    """Twelve star-like spots scattered at random, given a field of view by hand: nothing is identified with it or
    without it; the answer stays the first search's, and its notes say the second search was made and found
    nothing."""
    import io

    from PIL import Image

    from app.frames import frames_to_sequence
    from app.identification import NO_MATCH, solve_sequence

    rng = np.random.default_rng(41)
    y, x = np.mgrid[0:600, 0:800]
    pixels = 20.0 + rng.normal(0, 2, x.shape)
    for cx, cy, peak in zip(rng.uniform(20, 780, 12), rng.uniform(20, 580, 12), rng.uniform(80, 200, 12)):
        pixels += peak * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * 1.3 ** 2))
    out = io.BytesIO()
    Image.fromarray(np.clip(pixels, 0, 255).astype(np.uint8)).save(out, format="PNG")
    sequence = frames_to_sequence([("random.png", out.getvalue())], fov_deg=20.0).sequence
    assert sequence.snapshots[0].n_sources >= 10
    solved = solve_sequence(sequence, sky)
    assert solved.solution.status == NO_MATCH
    assert "searched again without the field of view given (20.0 deg): no match there" in solved.solution.notes
