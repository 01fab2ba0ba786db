"""Real frames as a user's copies of them come: ``python -m app bench --suite variants [--frames DIR] [--n N] [--json]``.

The real frames (:mod:`app.bench.real`) were taken by three cameras; the product meets other images.
Each frame is copied five ways that change the image and not the sky, and every copy is solved as
``solve`` would solve it, with the copy's field of view given (exact) and with none:

* ``2x``: resampled to twice the width and height (bicubic): a finer sensor behind the same lens, or
  a photograph binned to the detection budget, whose lens's errors span twice as many pixels;
* ``half``: to half (Lanczos): a coarser sensor, or a copy shrunk to be sent;
* ``turned``: turned 37 deg about the image centre (bicubic), the corners black: a copy turned in an
  editor, and the black wedges' edges;
* ``cropped``: its left two thirds, the full height: the lens's axis a quarter of the copy's width off
  its centre (its distortion no longer centred), a narrower field with fewer stars;
* ``foreground``: the bottom fifth dark under a ragged edge: trees, a roof, a horizon.

The reference is astrometry.net's image centre (the frame's JSON) for the copies that keep the centre
pixel's direction (PIL resamples pixel areas: the centre of a 2x or half copy is the frame's centre;
a turn is about it); a crop's centre is its own centre pixel through the frame's WCS
(``NAME.wcs`` beside it).  Right: identified within :data:`app.bench.real.RIGHT_DEG` of it; wrong:
identified and over :data:`app.bench.real.WRONG_DEG` off.  The copies are made in a scratch folder
and removed.
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from app.bench.real import (RIGHT_DEG, SUMMARY_HEADER, WRONG_DEG, FramesUnavailable, RealFrame, solve_ours, suite_frames,
                            summarise, summary_columns)

#: The copies, in the order of the table.
VARIANTS = ("2x", "half", "turned", "cropped", "foreground")
#: The optics each copy is solved under: its exact field of view, and none.
OPTICS = ("exact", "none")
TURN_DEG = 37.0
CROP_FRACTION = 2.0 / 3.0
FOREGROUND_FRACTION = 0.2


def copy_size(variant: str, width: int, height: int) -> tuple[int, int]:
    """(width, height) of a copy of a ``width`` x ``height`` frame."""
    if variant == "2x":
        return 2 * width, 2 * height
    if variant == "half":
        return width // 2, height // 2
    if variant == "cropped":
        return int(width * CROP_FRACTION), height
    return width, height


def centre_in_frame(variant: str, width: int, height: int) -> tuple[float, float]:
    """Where the copy's centre pixel lies in the frame's own pixels (the project's convention, (0, 0) the
    centre of the top-left pixel): the frame's centre, but for a crop, the crop's centre."""
    if variant == "cropped":
        w, h = copy_size(variant, width, height)
        return (w - 1) / 2.0, (h - 1) / 2.0
    return (width - 1) / 2.0, (height - 1) / 2.0


def copy_fov_deg(variant: str, frame: RealFrame) -> float:
    """The copy's horizontal field of view: the frame's, but a crop's is its width's at the same focal length."""
    if variant != "cropped":
        return frame.fov_deg
    focal = frame.width / 2.0 / math.tan(math.radians(frame.fov_deg) / 2.0)
    return math.degrees(2.0 * math.atan(copy_size(variant, frame.width, frame.height)[0] / 2.0 / focal))


def make_copy(variant: str, pixels: np.ndarray) -> np.ndarray:
    """The copy of 8-bit luminance ``pixels`` (height, width)."""
    from PIL import Image

    image = Image.fromarray(pixels)
    width, height = image.size
    if variant in ("2x", "half"):
        return np.asarray(image.resize(copy_size(variant, width, height),
                                       Image.BICUBIC if variant == "2x" else Image.LANCZOS))
    if variant == "turned":
        return np.asarray(image.rotate(TURN_DEG, resample=Image.BICUBIC))
    if variant == "cropped":
        w, h = copy_size(variant, width, height)
        return pixels[:h, :w].copy()
    if variant == "foreground":
        x = np.arange(width)
        edge = (height * (1.0 - FOREGROUND_FRACTION) + 0.03 * height * np.sin(x / 37.0)
                + 0.02 * height * np.sin(x / 11.0)).astype(int)
        out = pixels.copy()
        out[np.arange(height)[:, None] >= edge[None, :]] = 3
        return out
    raise ValueError(f"unknown variant {variant!r}; choose from {', '.join(VARIANTS)}")


def copy_reference(variant: str, frame: RealFrame) -> tuple[float, float]:
    """RA, Dec (degrees) the copy's centre pixel sees."""
    if variant != "cropped":
        return frame.ra_deg, frame.dec_deg
    from astropy.io import fits
    from astropy.wcs import WCS

    header = frame.image.with_suffix(".wcs")
    if not header.is_file():
        raise FramesUnavailable(f"{frame.name}: the cropped copy's reference needs {header.name} beside the frame")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # astropy's notes on the SIP header
        ra, dec = WCS(fits.getheader(header), naxis=2).all_pix2world(
            [centre_in_frame(variant, frame.width, frame.height)], 0)[0]
    return float(ra), float(dec)


