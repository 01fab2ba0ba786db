"""Lost in space with an unknown field of view: the scale from the stars themselves.

Why.  A photograph, or a star-tracker test frame, often comes with no optics
at all.  The bright-pair lookup needs the scale (an edge is looked up by its
angle), but a triangle's *shape* does not depend on it
(:mod:`.focal_estimate`): one lookup by shape finds the catalogue triangles a
pattern triangle can be whatever the focal length, and each says which focal
length it needs.  astrometry.net searches without a scale the same way (with
four-star "quads"), as does tetra3 within its ``fov_max_error``.

A hint first.  A camera that keeps ``focal_length_unknown`` but has a ``focal_length_tolerance`` carries a
hint (a photograph's EXIF lens, :mod:`app.frames.lens`): its focal length is searched first, as if declared
to that tolerance; where nothing is identified there (a cropped photograph keeps its lens's EXIF), the bands
follow, the hint's hypotheses counted.

Bands.  The fields of view from :data:`FOV_RANGE_DEG` are split into bands
whose focal lengths differ by :data:`BAND_RATIO` at most; each band is a
nominal camera at its middle focal length, known to the band's half-width.
Within a band the check radius (pixels at the nominal focal length) and the
shape lookup's range of sizes are those of a declared camera with that
tolerance, and the catalogue depth is the band's (:meth:`app.identification.sky.Sky.for_camera`:
a narrow field needs fainter stars to hold a pattern).  The bands are
searched from the widest field down (the shallow catalogue and large
triangles are the cheapest), each by :func:`focal_estimate`, whose chance
test counts every shape match checked.

Bright pairs when no shape fits.  When no band's triangles fit a focal length (a narrow field's few
bright stars, whose shapes the deep catalogue matches by the thousand: its band stops at
:data:`BAND_MAX_TRIED` shape matches first), each band is searched as a declared camera at its middle
focal length known to its half-width, widest first, by the engine's own search over focal lengths
(bright pairs, :mod:`.focal_scan`), until one is identified.  It costs a frame that matches nothing about
a second (every band's pairs) where the shapes alone take a tenth; the time-out bounds it.

Answer.  At the first band whose triangles fit a focal length beyond chance,
the pattern is identified as if that focal length had been declared, known to
:data:`FOUND_TOLERANCE` (:func:`app.identification.engine.identify`: bright
pairs, the estimate's own match as a hypothesis, refinement, the optics fit,
the false-match probability).  Where that finds nothing credible and the stars fit a focal length
beyond :data:`FOUND_TOLERANCE` (the triangles' refit on every point they caught, or the optics fitted
with a candidate: a wide lens's barrel moves the best pinhole by a few per cent), it is searched there
once more.  Every shape match checked in the bands before
counts among its hypotheses, so the false-match probability pays for the
search over scales.  A band whose identification is not ``identified`` does
not stop the search; the best answer found is returned, with notes saying
what was searched and where the scale came from.

Bound.  Each band checks at most :data:`BAND_MAX_TRIED` shape matches, and the whole search stops at ``options.timeout_s``.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, replace
from datetime import datetime
from typing import Callable

import numpy as np

from app.camera import Camera
from app.identification.candidates import prepare_pattern
from app.identification.focal_estimate import focal_estimate
from app.identification.options import SearchOptions
from app.identification.result import AMBIGUOUS, IDENTIFIED, NO_MATCH, Solution
from app.identification.sky import Sky

#: Horizontal fields of view searched when the optics are unknown, degrees: from a long lens on a star
#: tracker's test bench to a rectilinear wide-angle photographic lens (a 24 mm lens on a full-frame camera spans
#: 74 deg, a 14 mm one 104 deg; a rectilinear lens is a pinhole with a barrel distortion that the optics fit's
#: k1 takes up). A fisheye is no pinhole at all. Narrower than 2 deg, Hipparcos holds too few stars.
FOV_RANGE_DEG = (2.0, 110.0)
#: Largest ratio of focal lengths within one band: the check radius (5 px at the band's middle) stays within
#: 4-6 px of the truth, and the shape lookup's size range is a declared camera's at +-20 %.
BAND_RATIO = 1.5
#: Shape matches checked at most in one band: a band spans +-20 % of scale where a declared camera spans its
#: +-5-10 %, so its triangles have several times the shape matches (:data:`focal_estimate.MAX_TRIED` for a
#: declared camera), and on real frames the first triangles often hold an artefact.
BAND_MAX_TRIED = 6000
#: The focal length a band's triangles fit is then known to this fraction: the estimate errs by ~0.1 % (all
#: the caught points' pairs), a real lens's distortion moves the best pinhole focal length by ~1 %.
FOUND_TOLERANCE = 0.02


@dataclass(frozen=True)
class Band:
    """Focal lengths from ``low_px`` to ``high_px`` (a narrower field of view at the higher)."""

    low_px: float
    high_px: float

    @property
    def middle_px(self) -> float:
        return 0.5 * (self.low_px + self.high_px)

    @property
    def tolerance(self) -> float:
        """Half the band's width over its middle: the band as a declared camera's tolerance."""
        return (self.high_px - self.low_px) / (self.high_px + self.low_px)


#: How the notes of a search over scales begin (:func:`identify_unknown_scale`).
NOT_GIVEN = "the field of view was not given: "


def focal_length_for_fov(width_px: int, fov_deg: float) -> float:
    """The pinhole focal length (pixels) at which ``width_px`` spans ``fov_deg`` horizontally."""
    return (width_px / 2.0) / math.tan(math.radians(fov_deg) / 2.0)


def fov_for_focal_length(width_px: int, focal_length_px: float) -> float:
    """The horizontal field of view (degrees) of ``width_px`` at ``focal_length_px``."""
    return 2.0 * math.degrees(math.atan(width_px / 2.0 / focal_length_px))


def bands(width_px: int, fov_range_deg: tuple[float, float] = FOV_RANGE_DEG,
          ratio: float = BAND_RATIO) -> list[Band]:
    """The bands covering ``fov_range_deg`` for a sensor ``width_px`` wide, widest field (shortest focal
    length) first, in equal steps of log focal length no larger than ``ratio``."""
    f_short = focal_length_for_fov(width_px, max(fov_range_deg))
    f_long = focal_length_for_fov(width_px, min(fov_range_deg))
    n = max(1, math.ceil(math.log(f_long / f_short) / math.log(ratio) - 1e-9))
    edges = f_short * (f_long / f_short) ** (np.arange(n + 1) / n)
    return [Band(float(a), float(b)) for a, b in zip(edges[:-1], edges[1:])]


def identify_unknown_scale(pattern, camera: Camera, t: datetime, sky: Sky, *, velocity_km_s=None,
                           options: SearchOptions = SearchOptions(),
                           planets: Callable[[], dict[str, np.ndarray]] | None = None,
                           method: str = "bright_pair",
                           identify: Callable[..., Solution], hypotheses_before: int = 0) -> Solution:
    """Identify ``pattern`` (see :func:`app.identification.engine.identify`) seen by ``camera``, whose focal
    length is unknown (``camera.focal_length_unknown``): the scale searched band by band (module doc).

    ``identify`` is the engine's own function (passed in: the engine calls this one), run at the focal length
    a band's triangles fit; ``hypotheses_before`` counts those a caller tried for this pattern already (a field
    of view given that fitted nothing): they enter the false-match probability.
    """
    searched_bands = bands(camera.width)
    nominals = [replace(camera.known_at(band.middle_px, band.tolerance), mag_limit=None) for band in searched_bands]
    hinted = _hinted(camera)
    hint_sky = sky.for_camera(hinted) if hinted is not None else None
    # Each band's catalogue depth, loaded (or, the first time ever, built: the Hp 8 index takes 15-25 s)
    # before the clock starts: a first narrow field must not lose its search to the building.
    band_skies = [sky.for_camera(nominal) for nominal in nominals]
    started = _time.perf_counter()
    tried = hypotheses_before
    searched: list[str] = []
    best: Solution | None = None

    def solve_at(known: Camera, band_sky: Sky, focal_length_from: str) -> Solution:
        """The pattern identified as ``known`` sees it (a focal length known to a tolerance, whose origin the
        notes name), every hypothesis tried so far counted (and the count carried on); each candidate keeps the
        camera it was found with (the declared one had no focal length)."""
        nonlocal tried
        solution = identify(replace(pattern, vectors=known.pixels_to_vectors(pattern.xy)), known, t, band_sky,
                            velocity_km_s=velocity_km_s, options=options, planets=planets, method=method,
                            hypotheses_before=tried, focal_length_from=focal_length_from)
        tried = max(tried, solution.n_hypotheses)
        return replace(solution, candidates=tuple(c if c.camera is not None else replace(c, camera=known)
                                                  for c in solution.candidates))

    hint_note = ""
    if hinted is not None:
        best = solve_at(hinted, hint_sky, "hinted")
        f, tolerance = hinted.focal_length_px, hinted.focal_tolerance
        hint_note = (f"searched first around its hint (a photograph's lens), "
                     f"{fov_for_focal_length(camera.width, f):.1f} deg "
                     f"({_fovs(camera, Band(f * (1 - tolerance), f * (1 + tolerance)))} deg), {best.status}"
                     + ("; then " if best.status != IDENTIFIED else ""))
    elif camera.focal_length_tolerance is not None:  # a hint outside FOV_RANGE_DEG
        hint_note = (f"its hint (a photograph's lens), {fov_for_focal_length(camera.width, camera.focal_length_px):.1f} "
                     "deg, lies outside the fields of view searched and was set aside; ")
    shapes_fitted = False
    for band, nominal, band_sky in zip(searched_bands, nominals, band_skies):
        if best is not None and best.status == IDENTIFIED:
            break
        if _time.perf_counter() - started > options.timeout_s:
            searched.append("time-out")
            break
        seen = replace(pattern, vectors=nominal.pixels_to_vectors(pattern.xy))
        prepared = prepare_pattern(seen, nominal, t, band_sky, velocity_km_s, options)
        checked: list[int] = []
        estimate = focal_estimate(prepared, band_sky.bright_triangles(), options, band.tolerance, checked,
                                  BAND_MAX_TRIED)
        tried += sum(checked)
        fovs = _fovs(camera, band)
        if estimate is None:
            searched.append(f"{fovs} deg (stars to Hp {band_sky.depth_for(nominal, options.mag_margin):.1f}): "
                            f"no fit in {sum(checked)} triangles")
            continue
        shapes_fitted = True
        solution = solve_at(camera.known_at(estimate.focal_length_px, FOUND_TOLERANCE), band_sky, "triangles' fitted")
        fov = fov_for_focal_length(camera.width, estimate.focal_length_px)
        searched.append(f"{fovs} deg: the triangles fit {fov:.2f} deg ({estimate.focal_length_px:.1f} px, "
                        f"{estimate.n_matched} of {estimate.n_points} points), {solution.status}")
        refit = _stars_fit_beyond(solution, estimate.focal_length_px)
        if solution.status != IDENTIFIED and refit is not None:
            # Nothing was declared: what lies beyond the search is the stars' own better fit. On a lens whose
            # distortion moves the best pinhole focal length by a few per cent (a wide field's barrel), the first
            # shape's estimate can be 2-4 % off. Searched there once.
            solution = solve_at(camera.known_at(refit, FOUND_TOLERANCE), band_sky, "stars' fitted")
            searched.append(f"the stars then fit {fov_for_focal_length(camera.width, refit):.2f} deg "
                            f"({refit:.1f} px), {solution.status}")
        if best is None or _better(solution, best):
            best = solution
        if solution.status == IDENTIFIED:
            break
    if not shapes_fitted and (best is None or best.status != IDENTIFIED):
        # No shape fitted anywhere: each band's focal lengths searched by bright pairs.
        for band, nominal, band_sky in zip(searched_bands, nominals, band_skies):
            if _time.perf_counter() - started > options.timeout_s:
                searched.append("time-out")
                break
            solution = solve_at(nominal, band_sky, "band's middle")
            searched.append(f"{_fovs(camera, band)} deg by bright pairs: {solution.status}")
            if best is None or _better(solution, best):
                best = solution
            if solution.status == IDENTIFIED:
                break
    elapsed = _time.perf_counter() - started
    note = NOT_GIVEN + hint_note
    if searched:
        note += (f"searched {FOV_RANGE_DEG[0]:g}-{FOV_RANGE_DEG[1]:g} deg by the shapes of the pattern's bright "
                 "triangles, widest first (" + "; ".join(searched) + ")")
    if best is None:
        return Solution(status=NO_MATCH, candidates=(), elapsed_s=elapsed, notes=(note,), n_hypotheses=tried)
    # No focal length was declared, so none is contradicted: what the stars fitted is in the note above.
    return replace(best, elapsed_s=elapsed, notes=(note, *best.notes), n_hypotheses=tried,
                   focal_length_contradiction=None)


def _hinted(camera: Camera) -> Camera | None:
    """The camera at its hinted focal length (``focal_length_px`` within ``focal_length_tolerance``, given with
    an unknown focal length: a photograph's EXIF lens, :mod:`app.frames.lens`), or None: no hint, or one whose
    field of view lies outside :data:`FOV_RANGE_DEG`."""
    if camera.focal_length_tolerance is None:
        return None
    fov = fov_for_focal_length(camera.width, camera.focal_length_px)
    if not FOV_RANGE_DEG[0] <= fov <= FOV_RANGE_DEG[1]:
        return None
    return replace(camera.known_at(camera.focal_length_px, camera.focal_length_tolerance), mag_limit=None)


def _stars_fit_beyond(solution: Solution, searched_px: float) -> float | None:
    """The focal length the stars fit outside the search at ``searched_px`` (within :data:`FOUND_TOLERANCE`),
    or None: the triangles' refit on every point they caught (``focal_length_contradiction``), else the optics
    fitted with a candidate that was credible before its fit (the engine fits no other), the most stars first.
    """
    if solution.focal_length_contradiction is not None:
        return solution.focal_length_contradiction.focal_length_px
    fitted = [c for c in solution.candidates if c.camera_fit is not None and c.camera is not None
              and abs(c.camera.focal_length_px / searched_px - 1.0) > FOUND_TOLERANCE]
    return max(fitted, key=lambda c: c.n_matched).camera.focal_length_px if fitted else None


def _fovs(camera: Camera, band: Band) -> str:
    """The band's fields of view across ``camera``'s width, ``"13.9-20.4"`` (degrees)."""
    return f"{fov_for_focal_length(camera.width, band.high_px):.1f}-{fov_for_focal_length(camera.width, band.low_px):.1f}"


def _better(a: Solution, b: Solution) -> bool:
    """Whether ``a`` is a better answer than ``b``: a lower status rank, then a smaller best false-match
    probability."""
    rank = {IDENTIFIED: 0, AMBIGUOUS: 1, NO_MATCH: 2}
    pa = a.candidates[0].false_match_probability if a.candidates else 1.0
    pb = b.candidates[0].false_match_probability if b.candidates else 1.0
    return (rank.get(a.status, 3), pa) < (rank.get(b.status, 3), pb)
