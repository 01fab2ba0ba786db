"""Wide-angle photographs: ``python -m app bench --suite wide [--n N] [--seed S] [--json]``.

The real frames (:mod:`app.bench.real`) span 6-27 deg; a photograph of the night sky is often taken with a
wide lens (a 24 mm lens on a full-frame camera spans 74 deg, a 14 mm one 104 deg). ``N`` photographs
(default 8) at each of :data:`FIELDS_DEG` are rendered by the simulator (:func:`app.simulate.simulate_frames`):

* 3000 x 2000 px, 8 bit, saved as JPEG (quality 92), as a camera or a phone gives them;
* a rectilinear lens: a pinhole with a radial distortion (k1) moving the sensor corner by up to 6 % of its
  radius inwards (barrel) at 105 deg, in proportion to the field (2.3 % at 40 deg), or a fifth of that outwards
  (pincushion; drawn uniformly): photographic lenses measured before software correction, a 14 mm lens
  -1.5 to -5 %, a 24 mm one -2 to -3 %, a 50 mm one -1 to +0.5 %; the principal point centred;
* a sky whose stars are detected to Hp 4.5-6.5 (a town's sky to a dark one; drawn), a point-spread of
  1.0-2.0 px (drawn), bright stars saturated;
* a landscape under a ragged horizon over the bottom 0-30 % (drawn), with a town's glow above it fading
  over a quarter of the height (0-40 DN; drawn): trees, hills, a roof;
* on half of them a Milky Way: a band 700 px wide (FWHM 820) at a random angle through the centre, 20-60 DN
  (drawn) with star clouds of +-40 % over 25 px and a finer grain of +-15 % over 4 px;
* a random pointing, no time (solved at J2000.0, as a photograph with no EXIF time is).

Each is solved through the ``solve`` workflow (:func:`app.bench.real.solve_ours`) with its exact field of
view (the pinhole's, at the true focal length), with one 5 % off (long and short in turn), with none but the
lens's 35 mm equivalent in its EXIF (:mod:`app.frames.lens`), and with none.
Right: identified within :data:`app.bench.real.RIGHT_DEG` of the true direction of the image's centre
pixel; wrong: identified and over :data:`app.bench.real.WRONG_DEG` off.
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from app.bench.real import (RIGHT_DEG, SUMMARY_HEADER, WRONG_DEG, RealFrame, solve_ours, summarise,
                            summary_columns)
from app.catalogue import vectors_to_radec
from app.frames.lens import FOCAL_LENGTH_35MM, FULL_FRAME_DIAGONAL_MM
from app.frames.times import EXIF_IFD

#: Horizontal fields of view of the rows, degrees.
FIELDS_DEG = (40.0, 60.0, 75.0, 90.0, 105.0)
#: The optics each photograph is solved under: the exact field of view, one 5 % off, none but the lens in its
#: EXIF, none.
OPTICS = ("exact", "5 % off", "EXIF", "none")
SIZE_PX = (3000, 2000)
#: Radial distortion at the sensor corner of a 105 deg lens, a fraction of its radius (drawn uniformly; a
#: narrower lens's in proportion to its field).
CORNER_DISTORTION_AT_105_DEG = (-0.06, 0.012)
#: Faintest star detected, Hp (drawn uniformly): a town's sky to a dark one.
SKY_LIMIT_HP = (4.5, 6.5)
PSF_SIGMA_PX = (1.0, 2.0)
JPEG_QUALITY = 92
#: Part of the height under the horizon, and the town's glow above it in DN (each drawn uniformly).
LANDSCAPE_FRACTION = (0.0, 0.3)
GLOW_DN = (0.0, 40.0)
#: The Milky Way's brightness at its middle, DN (drawn uniformly), on every other photograph.
MILKY_WAY_DN = (20.0, 60.0)
DEFAULT_N = 8


def photograph(fov_deg: float, rng: np.random.Generator, *, smear_px: float = 0.0, milky_way: bool = True,
               sky_limit_hp: float | None = None):
    """(8-bit pixels, the true camera, the truth's ICRS -> camera rotation, a description) of one photograph.

    ``smear_px``: every star trailed over that many pixels in one direction (drawn), as from a fixed tripod
    (:mod:`app.bench.trails`); ``milky_way`` False: none on any; ``sky_limit_hp``: the faintest star detected
    (a town's sky of Hp 3.5, say) instead of one drawn from :data:`SKY_LIMIT_HP` (the draw is made anyway, so
    the rest of the photograph stays the same)."""
    from app import simulate
    from app.camera import Camera
    from app.identification.scale_free import focal_length_for_fov

    width, height = SIZE_PX
    camera = Camera(width, height, focal_length_for_fov(width, fov_deg), (width - 1) / 2, (height - 1) / 2)
    corner = float(rng.uniform(*CORNER_DISTORTION_AT_105_DEG)) * fov_deg / 105.0
    true = simulate.true_optics(camera, k1=simulate.k1_for_corner_distortion(camera, corner))
    limit = float(rng.uniform(*SKY_LIMIT_HP))
    limit = limit if sky_limit_hp is None else float(sky_limit_hp)
    # 8 bit: a dark sky of ~25 DN over a bias of 10, its noise ~2 DN; the brightest stars saturate at 255.
    smear = {"smear_px": smear_px, "smear_angle_deg": float(rng.uniform(0.0, 180.0))} if smear_px > 0 else {}
    model = simulate.FrameModel(psf_sigma_px=float(rng.uniform(*PSF_SIGMA_PX)), detection_limit_mag=limit, bits=8,
                                bias_adu=10.0, gain_e_per_adu=8.0, n_hot_pixels=0, **smear)
    frames, _, truth = simulate.simulate_frames(rng, camera, n_frames=1, true_camera=true, model=model,
                                                hot_pixels=False)
    landscape = float(rng.uniform(*LANDSCAPE_FRACTION))
    glow = float(rng.uniform(*GLOW_DN))
    band = float(rng.uniform(*MILKY_WAY_DN)) if rng.uniform() < 0.5 and milky_way else 0.0
    pixels = with_landscape(with_milky_way(frames[0], band, rng), landscape, glow, rng)
    described = (f"distortion {100 * corner:+.1f} % at the corner, stars to Hp {limit:.1f}"
                 + (f", trailed {smear_px:g} px" if smear_px > 0 else "")
                 + f", landscape {100 * landscape:.0f} % under a glow of {glow:.0f} DN"
                 + (f", a Milky Way of {band:.0f} DN" if band else ""))
    return pixels, true, np.asarray(truth["rotation_matrices"][0]), described


def jpeg(pixels: np.ndarray, focal_35mm: int | None = None) -> bytes:
    """``pixels`` as a JPEG (quality :data:`JPEG_QUALITY`), its EXIF holding ``FocalLengthIn35mmFilm`` when given,
    as a camera's does (the same pixels encode the same with and without it)."""
    import io

    from PIL import Image

    exif = Image.Exif()
    if focal_35mm is not None:
        exif.get_ifd(EXIF_IFD)[FOCAL_LENGTH_35MM] = int(focal_35mm)
    stream = io.BytesIO()
    Image.fromarray(pixels).save(stream, format="JPEG", quality=JPEG_QUALITY, exif=exif)
    return stream.getvalue()


def with_milky_way(pixels: np.ndarray, middle_dn: float, rng: np.random.Generator) -> np.ndarray:
    """8-bit ``pixels`` under a band of glow through the centre at a random angle (Gaussian across, sigma
    350 px, ``middle_dn`` at its middle) with star clouds and a grain (smoothed noise over 25 and 4 px, +-40 %
    and +-15 %); unchanged when ``middle_dn`` is 0."""
    if middle_dn <= 0:
        return pixels
    from scipy.ndimage import gaussian_filter

    height, width = pixels.shape
    rows, cols = np.mgrid[:height, :width]
    angle = rng.uniform(0.0, np.pi)
    across = (cols - width / 2) * np.sin(angle) - (rows - height / 2) * np.cos(angle)
    texture = np.ones((height, width))
    for scale, depth in ((25.0, 0.4), (4.0, 0.15)):
        noise = gaussian_filter(rng.standard_normal((height, width)), scale)
        texture += depth * noise / noise.std()
    band = middle_dn * np.exp(-0.5 * (across / 350.0) ** 2) * np.clip(texture, 0.0, None)
    return np.clip(np.round(pixels + band), 0, 255).astype(np.uint8)


def with_landscape(pixels: np.ndarray, fraction: float, glow_dn: float, rng: np.random.Generator) -> np.ndarray:
    """8-bit ``pixels`` with the bottom ``fraction`` of the height dark (a few DN of noise) under a ragged
    horizon (two sine waves of random phase and a treeline's jitter), and a glow of ``glow_dn`` at the horizon
    fading as exp(-height above it / a quarter of the frame's height)."""
    height, width = pixels.shape
    x = np.arange(width)
    horizon = height * (1.0 - fraction) + height * (
        0.03 * np.sin(x / 83.0 + rng.uniform(0, 2 * np.pi)) + 0.015 * np.sin(x / 19.0 + rng.uniform(0, 2 * np.pi))
        + 0.004 * rng.standard_normal(width))
    above = horizon[None, :] - np.arange(height)[:, None]
    out = pixels.astype(float) + glow_dn * np.exp(-np.clip(above, 0, None) / (0.25 * height))
    ground = above < 0
    out[ground] = 4.0 + 1.5 * rng.standard_normal(int(ground.sum()))
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def focal_length_35mm(camera) -> int:
    """The whole millimetres EXIF's ``FocalLengthIn35mmFilm`` gives for ``camera`` (through the diagonal)."""
    return round(camera.focal_length_px * FULL_FRAME_DIAGONAL_MM / math.hypot(camera.width, camera.height))


def centre_radec_deg(true_camera, rotation: np.ndarray) -> tuple[float, float]:
    """The true sky direction (ICRS RA, Dec, degrees) of the image's centre pixel."""
    centre = np.array([[(true_camera.width - 1) / 2, (true_camera.height - 1) / 2]])
    ra, dec = vectors_to_radec(true_camera.pixels_to_vectors(centre) @ rotation)
    return math.degrees(float(ra[0])), math.degrees(float(dec[0]))


def photographed_frame(name: str, image: Path, true_camera, rotation: np.ndarray) -> RealFrame:
    """A rendered photograph saved as ``image``, as the real-frame benches take a frame: its reference the true
    direction of its centre pixel and its exact field of view, no time."""
    ra, dec = centre_radec_deg(true_camera, rotation)
    return RealFrame(name=name, image=image, width=true_camera.width, height=true_camera.height, ra_deg=ra,
                     dec_deg=dec, fov_deg=true_camera.fov_deg[0], time=None)


def run(n_sequences: int | None = None, seed: int = 1) -> dict:
    from app.identification import Sky

    n = DEFAULT_N if n_sequences is None else n_sequences
    sky = Sky()
    load_before = round(os.getloadavg()[0], 2)
    rows = []
    with tempfile.TemporaryDirectory(prefix="starid-wide-") as scratch:
        for fov in FIELDS_DEG:
            for i in range(n):
                rng = np.random.default_rng([seed, 74, int(fov), i])
                pixels, true, rotation, described = photograph(fov, rng)
                name = f"wide-{fov:g}deg-{i}"
                with_lens, without = Path(scratch, f"{name}-exif.jpg"), Path(scratch, f"{name}.jpg")
                with_lens.write_bytes(jpeg(pixels, focal_length_35mm(true)))
                without.write_bytes(jpeg(pixels))
                frame = photographed_frame(name, without, true, rotation)
                exact = frame.fov_deg
                off = exact * (1.05 if i % 2 == 0 else 0.95)
                given = {"exact": exact, "5 % off": off, "EXIF": None, "none": None}
                row = {"name": name, "fov_deg": fov, "photograph": described, "ours": {
                    optics: solve_ours(replace(frame, image=with_lens) if optics == "EXIF" else frame, sky,
                                       given[optics], Path(scratch)) for optics in OPTICS}}
                rows.append(row)
                print(f"wide: {name} ({described}): "
                      + ", ".join(f"{o} {row['ours'][o]['status']}" for o in OPTICS), file=sys.stderr)
    summary = {f"{fov:g}": {optics: summarise([r["ours"][optics] for r in rows if r["fov_deg"] == fov])
                            for optics in OPTICS} for fov in FIELDS_DEG}
    summary["all"] = {optics: summarise([r["ours"][optics] for r in rows]) for optics in OPTICS}
    return {"n_per_field": n, "seed": seed, "rows": rows, "summary": summary, "load_average_before": load_before,
            "load_average_after": round(os.getloadavg()[0], 2)}


def format_table(result: dict) -> str:
    lines = [f"{result['n_per_field']} photographs a field of view, seed {result['seed']}; load average "
             f"{result['load_average_before']} before, {result['load_average_after']} after",
             "", f"{'field':<7} {'optics':<8} {SUMMARY_HEADER}"]
    for field, by_optics in result["summary"].items():
        for optics, s in by_optics.items():
            label = field if field == "all" else f"{field} deg"
            lines.append(f"{label:<7} {optics:<8} {summary_columns(s)}")
    lines.append(f"(right: identified within {RIGHT_DEG} deg of the image centre's true direction; wrong: identified "
                 f"and over {WRONG_DEG} deg off)")
    return "\n".join(lines)