def run(n_sequences: int | None = None, seed: int = 1, frames_dir: str | Path | None = None) -> dict:
    """The suite (``seed`` unused: nothing is drawn); ``{"skipped": REASON}`` without frames."""
    from PIL import Image

    from app.identification import Sky

    try:
        folder, frames = suite_frames("variants", frames_dir, n_sequences)
    except FramesUnavailable as exc:
        return {"skipped": str(exc)}
    sky = Sky()
    rows = []
    load_before = round(os.getloadavg()[0], 2)
    with tempfile.TemporaryDirectory(prefix="starid-variants-") as scratch:
        copies, solving = Path(scratch, "copies"), Path(scratch, "solve")
        copies.mkdir()
        solving.mkdir()
        for frame in frames:
            pixels = np.asarray(Image.open(frame.image).convert("L"))
            for variant in VARIANTS:
                path = copies / f"{frame.name}-{variant}.png"
                Image.fromarray(make_copy(variant, pixels)).save(path)
                width, height = copy_size(variant, frame.width, frame.height)
                ra, dec = copy_reference(variant, frame)
                copy = replace(frame, name=path.stem, image=path, width=width, height=height, ra_deg=ra,
                               dec_deg=dec, fov_deg=copy_fov_deg(variant, frame), time=None)
                row = {"frame": frame.name, "variant": variant, "ours": {}}
                for optics in OPTICS:
                    row["ours"][optics] = solve_ours(copy, sky, copy.fov_deg if optics == "exact" else None, solving)
                rows.append(row)
            print(f"variants: {frame.name}: " + ", ".join(
                f"{r['variant']} {'/'.join(r['ours'][o]['status'] for o in OPTICS)}" for r in rows[-len(VARIANTS):]),
                file=sys.stderr)
    summary = {variant: {optics: summarise([r["ours"][optics] for r in rows if r["variant"] == variant])
                         for optics in OPTICS} for variant in VARIANTS}
    return {"frames_dir": str(folder), "n_frames": len(frames), "rows": rows, "summary": summary,
            "load_average_before": load_before, "load_average_after": round(os.getloadavg()[0], 2)}


def format_table(result: dict) -> str:
    if "skipped" in result:
        return f"skipped: {result['skipped']}"
    lines = [f"{result['n_frames']} real frames in {result['frames_dir']}, each copied {len(VARIANTS)} ways; "
             f"load average {result['load_average_before']} before, {result['load_average_after']} after",
             "", f"{'copy':<11} {'optics':<7} {SUMMARY_HEADER}"]
    for variant, by_optics in result["summary"].items():
        for optics, s in by_optics.items():
            lines.append(f"{variant:<11} {optics:<7} {summary_columns(s)}")
    lines.append(f"(right: identified within {RIGHT_DEG} deg of the reference centre; wrong: identified and over "
                 f"{WRONG_DEG} deg off; optics: the copy's exact field of view given, or none)")
    return "\n".join(lines)
