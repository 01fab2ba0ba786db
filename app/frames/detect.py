"""Detecting and centroiding stars in a frame with ``sep`` (Source Extractor as a library).

Why sep: measured against photutils on rendered frames with known truth
(``python -m app bench --suite frames``, docs/frames.md): the same
completeness and centroid accuracy at a fraction of the time per megapixel.

Steps, per frame:

1. known hot pixels (the camera's map, :mod:`app.frames.hotpixels`) are
   replaced by the median of their neighbours;
2. the sky (:func:`_sky`), on a mesh of ``background_box_px`` boxes (median-filtered
   3 x 3, interpolated bilinearly): its level is the median of the image seen through
   the detection filter (sep's 3 x 3 [1 2 1] x [1 2 1] / 16), its noise that image's
   upper half-width, 84th percentile minus median, once bands and glows are set aside.
   The threshold is thus set on the spread of the very image it is compared with,
   whatever the noise is like: real 8-bit frames have their black level clipped at 0
   (55-97 % of their pixels are 0) and noise correlated between neighbours
   (demosaicing, compression), where sep's own clipped RMS came out 4-8 times too
   small, the threshold fell to about 1 sigma and a frame gave tens of thousands of
   blobs (6-40 s for 1.45 Mpx);
3. ``sep.extract`` finds connected pixels ``threshold_sigma`` times that noise above the
   level in the filtered image (deblending); the ``max_candidates`` brightest are kept,
   which bounds every later step whatever the frame holds;
   a frame whose stars are all trailed alike (:func:`_smear`: a fixed tripod under the turning sky,
   a spacecraft turning during the exposure) is extracted again without deblending, which cuts a
   trail's noisy ridge into pieces, and its stars' own a / b raises the elongation limit (step 6);
   its stars are not split again nor looked for on trails (step 5), and its PSF (step 4) is theirs;
4. the frame's point-spread function (:func:`_measure_psf`) from its bright, unsaturated,
   isolated blobs: their median *effective area*, isophotal flux over the peak's height
   above the isophote (2 pi sigma^2 for a Gaussian at any brightness, the top's area for
   a defocused disc), and median elongation.  Every limit below that names the PSF falls
   back to the options' fixed limits on a frame with too few stars to measure it;
5. blobs the filter merged are split again from an unfiltered look at 10 sigma (sharp
   PSFs only, :func:`_split_blends`); stars a trail ran over are looked for again once
   the trail is modelled and subtracted (:func:`_stars_on_trails`); pieces of one star
   (a defocused ring, a noisy top cut apart) are made one again (:func:`_merge_fragments`);
6. every blob is classified: ``hot_pixel`` (one sharp pixel: its four neighbours stay
   below ``max(2.5 sigma, 15 %)`` of its peak, which no PSF of sigma >= 0.6 px does; or two:
   the second brightest neighbour below 15 %),
   ``elongated`` (a / b above ``max_elongation`` and twice the PSF's: trails of
   satellites, aircraft, meteors), ``extended`` (an effective area more than 3 times the
   PSF's, more pixels than a star of its peak covers (:func:`_star_area_limit`, at least
   ``max_area_px``), or lying on something extended,
   :func:`_on_structure`: the Moon, a comet's head and tail, clouds, glare, lit trees,
   bloomed city lights, a glowing corner; or a ring uneven beyond the noise: the edge where a
   bright sky meets a dark treeline or roof), ``border`` (cut by the frame's edge with its
   peak within the PSF's radius of it, or cut and not point-like: vignetting and read-out
   artefacts hug the border, and a cut star's centroid is pulled inwards anyway),
   ``saturated`` (its peak at the saturation level), ``edge`` (cut by the frame's border);
   hot pixels, elongated, extended and border blobs are not stars; saturated round blobs
   are bright stars and stay, flagged (their flat top makes the effective area
   meaningless, so only their pixel count, the elongation and the ring judge them);
7. positions: windowed centroids (``sep.winpos``, SExtractor's XWIN/YWIN, a Gaussian
   window of the PSF's sigma), which at SNR 50 land within a few hundredths of a pixel;
   brightness = flux in a circular aperture of 3 window sigmas, background subtracted
   (:func:`_refine`); a star-like blob whose aperture holds no light above the sky's level is
   ``no_flux`` and no star: the sky between a treeline's branches and the noise along a dark edge
   stand above the level the mesh puts there, but their apertures take in the dark beside them (on
   the wide bench, 58 % of the reported blobs that were no star, and none of the stars but on a frame
   whose PSF was measured on junk; a star in a deep trough of the Milky Way's clouds can be one).

Pixel convention: sep puts (0, 0) at the centre of the first pixel of the
array, the array's row 0 is the sensor's top row (:mod:`app.frames.images`),
so sep's (x, y) are this project's (x, y) unchanged (tests/test_frames_detect.py
checks a single bright pixel at (x, y) comes back at (x, y)).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

#: sep's default 3 x 3 detection filter [[1,2,1],[2,4,2],[1,2,1]] / 16 scales white noise by sqrt(36)/16.
FILTER_NOISE_GAIN = 6.0 / 16.0
#: Threshold (sigma, unfiltered) at which merged close pairs are looked for again.
SPLIT_SIGMA = 10.0
#: Values more than this many core sigmas above a box's median are no noise (:func:`_sky`).
CLIP_SIGMA = 6.0
#: Merged blobs are not split again when the PSF's sigma is at least this (px; see :func:`_split_blends`).
SPLIT_MAX_PSF_SIGMA = 2.0
#: Noise maps whose largest and smallest values differ by less than this are taken as even.
UNIFORM_NOISE_RATIO = 1.3
#: A sharp blob is a hot-pixel candidate for the camera's map when its peak is this many sigma high.
CANDIDATE_SIGMA = 10.0
#: Flags that make a blob "not a star".
REJECTING_FLAGS = ("hot_pixel", "elongated", "extended", "border", "row", "no_flux")
#: Every flag a detection may carry.
FLAGS = ("hot_pixel", "elongated", "extended", "border", "row", "no_flux", "saturated", "edge")
#: sep's internal buffer of object pixels: its default, enough for star fields; sep allocates it on
#: every call (3 million cost ~150 ms), so a larger one is used only when a frame overflows it.
SEP_PIXSTACK = 300_000
SEP_PIXSTACK_LARGE = 4_000_000
#: The PSF is measured on blobs whose peak is at least this many sigma high (their effective area is
#: then known to a few per cent) ...
PSF_PEAK_SIGMA = 15.0
#: ... or this many, when fewer than :data:`PSF_MIN_STARS` reach that: the noise then moves a star's effective
#: area by about 30 %, well within the factor :data:`EXTENDED_AREA_RATIO` the PSF is used with.
PSF_FALLBACK_SIGMA = 6.0
#: ... from at least this many of them (fewer: the fixed limits of the options alone) ...
PSF_MIN_STARS = 3
#: ... and at most this many, the brightest.
PSF_MAX_STARS = 50
#: ... whose effective areas agree within this factor (the smallest and largest, a tenth of them set aside at
#: each end): a frame's stars share one PSF; the candidates of the real frames agree within 4.
PSF_AGREEMENT = 10.0
#: A blob is extended when its effective area exceeds the PSF's this many times (a Gaussian 1.7 times
#: wider; noise moves a 15-sigma star's area by ~10 %, a 5-sigma one's by ~40 %).
EXTENDED_AREA_RATIO = 3.0
#: How many pixels a star's image covers above sep's threshold t, in units of the PSF's effective area:
#: for a Moffat profile of index beta, (beta - 1) ((P / t)^(1 / beta) - 1) at peak P (Moffat 1969; the
#: wings of real optics are broader than a Gaussian's, whose ln(P / t) is less).  beta = 2.5 is the broad
#: end of what seeing and lenses give (2.5-4.8), so the count is the most a star of that peak can cover.
MOFFAT_BETA = 2.5
#: ... at most twice that for a star of known peak (the profile's shape, a neighbour's wing) ...
STAR_AREA_MARGIN = 2.0
#: ... and for a saturated one, whose true peak is unknown, that of a peak this many times the threshold
#: (far beyond a 16-bit sensor's full scale over its noise): 40 effective areas (the real frames'
#: saturated stars reach 32).  ``max_area_px`` stays a floor: on a sharp frame a saturated star's
#: bloom and halo cover more than the profile says.
SATURATED_PEAK_RATIO = 4000.0
#: A blob near another is a piece of the same star when its effective area is below this part of the PSF's.
PIECE_AREA_RATIO = 0.5
#: A blob is elongated when its a / b exceeds the PSF's this many times (and ``max_elongation``): the
#: median hides a field's coma and astigmatism (a frame whose median star has a / b = 1.6 has 3 at its edge).
PSF_ELONGATION_FACTOR = 2.0
#: The ring around a blob that tells whether it lies on an extended structure (:func:`_on_structure`):
#: how many pixels, and how bright its median may be, in sigma of the noise and as a part of the peak;
#: then how uneven it may be (its interquartile range), alike.
RING_POINTS = 32
RING_SIGMA = 1.0
RING_FRACTION = 0.1
RING_SPREAD_SIGMA = 2.0
RING_SPREAD_FRACTION = 0.1
RING_SPREAD_QUANTA = 2.0
#: A frame's stars are trailed when the median a / b of its brightest compact blobs (at most the first
#: many, at least the second, peaks of the next sigma, none thinner than the next px) exceeds
#: ``max_elongation``, the elongated ones spread over the next part of the frame's height (:func:`_smear`).
SMEAR_BLOBS = 30
SMEAR_MIN_BLOBS = 6
SMEAR_PEAK_SIGMA = 6.0
SMEAR_MIN_MINOR_PX = 0.7
SMEAR_MIN_SPREAD = 0.1
#: A row (:func:`_in_rows`: text, a treeline's gaps): at least this many blobs side by side, gaps of at most
#: the next times the lower one's height, heights within the next factor, the whole at least the last
#: times longer than high.
ROW_MIN_BLOBS = 4
ROW_GAP = 1.0
ROW_HEIGHT_RATIO = 3.0
ROW_MIN_ASPECT = 3.0
#: Windowed centroids for blobs whose peak is at least this many sigma high (see :func:`_refine`).
WINDOW_PEAK_SIGMA = 5.0
#: A trail is modelled as a satellite's (:func:`_stars_on_trails`) only when at least this many times longer than
#: wide: a knot of a treeline's edge is elongated, but its light is no line of even brightness.
TRAIL_MIN_ASPECT = 3.0


class DetectionError(ValueError):
    """A frame where detection cannot work (e.g. nothing but noise features: sep's buffers overflow)."""


@dataclass(frozen=True)
class DetectionOptions:
    """How sources are found and which are kept (defaults suit star cameras of 0.5-16 Mpx)."""

    threshold_sigma: float = 5.0
    min_area_px: int = 3
    background_box_px: int = 64
    #: Sources reported per frame, brightest first: enough for the faint stars of a narrow field (a
    #: TUBSAT sensor reports ~10, others 16; identification picks what it uses).
    max_sources: int = 32
    #: Fewest a / b that is "elongated" (the PSF's own elongation raises it, see the module).
    max_elongation: float = 2.0
    #: Elongation is judged only on blobs with at least this many pixels (shape noise of tiny blobs).
    min_area_for_shape_px: int = 10
    #: Most pixels a star's blob covers, or what a star of its peak covers at the frame's PSF where that is
    #: more (:func:`_star_area_limit`): larger blobs are extended (the Moon, clouds, glare).
    max_area_px: int = 2000
    #: A blob is one hot pixel when its four neighbours stay below this fraction of its peak
    #: (and below 2.5 sigma of the noise when that is higher).
    hot_neighbour_fraction: float = 0.15
    #: Most blobs measured in detail per frame (the brightest by isophotal flux).
    max_candidates: int = 500
    #: Most merged blobs split again per frame (:func:`_split_blends`; 0: never split).
    max_split_per_frame: int = 50

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class PointSpread:
    """The frame's point-spread function as measured on its stars (see :func:`_measure_psf`)."""

    #: Median effective area (px^2): isophotal flux over the peak's height above the isophote.
    area_px: float
    #: Median a / b of the same stars.
    elongation: float
    #: How many stars it was measured on.
    stars: int

    @property
    def radius_px(self) -> float:
        """Radius of the disc of the effective area (sigma * sqrt(2) for a Gaussian)."""
        return float(np.sqrt(self.area_px / np.pi))

    @property
    def sigma_px(self) -> float:
        """The sigma of the Gaussian of the same effective area."""
        return float(np.sqrt(self.area_px / (2.0 * np.pi)))


@dataclass(frozen=True, eq=False)
class Detections:
    """Every blob of one frame, brightest first, with its flags (empty tuple: a star)."""

    xy: np.ndarray          # (n, 2) project pixel convention
    flux: np.ndarray        # (n,) aperture flux, background subtracted (>= 0)
    snr: np.ndarray         # (n,) flux / its noise
    peak: np.ndarray        # (n,) background-subtracted peak pixel value
    peak_pixel: np.ndarray  # (n, 2) integer (x, y) of the peak pixel
    npix: np.ndarray        # (n,) pixels above the threshold
    elongation: np.ndarray  # (n,) a / b
    flags: tuple[tuple[str, ...], ...]
    background: float       # median background level
    noise: float            # median noise (RMS) per pixel
    #: Known hot pixels (replaced before detection) still standing out of their neighbours' median.
    still_hot: tuple[tuple[int, int], ...] = ()
    #: (n,) peak over the local noise.
    peak_sigma: np.ndarray | None = None
    #: The frame's PSF, None when too few stars were bright enough to measure it.
    psf: PointSpread | None = None
    #: The median a / b of the frame's stars when they are trailed (:func:`_smear`), else None.
    smear: float | None = None

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    @property
    def is_star(self) -> np.ndarray:
        return np.array([not any(f in REJECTING_FLAGS for f in flags) for flags in self.flags], dtype=bool)

    def kept(self, max_sources: int) -> np.ndarray:
        """Indices of the ``max_sources`` brightest star-like detections (already brightest first)."""
        return np.flatnonzero(self.is_star)[:max_sources]

    def hot_pixel_candidates(self) -> list[tuple[int, int]]:
        """Peak pixels of the blobs flagged ``hot_pixel``: what :mod:`app.frames.hotpixels` counts."""
        # Only strong ones: a faint star's wings may drown in the noise, but not at 10 sigma.
        strong = self.peak_sigma if self.peak_sigma is not None else np.full(len(self), np.inf)
        found = [(int(x), int(y)) for (x, y), flags, s in zip(self.peak_pixel, self.flags, strong)
                 if "hot_pixel" in flags and s >= CANDIDATE_SIGMA]
        return found + [p for p in self.still_hot if p not in found]


def replace_pixels(pixels: np.ndarray, bad: list[tuple[int, int]]) -> np.ndarray:
    """A copy of ``pixels`` with each (x, y) in ``bad`` replaced by the median of its good neighbours."""
    if not bad:
        return pixels
    out = pixels.copy()
    height, width = pixels.shape
    bad_set = {(int(x), int(y)) for x, y in bad}
    for x, y in bad_set:
        if not (0 <= x < width and 0 <= y < height):
            continue
        values = [pixels[j, i] for j in range(max(0, y - 1), min(height, y + 2))
                  for i in range(max(0, x - 1), min(width, x + 2)) if (i, j) not in bad_set]
        if values:
            out[y, x] = float(np.median(values))
    return out


def detect(pixels: np.ndarray, options: DetectionOptions = DetectionOptions(), *,
           saturation: float | None = None, hot_pixels: list[tuple[int, int]] | None = None) -> Detections:
    """Find, classify and centroid the blobs of one frame (see the module's steps)."""
    import sep

    # Writable: sep takes the frame as a writable buffer, and a caller's read-only array (a view of a
    # decoded image's buffer) is copied rather than refused with sep's "buffer source array is read-only".
    raw = np.require(pixels, dtype=np.float32, requirements=["C_CONTIGUOUS", "WRITEABLE"])
    data = replace_pixels(raw, hot_pixels or [])
    height, width = data.shape
    box = int(max(8, min(options.background_box_px, min(data.shape) // 2)))
    sky = _sky(data, box)
    sub = np.ascontiguousarray(data - sky.level, dtype=np.float32)
    still_hot = tuple((int(x), int(y)) for x, y in sorted(set(map(tuple, hot_pixels or [])))
                      if 0 <= x < width and 0 <= y < height
                      and raw[y, x] - data[y, x] > 5.0 * float(sky.pixel_noise_at(np.array([y]), np.array([x]))[0]))
    objects = _brightest(_extract(sep, sub, sky.noise, options), options.max_candidates)
    smear = _smear(objects, sub, sky, options)
    if smear is not None:
        # Every star is a short trail: whole trails, not the pieces deblending cuts a trail's noisy ridge
        # into, elongated only beyond the stars' own a / b, and never cut again (below).
        options = replace(options, max_elongation=max(options.max_elongation, PSF_ELONGATION_FACTOR * smear))
        objects = _brightest(_extract(sep, sub, sky.noise, options, deblend=False), options.max_candidates)
    psf = _measure_psf(objects, sub, sky, saturation, raw, options, fallback=smear is None)
    measured = sub
    if smear is None:  # a trailed frame's PSF is no model of a satellite's trail, nor a sharp star's
        objects = _split_blends(sep, sub, sky.median_pixel_noise, objects, options, psf)
        objects, measured = _stars_on_trails(sep, sub, sky.median_pixel_noise, objects, options, psf)
    objects = _brightest(objects, options.max_candidates)
    objects = _merge_fragments(objects, sub, sky, options, psf)
    n = len(objects)
    xpeak, ypeak, peak, local_noise = _peaks(objects, sub, sky)
    a, b = objects["a"].astype(float), objects["b"].astype(float)
    elongation = np.where(b > 0, a / np.maximum(b, 1e-9), np.inf)
    flags = _classify(sep, objects, sub, raw, sky, psf, saturation, options, measured)
    xy = np.column_stack([objects["x"], objects["y"]]).astype(float) if n else np.zeros((0, 2))
    flux = objects["flux"].astype(float).copy()
    snr = np.zeros(n)
    measure = np.array([not any(x in REJECTING_FLAGS for x in f) for f in flags], dtype=bool)
    if measure.any():
        xy[measure], flux[measure], snr[measure] = _refine(
            sep, measured, sky.pixel_noise, xy[measure], a[measure], flux[measure], psf,
            peak[measure] >= WINDOW_PEAK_SIGMA * local_noise[measure])
    # A star adds light: a blob whose aperture holds none above the sky is a spike of sky between dark
    # branches, a ridge of noise at a dark edge (step 7).
    empty = measure & (flux <= 0.0)
    flags = [f + ("no_flux",) if empty[k] else f for k, f in enumerate(flags)]
    xy[:, 0] = np.clip(xy[:, 0], -0.5, width - 0.5)
    xy[:, 1] = np.clip(xy[:, 1], -0.5, height - 0.5)
    flux = np.maximum(flux, 0.0)
    order = np.argsort(-flux, kind="stable")
    return Detections(xy=xy[order], flux=flux[order], snr=snr[order], peak=peak[order],
                      peak_pixel=np.column_stack([xpeak, ypeak])[order] if n else np.zeros((0, 2), int),
                      npix=objects["npix"][order].astype(int), elongation=elongation[order],
                      flags=tuple(flags[k] for k in order), background=sky.median_level,
                      noise=sky.median_pixel_noise, still_hot=still_hot,
                      peak_sigma=(peak / np.maximum(local_noise, 1e-12))[order], psf=psf, smear=smear)


def _classify(sep, objects, sub: np.ndarray, raw: np.ndarray, sky: _Sky, psf: PointSpread | None,
              saturation: float | None, options: DetectionOptions,
              measured: np.ndarray | None = None) -> list[tuple[str, ...]]:
    """Each blob's flags (:data:`FLAGS`; see the module's step 6).  ``measured``: ``sub`` with the satellites'
    trails taken out (:func:`_stars_on_trails`), where the ring around a star beside one is judged."""
    shape = sub.shape
    xpeak, ypeak, peak, noise = _peaks(objects, sub, sky)
    hot = _is_hot(objects, sub, sky, options)
    saturated = (_max_around(raw, xpeak, ypeak) >= 0.995 * saturation) if saturation is not None \
        else np.zeros(len(objects), dtype=bool)
    elongated = _is_elongated(objects, options, psf)
    not_point = _too_large(objects, peak, noise, psf) | _on_structure(
        objects, sub if measured is None else measured, peak, noise, psf, quantum=sky.quantum)
    too_many = objects["npix"] > _star_area_limit(options, psf and psf.area_px,
                                                  peak / np.maximum(objects["thresh"], 1e-12), saturated)
    extended = too_many | (~saturated & ~hot & not_point)
    cut = _touches_border(objects, shape)
    border = cut & (_peak_near_border(xpeak, ypeak, shape, psf) | elongated | extended)
    trunc = (objects["flag"] & sep.OBJ_TRUNC) != 0
    columns = (("hot_pixel", hot), ("elongated", elongated), ("extended", extended), ("border", border),
               ("row", _in_rows(objects)),
               ("saturated", saturated), ("edge", trunc | cut))
    return [tuple(name for name, column in columns if column[k]) for k in range(len(objects))]


def _peak_pixels(objects, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Integer (x, y) of each blob's brightest pixel, inside the frame."""
    height, width = shape
    return np.clip(objects["xpeak"].astype(int), 0, width - 1), np.clip(objects["ypeak"].astype(int), 0, height - 1)


def _peaks(objects, sub: np.ndarray, sky: _Sky) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each blob's peak pixel (x, y), its height above the sky, and the sky's noise per pixel there."""
    xpeak, ypeak = _peak_pixels(objects, sub.shape)
    return xpeak, ypeak, sub[ypeak, xpeak].astype(float), sky.pixel_noise_at(ypeak, xpeak)


def _sample(data: np.ndarray) -> np.ndarray:
    """About 64 x 64 of the frame's pixels, evenly spaced."""
    return data[:: max(1, data.shape[0] // 64), :: max(1, data.shape[1] // 64)]


def _quantum(data: np.ndarray) -> float:
    """The values' quantisation step: 1 for integer data (judged on a sample), 0 else."""
    sample = _sample(data)
    return 1.0 if np.all(sample == np.round(sample)) else 0.0


def _noise_floor(data: np.ndarray, quantum: float) -> float:
    """Smallest noise assumed: the quantisation of integer data (0.3 of a step, about 1 / sqrt 12), a tiny
    fraction of the range else."""
    if quantum:
        return 0.3 * quantum
    sample = _sample(data)
    return max(1e-6, 1e-4 * (float(np.ptp(sample)) if sample.size else 0.0))


# --- the sky -----------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class _Sky:
    """The sky of one frame (:func:`_sky`): background level and noise, as maps or, when even, numbers.

    ``noise`` is the filtered image's; ``pixel_noise`` the noise per pixel of the white noise the
    filter would bring to it (``noise / FILTER_NOISE_GAIN``): the pixels' RMS for white noise,
    larger for correlated noise, as is the noise of any sum over neighbouring pixels (apertures,
    peaks of blobs).
    """

    level: np.ndarray
    noise: float | np.ndarray
    pixel_noise: float | np.ndarray
    #: Medians over the frame's boxes.
    median_level: float
    median_pixel_noise: float
    #: The values' quantisation step (:func:`_quantum`).
    quantum: float = 0.0

    def pixel_noise_at(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        noise = self.pixel_noise
        return noise[y, x].astype(float) if isinstance(noise, np.ndarray) else np.full(len(x), float(noise))


def _smooth(data: np.ndarray, step: int = 1) -> np.ndarray:
    """The detection filter [1 2 1] x [1 2 1] / 16 (sep's default), separably, edges repeated, at
    every ``step``-th pixel of every ``step``-th row (from the first)."""
    height, width = data.shape
    padded = np.pad(data, 1, mode="edge")
    rows = padded[0:height:step] + 2.0 * padded[1:height + 1:step] + padded[2:height + 2:step]
    return (rows[:, 0:width:step] + 2.0 * rows[:, 1:width + 1:step] + rows[:, 2:width + 2:step]) \
        * np.float32(1.0 / 16.0)


def _sky(data: np.ndarray, box: int) -> _Sky:
    """Level and noise of the sky, from the filtered image in boxes of about ``box`` px.

    Per box, on the filtered image at every second pixel of every second row:

    * the level is the median;
    * the noise is the 84th percentile minus the median (one sigma for Gaussian noise) of the
      values at most :data:`CLIP_SIGMA` core sigmas above the median.  The upper half only: a
      black level clipped at 0 does not count.  The 84th percentile, not the core sigma, because
      real noise has a heavier upper tail than its core (2-3 times on clipped 8-bit frames) and
      the tail is what makes false stars;
    * the core sigma (:func:`_core_sigma`) comes from differences of values 4 px apart, which a
      flat structure leaves alone: clipping there sets aside a band of light, a glow, or stars
      covering up to half a box (a band along the border made the noise 80 times the sky's, and
      the stars beside it vanished).  Where the core sigma is the larger (a steep gradient), it is
      the noise.

    The meshes are median-filtered 3 x 3 (a box on a bright object takes its neighbours' level
    and noise).  The smallest noise per pixel believed is :func:`_noise_floor` (the quantisation of
    integer data, :func:`_quantum`).
    """
    from scipy.ndimage import median_filter

    quantum = _quantum(data)
    floor = _noise_floor(data, quantum)
    height, width = data.shape
    ny, nx = max(1, round(height / box)), max(1, round(width / box))
    step = 2 if min(height // ny, width // nx) >= 16 else 1
    filtered = _smooth(data, step)
    by, bx = filtered.shape[0] // ny, filtered.shape[1] // nx

    def boxes(image: np.ndarray) -> np.ndarray:
        return image[:ny * by, :nx * bx].reshape(ny, by, nx, bx).transpose(0, 2, 1, 3).reshape(ny, nx, -1)

    values = np.sort(boxes(filtered), axis=-1)
    n = values.shape[-1]
    median = values[..., n // 2]
    core = _core_sigma(filtered, boxes)
    ceiling = median + CLIP_SIGMA * np.maximum(core, floor * FILTER_NOISE_GAIN)
    kept = np.maximum(1, (values <= ceiling[..., None]).sum(axis=-1))
    upper = np.take_along_axis(values, np.rint(0.8413 * (kept - 1)).astype(int)[..., None], axis=-1)[..., 0]
    level_mesh = median_filter(median.astype(float), size=3, mode="nearest")
    noise_mesh = median_filter(np.maximum(upper - median, core).astype(float), size=3, mode="nearest")
    noise_mesh = np.maximum(noise_mesh, floor * FILTER_NOISE_GAIN)
    level = _interpolate_mesh(level_mesh, (step * by, step * bx), (height, width))
    typical = float(np.median(noise_mesh))
    noise = typical if noise_mesh.max() <= UNIFORM_NOISE_RATIO * noise_mesh.min() \
        else _interpolate_mesh(noise_mesh, (step * by, step * bx), (height, width))
    return _Sky(level=level, noise=noise, pixel_noise=noise / np.float32(FILTER_NOISE_GAIN),
                median_level=float(np.median(level_mesh)), median_pixel_noise=typical / FILTER_NOISE_GAIN,
                quantum=quantum)


def _core_sigma(filtered: np.ndarray, boxes) -> np.ndarray:
    """Per box, the sigma of the filtered image's noise from differences of values 2 apart across and
    down (4 px apart on the half-resolution grid, beyond the filter's reach, so independent): the
    median absolute difference / 0.6745 / sqrt 2, the larger of the two.  A gradient raises it."""
    lag = 2
    if min(filtered.shape) <= lag:
        return np.zeros(boxes(filtered).shape[:-1])
    across = np.pad(np.abs(filtered[:, lag:] - filtered[:, :-lag]), ((0, 0), (0, lag)), mode="edge")
    down = np.pad(np.abs(filtered[lag:] - filtered[:-lag]), ((0, lag), (0, 0)), mode="edge")
    middle = boxes(across).shape[-1] // 2
    medians = [np.partition(boxes(d), middle, axis=-1)[..., middle] for d in (across, down)]
    return np.maximum(*medians) / (0.6745 * np.sqrt(2.0))


def _interpolate_mesh(mesh: np.ndarray, box: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """Bilinear interpolation of a mesh of box values (at the boxes' centres) to every pixel, constant
    beyond the outer centres: along each row of the small mesh first, then between whole rows (which
    numpy copies fast)."""
    def along(values: np.ndarray, size: int, n_pixels: int) -> np.ndarray:
        """``values`` (boxes along axis 0) interpolated to ``n_pixels`` along axis 0."""
        if values.shape[0] == 1:
            return np.repeat(values, n_pixels, axis=0)
        position = np.clip((np.arange(n_pixels) + 0.5) / size - 0.5, 0.0, values.shape[0] - 1.0)
        lower = np.minimum(position.astype(int), values.shape[0] - 2)
        weight = (position - lower).astype(np.float32)[:, None]
        return values[lower] * (1 - weight) + values[lower + 1] * weight

    columns = along(mesh.astype(np.float32).T, box[1], shape[1]).T
    return np.ascontiguousarray(along(np.ascontiguousarray(columns), box[0], shape[0]), dtype=np.float32)


# --- finding blobs -----------------------------------------------------------------------------------

def _extract(sep, sub: np.ndarray, noise: float | np.ndarray, options: DetectionOptions, *, deblend: bool = True):
    """sep.extract; when its buffers overflow, again with a larger buffer, then at twice the threshold.

    ``filter_type="conv"``: the filtered image is compared with ``threshold_sigma`` times ``noise``,
    the filtered image's own noise (:func:`_sky`), one number or a map.  ``deblend`` False: a blob's
    local maxima stay one object.
    """
    attempts = ((SEP_PIXSTACK, 1.0), (SEP_PIXSTACK_LARGE, 1.0), (SEP_PIXSTACK_LARGE, 2.0))
    error = None
    for stack, factor in attempts:
        sep.set_extract_pixstack(stack)
        try:
            # clean=False: SExtractor's cleaning treats everything within a bright trail's huge
            # second moments as its wings and drops whole star fields beside a satellite trail.
            return sep.extract(sub, factor * options.threshold_sigma, err=noise, minarea=options.min_area_px,
                               filter_type="conv", deblend_cont=0.005 if deblend else 1.0, clean=False)
        except Exception as exc:  # noqa: BLE001 - sep raises plain Exceptions ("internal pixel buffer full")
            error = exc
        finally:
            sep.set_extract_pixstack(SEP_PIXSTACK)
    raise DetectionError(f"too many blobs to separate even at {2 * options.threshold_sigma:g} sigma ({error}); "
                         "is this a star field?")


def _smear(objects, sub: np.ndarray, sky: _Sky, options: DetectionOptions) -> float | None:
    """The stars' a / b when the frame's stars are trailed (a fixed tripod under the turning sky, a
    spacecraft turning during the exposure), else None.

    A star trailed by L px is an ellipse of minor axis its PSF's sigma and major axis
    sqrt(sigma^2 + L^2 / 12).  The frame is trailed when the median a / b of its :data:`SMEAR_BLOBS`
    brightest compact blobs exceeds ``max_elongation``.  Compact: a peak of :data:`SMEAR_PEAK_SIGMA`
    sigma or more, ``min_area_for_shape_px`` to ``max_area_px`` pixels, b of :data:`SMEAR_MIN_MINOR_PX`
    or more (no sliver thinner than a PSF), not cut by the border, not a hot pixel, not on something
    extended (:func:`_on_structure`).  A satellite, an aircraft or a meteor is one blob among them and
    moves no median.  The elongated ones must also fill the sky's two dimensions (the smaller axis of
    their spread at least :data:`SMEAR_MIN_SPREAD` of the frame's height): a treeline's gaps or a
    lit horizon's glints, elongated alike, lie along a line.  Fewer than :data:`SMEAR_MIN_BLOBS`: None.
    """
    if len(objects) < SMEAR_MIN_BLOBS:
        return None
    _, _, peak, noise = _peaks(objects, sub, sky)
    a, b = objects["a"].astype(float), objects["b"].astype(float)
    compact = np.flatnonzero(
        (peak >= SMEAR_PEAK_SIGMA * noise) & (objects["npix"] >= options.min_area_for_shape_px)
        & (objects["npix"] <= options.max_area_px) & (b >= SMEAR_MIN_MINOR_PX) & ~_touches_border(objects, sub.shape)
        & ~_is_hot(objects, sub, sky, options)
        & ~_on_structure(objects, sub, peak, noise, None, quantum=sky.quantum))
    if len(compact) < SMEAR_MIN_BLOBS:
        return None
    brightest = compact[np.argsort(-objects["flux"][compact], kind="stable")[:SMEAR_BLOBS]]
    elongation = a[brightest] / b[brightest]
    median = float(np.median(elongation))
    if median <= options.max_elongation:
        return None
    trailed = brightest[elongation > options.max_elongation]
    spread = np.linalg.eigvalsh(np.cov(np.stack([objects["x"][trailed], objects["y"][trailed]]).astype(float)))
    if math.sqrt(max(float(spread[0]), 0.0)) < SMEAR_MIN_SPREAD * sub.shape[0]:
        return None
    return median


def _brightest(objects, limit: int):
    """The ``limit`` blobs of largest isophotal flux, in their original order."""
    if len(objects) <= limit:
        return objects
    order = np.argsort(-objects["flux"], kind="stable")[:limit]
    return objects[np.sort(order)]


def _split_blends(sep, sub: np.ndarray, noise: float, objects, options: DetectionOptions,
                  psf: PointSpread | None):
    """Close pairs the detection filter merged, split again.

    The matched filter that finds faint stars also fills the saddle between two stars a few pixels
    apart, so sep's deblending sees one blob with its centroid between them.  Unfiltered, at
    :data:`SPLIT_SIGMA`, bright stars separate: a filtered blob holding two or more unfiltered
    ones is replaced by them (nothing changes when each holds one); elongated and extended blobs
    (trails, glare) are never split.  Nor is anything when the PSF's sigma is
    :data:`SPLIT_MAX_PSF_SIGMA` or more: the filter (variance 0.5 px^2 per axis) then widens stars
    by 6 % or less and merges no pair the unfiltered image separates, and the unfiltered look only
    cuts the noisy tops of wide (defocused) stars into pieces.  Each unfiltered blob goes to the
    nearest filtered one (a k-d tree: the work grows as n log n, whatever the frame holds).
    """
    if not len(objects) or options.max_split_per_frame <= 0:
        return objects
    if psf is not None and psf.sigma_px >= SPLIT_MAX_PSF_SIGMA:
        return objects
    from scipy.spatial import cKDTree

    sep.set_extract_pixstack(SEP_PIXSTACK)
    try:
        sharp = sep.extract(sub, SPLIT_SIGMA, err=noise, minarea=options.min_area_px,
                            filter_kernel=None, deblend_cont=0.005, clean=False)
    except Exception:  # noqa: BLE001 - a refinement only: keep what the filtered pass found
        return objects
    if len(sharp) < 2:
        return objects
    sharp = _brightest(sharp, 4 * options.max_candidates)
    d, owner = cKDTree(np.column_stack([objects["x"], objects["y"]])).query(
        np.column_stack([sharp["x"], sharp["y"]]))
    near = d <= np.maximum(3.0 * objects["a"][owner], 3.0)
    trail = _is_trail(objects, options, psf)  # a trail's pieces are no stars: it stays one flagged blob
    counts = np.bincount(owner[near], minlength=len(objects))
    split = np.flatnonzero((counts >= 2) & ~trail)[:options.max_split_per_frame]
    if not len(split):
        return objects
    parts = sharp[np.isin(owner, split) & near]
    keep = np.ones(len(objects), dtype=bool)
    keep[split] = False
    return np.concatenate([objects[keep], parts.astype(objects.dtype)])


# --- the point-spread function and what is not a point source ----------------------------------------

def _is_hot(objects, sub: np.ndarray, sky: _Sky, options: DetectionOptions) -> np.ndarray:
    """One or two sharp pixels, the peak at least 4 times the isophote (through the detection filter a lone
    pixel keeps a quarter of its value, and is found only above that; fainter sharp blobs are noise, not
    pixels):

    * one: the peak's four neighbours below ``max(2.5 sigma, hot_neighbour_fraction x peak)``;
    * two: the second brightest of them below ``hot_neighbour_fraction x peak``. A star of sigma 0.6 px
      lights at least two of them to a quarter of its peak wherever it is centred; a hot pixel with one lit
      neighbour (an uncooled sensor's pairs, a JPEG's or a demosaic's spread) does not. No noise floor here:
      a faint sharp star's second neighbour (8 DN of a 28 DN peak on the 6 deg frames) is within 2.5 sigma.
    """
    x, y = _peak_pixels(objects, sub.shape)
    peak = sub[y, x].astype(float)
    around = _neighbours(sub, x, y)
    one = around[:, 0] < np.maximum(2.5 * sky.pixel_noise_at(y, x), options.hot_neighbour_fraction * peak)
    two = around[:, 1] < options.hot_neighbour_fraction * peak
    return (peak >= 4.0 * objects["thresh"]) & (one | two)


def _merge_fragments(objects, sub: np.ndarray, sky: _Sky, options: DetectionOptions, psf: PointSpread | None):
    """Pieces of one star made one again: star-like blobs closer than the PSF's diameter, one of
    them a piece (an effective area under :data:`PIECE_AREA_RATIO` of the PSF's).

    Deblending and the unfiltered second look (:func:`_split_blends`) cut a defocused star's
    ring or a faint star's noisy top into several blobs, each then "a star" a few pixels from
    the others, each holding a part of the star's light under its full peak.  Two stars that
    close (1.2 FWHM for a Gaussian) each with a whole PSF's light are a resolved pair, and stay
    two.  A group keeps its brightest blob's record, with the group's flux, pixels,
    flux-weighted centre (the windowed centroid then starts from there) and second moments (each
    piece's plus its offset's, the parallel-axis theorem), whence its a, b and theta.
    """
    if psf is None or len(objects) < 2:
        return objects
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    # An arc of a ring is elongated, and no trail while shorter than the PSF is wide.
    trails = _is_trail(objects, options, psf) & (objects["a"] > psf.radius_px)
    eligible = np.flatnonzero(~_is_hot(objects, sub, sky, options) & ~trails)
    if len(eligible) < 2:
        return objects
    xy = np.column_stack([objects["x"][eligible], objects["y"][eligible]])
    pairs = cKDTree(xy).query_pairs(2.0 * psf.radius_px, output_type="ndarray")
    if not len(pairs):
        return objects
    x, y = _peak_pixels(objects[eligible], sub.shape)
    piece = _effective_area(objects[eligible], sub[y, x].astype(float), sky.pixel_noise_at(y, x)) \
        < PIECE_AREA_RATIO * psf.area_px
    pairs = pairs[piece[pairs[:, 0]] | piece[pairs[:, 1]]]
    if not len(pairs):
        return objects
    links = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(eligible),) * 2)
    _, group = connected_components(links, directed=False)
    merged = objects.copy()
    drop = np.zeros(len(objects), dtype=bool)
    for g in np.flatnonzero(np.bincount(group) > 1):
        members = eligible[group == g]
        first = members[np.argmax(objects["flux"][members])]
        weight = np.maximum(objects["flux"][members], 0.0) + 1e-12
        cx, cy = np.average(objects["x"][members], weights=weight), np.average(objects["y"][members], weights=weight)
        dx, dy = objects["x"][members] - cx, objects["y"][members] - cy
        x2 = np.average(objects["x2"][members] + dx * dx, weights=weight)
        y2 = np.average(objects["y2"][members] + dy * dy, weights=weight)
        xy2 = np.average(objects["xy"][members] + dx * dy, weights=weight)
        spread = np.hypot((x2 - y2) / 2.0, xy2)
        merged["x"][first], merged["y"][first] = cx, cy
        merged["x2"][first], merged["y2"][first], merged["xy"][first] = x2, y2, xy2
        merged["a"][first] = np.sqrt((x2 + y2) / 2.0 + spread)
        merged["b"][first] = np.sqrt(max((x2 + y2) / 2.0 - spread, 0.0))
        merged["theta"][first] = 0.5 * np.arctan2(2.0 * xy2, x2 - y2)
        for name in ("flux", "npix"):
            merged[name][first] = objects[name][members].sum()
        for name, pick in (("xmin", np.min), ("ymin", np.min), ("xmax", np.max), ("ymax", np.max)):
            merged[name][first] = pick(objects[name][members])
        drop[members[members != first]] = True
    return merged[~drop]


def _effective_area(objects, peak: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Isophotal flux over the peak's height above the isophote (px^2), for each blob.

    For a Gaussian of width sigma, the light above the isophote t of a star of peak P is
    2 pi sigma^2 (P - t): the ratio is 2 pi sigma^2 at any brightness; for a flat-topped
    (defocused) star it is the top's area.  An extended object's light is spread over far more
    pixels than its peak accounts for.  The height is kept to at least one sigma of the noise.
    """
    height = np.maximum(peak - objects["thresh"], noise)
    return objects["flux"] / np.maximum(height, 1e-12)


def _measure_psf(objects, sub: np.ndarray, sky: _Sky, saturation: float | None, raw: np.ndarray,
                 options: DetectionOptions, *, fallback: bool = True) -> PointSpread | None:
    """The frame's PSF from its best star-like blobs, None when fewer than :data:`PSF_MIN_STARS`.

    Candidates: peak at least :data:`PSF_PEAK_SIGMA` sigma (:data:`PSF_FALLBACK_SIGMA` when that leaves no
    PSF: a bright sky, the Milky Way's clouds inflating the noise, an 8-bit frame whose stars saturate
    early; 6 of 7 Milky Way photographs of the wide bench looked at had none; not on a trailed frame, whose
    fainter trails are shorter, and made the longer ones extended), at least ``min_area_for_shape_px``
    pixels and no more than a star's image covers at their own median effective area, unsaturated, not
    cut by the border, no other blob within four times its size, a / b
    below twice ``max_elongation`` (not a trail), and not one or two hot pixels: the second
    brightest of the peak's four neighbours above the hot-pixel limit (a star of sigma 0.5 px or
    more lights both neighbours on at least one axis; a pair of hot pixels, as bright as stars in
    uncooled sensors and as many, made a PSF of 2 px^2 that called every star extended).  Of the
    :data:`PSF_MAX_STARS` brightest, the median effective area and elongation.  Medians: a few
    galaxies, knots of a comet or double stars among them do not move it; but where the candidates
    do not agree within :data:`PSF_AGREEMENT` they are not one PSF's stars, and there is none.
    """
    if len(objects) < PSF_MIN_STARS:
        return None
    xpeak, ypeak, peak, noise = _peaks(objects, sub, sky)
    elongation = objects["a"].astype(float) / np.maximum(objects["b"].astype(float), 1e-9)
    shaped = ((objects["npix"] >= options.min_area_for_shape_px)
              & (elongation < 2.0 * options.max_elongation) & ~_touches_border(objects, sub.shape)
              & (_neighbours(sub, xpeak, ypeak)[:, 1] >= np.maximum(2.5 * noise, options.hot_neighbour_fraction * peak)))
    if saturation is not None:
        shaped &= _max_around(raw, xpeak, ypeak) < 0.995 * saturation
    for sigma in (PSF_PEAK_SIGMA, PSF_FALLBACK_SIGMA) if fallback else (PSF_PEAK_SIGMA,):
        psf = _psf_of(objects, shaped & (peak >= sigma * noise), peak, noise, elongation, options)
        if psf is not None:
            return psf
    return None


def _psf_of(objects, ok: np.ndarray, peak: np.ndarray, noise: np.ndarray, elongation: np.ndarray,
            options: DetectionOptions) -> PointSpread | None:
    """The PSF of the candidates ``ok`` (:func:`_measure_psf`): the isolated ones, no larger than a star's image
    can be, agreeing; None when fewer than :data:`PSF_MIN_STARS` are left or they disagree."""
    from scipy.spatial import cKDTree

    a = objects["a"].astype(float)
    if np.count_nonzero(ok) < PSF_MIN_STARS:
        return None
    xy = np.column_stack([objects["x"], objects["y"]])
    gap, _ = cKDTree(xy).query(xy[ok], k=2)
    candidates = np.flatnonzero(ok)[gap[:, 1] > 4.0 * np.maximum(a[ok], 1.0)]
    if len(candidates) < PSF_MIN_STARS:
        return None
    # No larger than a star's image can be (:func:`_star_area_limit`), judged by the candidates' own PSF:
    # a fixed count of pixels would leave a blurred frame's bright stars out, and the frame without a PSF.
    first_look_px = float(np.median(_effective_area(objects[candidates], peak[candidates], noise[candidates])))
    limit = _star_area_limit(options, first_look_px, peak[candidates] / np.maximum(objects["thresh"][candidates], 1e-12),
                             np.zeros(len(candidates), dtype=bool))
    candidates = candidates[objects["npix"][candidates] <= limit]
    if len(candidates) < PSF_MIN_STARS:
        return None
    best = candidates[np.argsort(-objects["flux"][candidates], kind="stable")[:PSF_MAX_STARS]]
    area = _effective_area(objects[best], peak[best], noise[best])
    ordered, spared = np.sort(area), len(area) // 10
    if ordered[-1 - spared] > PSF_AGREEMENT * max(ordered[spared], 1e-12):
        return None  # unlike blobs (a star and two knots of a horizon's glow made a PSF of 1,900 px^2)
    return PointSpread(area_px=float(np.median(area)), elongation=float(np.median(elongation[best])),
                       stars=len(best))


def _elongation_limit(options: DetectionOptions, psf: PointSpread | None) -> float:
    return options.max_elongation if psf is None else max(options.max_elongation,
                                                          PSF_ELONGATION_FACTOR * psf.elongation)


def _is_elongated(objects, options: DetectionOptions, psf: PointSpread | None) -> np.ndarray:
    """a / b beyond :func:`_elongation_limit`, judged on blobs of ``min_area_for_shape_px`` or more."""
    a, b = objects["a"], objects["b"]
    return (objects["npix"] >= options.min_area_for_shape_px) & (
        a > _elongation_limit(options, psf) * np.maximum(b, 1e-9))


def _too_large(objects, peak: np.ndarray, noise: np.ndarray, psf: PointSpread | None) -> np.ndarray:
    """Effective area over :data:`EXTENDED_AREA_RATIO` times the PSF's (nothing without a PSF)."""
    if psf is None:
        return np.zeros(len(objects), dtype=bool)
    return _effective_area(objects, peak, noise) > EXTENDED_AREA_RATIO * psf.area_px


def _on_structure(objects, sub: np.ndarray, peak: np.ndarray, noise: np.ndarray,
                  psf: PointSpread | None, *, quantum: float = 0.0) -> np.ndarray:
    """Blobs lying on something extended: the ring around them stands above the sky, or is uneven.

    The ring (:data:`RING_POINTS` pixels at 3 PSF radii, where a star's own light has fallen
    below 0.1 % of its peak for a Gaussian; 4 times the blob's ``a`` without a PSF):

    * its median (a neighbour covering part of it does not count) above :data:`RING_SIGMA` sigma
      and :data:`RING_FRACTION` of the blob's peak: on a comet's tail, the Moon's halo, a cloud or a
      glowing corner the ring is as bright as the structure, which the background mesh (64 px
      boxes) does not follow;
    * its interquartile range above :data:`RING_SPREAD_SIGMA` sigma, :data:`RING_SPREAD_FRACTION`
      of the peak and :data:`RING_SPREAD_QUANTA` steps of integer values: where a bright sky meets a
      dark treeline or roof (the Milky Way setting behind trees), the mesh's level lies between the
      two, and the sky's noise along the edge, its knots and the gaps between branches stand out as
      blobs whose ring is part sky, part ground; its median may be either's.  Around a star on flat
      sky the quartiles are those of the noise (1.35 sigma apart for white noise; 0.9 sigma at the
      median, 1.4 at the 95th percentile measured on the wide bench's stars, whose sigma is the
      correlated noise's larger one), and a neighbour on under a quarter of the ring does not move
      them.  The steps: on a dim 8-bit JPEG whose noise is under a step, a faint star's ring is
      rounded, and rings with the compression's, to levels two steps apart.

    Either way the blob is a knot of that structure, or a star that cannot be measured on it.
    """
    if not len(objects):
        return np.zeros(0, dtype=bool)
    height, width = sub.shape
    radius = 3.0 * psf.radius_px if psf is not None else 4.0 * objects["a"].astype(float)
    radius = np.maximum(radius, 3.0) * np.ones(len(objects))
    angle = np.linspace(0.0, 2.0 * np.pi, RING_POINTS, endpoint=False)
    x = np.rint(objects["x"][:, None] + radius[:, None] * np.cos(angle)).astype(int)
    y = np.rint(objects["y"][:, None] + radius[:, None] * np.sin(angle)).astype(int)
    inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    ring = np.where(inside, sub[np.clip(y, 0, height - 1), np.clip(x, 0, width - 1)], np.nan)
    enough = inside.sum(axis=1) >= RING_POINTS // 4
    level, spread = np.full(len(objects), -np.inf), np.zeros(len(objects))
    if enough.any():
        lower, level[enough], upper = np.nanpercentile(ring[enough], [25.0, 50.0, 75.0], axis=1)
        spread[enough] = upper - lower
    uneven = np.maximum(np.maximum(RING_SPREAD_SIGMA * noise, RING_SPREAD_FRACTION * peak),
                        RING_SPREAD_QUANTA * quantum)
    return (level > np.maximum(RING_SIGMA * noise, RING_FRACTION * peak)) | (spread > uneven)


def _in_rows(objects) -> np.ndarray:
    """Blobs standing side by side in a row: the characters of a line of text (a date stamp, a camera's
    settings, a caption, a watermark), a treeline's gaps along the horizon, a street's lights.

    Side by side: boxes (sep's ``xmin``-``ymax``) of heights within a factor :data:`ROW_HEIGHT_RATIO`,
    overlapping by at least half the lower one's height, with a gap no wider than :data:`ROW_GAP` times
    that height (a letter's spacing, a word's).  A chain of :data:`ROW_MIN_BLOBS` or more such blobs (across,
    or down: a turned image) whose whole is at least :data:`ROW_MIN_ASPECT` times longer than high is a
    row, with every blob inside its box (a colon's dots, a full stop).  Stars are strewn: four of a size
    whose boxes touch in a row, each within its own height of the next, is no star field's pattern.  A
    text's digits are as bright as stars, saturated: the brightest sources of a stamped photograph were its
    text.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(objects)
    in_row = np.zeros(n, dtype=bool)
    if n < ROW_MIN_BLOBS:
        return in_row
    for lo_a, hi_a, lo_b, hi_b in (("xmin", "xmax", "ymin", "ymax"), ("ymin", "ymax", "xmin", "xmax")):
        start, end = objects[lo_a].astype(float), objects[hi_a].astype(float)  # along the row
        low, high = objects[lo_b].astype(float), objects[hi_b].astype(float)   # across it
        height = high - low + 1.0
        lower = np.minimum(height[:, None], height[None, :])
        overlap = np.minimum(high[:, None], high[None, :]) - np.maximum(low[:, None], low[None, :]) + 1.0
        gap = np.maximum(start[:, None], start[None, :]) - np.minimum(end[:, None], end[None, :]) - 1.0
        neighbours = ((overlap >= 0.5 * lower) & (gap <= ROW_GAP * lower)
                      & (np.maximum(height[:, None], height[None, :]) <= ROW_HEIGHT_RATIO * lower))
        np.fill_diagonal(neighbours, False)
        rows, cols = np.nonzero(neighbours)
        if not len(rows):
            continue
        count, label = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)),
                                            directed=False)
        for k in np.flatnonzero(np.bincount(label, minlength=count) >= ROW_MIN_BLOBS):
            members = label == k
            first, last = start[members].min(), end[members].max()
            bottom, top = low[members].min(), high[members].max()
            if last - first + 1.0 >= ROW_MIN_ASPECT * (top - bottom + 1.0):
                in_row |= (start >= first) & (end <= last) & (low >= bottom) & (high <= top)
    return in_row


def _touches_border(objects, shape: tuple[int, int]) -> np.ndarray:
    """Blobs with a pixel in the frame's outermost row or column."""
    height, width = shape
    return ((objects["xmin"] <= 0) | (objects["ymin"] <= 0)
            | (objects["xmax"] >= width - 1) | (objects["ymax"] >= height - 1))


def _peak_near_border(x: np.ndarray, y: np.ndarray, shape: tuple[int, int], psf: PointSpread | None) -> np.ndarray:
    """Peaks closer to the frame's edge than the PSF's radius (2 px without a PSF): a blob cut there
    has lost a large part of its light, and its centroid means little."""
    height, width = shape
    reach = 2.0 if psf is None else max(2.0, psf.radius_px)
    return np.minimum.reduce([x + 0.5, y + 0.5, width - 0.5 - x, height - 0.5 - y]) < reach


def _is_trail(objects, options: DetectionOptions, psf: PointSpread | None) -> np.ndarray:
    """Blobs that are no stars by shape: elongated (trails) or larger than any star image."""
    return _is_elongated(objects, options, psf) | (objects["npix"] > _star_area_limit(options, psf and psf.area_px))


def _star_area_limit(options: DetectionOptions, psf_area_px: float | None, peak_over_threshold=None,
                     saturated=None) -> np.ndarray | float:
    """The most pixels a star's blob covers: what a Moffat star (:data:`MOFFAT_BETA`) of its peak covers at
    the frame's PSF (effective area ``psf_area_px``), :data:`STAR_AREA_MARGIN` times (a saturated one, or one of unknown peak: a peak of
    :data:`SATURATED_PEAK_RATIO` thresholds, once), and never less than ``max_area_px`` (alone without a PSF).

    A pixel count alone is no scale: a defocused lens imaged finely (a PSF of 400 px^2) puts its brightest
    stars over 2,000 px, while a glare that swallowed a star on a sharp frame covers more than the star's
    peak can light.
    """
    if psf_area_px is None:
        return float(options.max_area_px)
    if peak_over_threshold is None:
        ratio, margin = SATURATED_PEAK_RATIO, 1.0
    else:
        known = ~np.asarray(saturated, dtype=bool)
        ratio = np.where(known, np.maximum(peak_over_threshold, 1.0), SATURATED_PEAK_RATIO)
        margin = np.where(known, STAR_AREA_MARGIN, 1.0)
    covered = (MOFFAT_BETA - 1.0) * (ratio ** (1.0 / MOFFAT_BETA) - 1.0) * psf_area_px
    return np.maximum(float(options.max_area_px), margin * covered)


@dataclass(frozen=True)
class _Trail:
    """A straight trail: centre, direction (radians, sep's ``theta`` convention), half length and half
    width (px), and the box of pixels it covers (rows, columns)."""

    x: float
    y: float
    theta: float
    half_length: float
    half_width: float
    rows: slice
    cols: slice


def _trails(objects, indices: np.ndarray, shape: tuple[int, int]) -> list[_Trail]:
    """The straight trails behind the elongated blobs ``indices``, pieces of one line joined.

    sep's deblending cuts a long trail into several blobs; modelled apart, the joins would leave
    residual pieces.  Blobs whose centres lie on one another's axis (within twice the wider one's
    RMS width) and whose axes agree within 5 degrees are one line: its direction is the longest
    piece's, its extent covers every piece (a uniform segment of RMS length ``a`` is ``2 a sqrt(3)``
    long).
    """
    group = list(range(len(indices)))

    def root(i: int) -> int:
        while group[i] != i:
            group[i] = group[group[i]]
            i = group[i]
        return i

    obj = objects[indices]
    for i in range(len(obj)):
        for j in range(i + 1, len(obj)):
            turn = abs((float(obj["theta"][i] - obj["theta"][j]) + np.pi / 2) % np.pi - np.pi / 2)
            c, s = np.cos(obj["theta"][i]), np.sin(obj["theta"][i])
            off = abs((obj["y"][j] - obj["y"][i]) * c - (obj["x"][j] - obj["x"][i]) * s)
            if turn < np.radians(5.0) and off < 2.0 * max(float(obj["b"][i]), float(obj["b"][j]), 1.0):
                group[root(j)] = root(i)
    height, width = shape
    pad = 3
    out = []
    for r in sorted({root(i) for i in range(len(obj))}):
        members = obj[[i for i in range(len(obj)) if root(i) == r]]
        longest = members[int(np.argmax(members["a"]))]
        theta = float(longest["theta"])
        c, s = np.cos(theta), np.sin(theta)
        weight = members["npix"].astype(float)
        x0, y0 = float(np.average(members["x"], weights=weight)), float(np.average(members["y"], weights=weight))
        along = (members["x"] - x0) * c + (members["y"] - y0) * s
        ends = np.concatenate([along - members["a"] * np.sqrt(3.0), along + members["a"] * np.sqrt(3.0)])
        shift = (ends.max() + ends.min()) / 2.0
        out.append(_Trail(x=x0 + shift * c, y=y0 + shift * s, theta=theta,
                          half_length=float(ends.max() - ends.min()) / 2.0,
                          half_width=max(3.0 * float(members["b"].max()), 2.0),
                          rows=slice(max(0, int(members["ymin"].min()) - pad),
                                     min(height, int(members["ymax"].max()) + pad + 1)),
                          cols=slice(max(0, int(members["xmin"].min()) - pad),
                                     min(width, int(members["xmax"].max()) + pad + 1))))
    return out


def _trail_model(sub: np.ndarray, trail: _Trail) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A straight trail's light: (model cut-out over ``trail.rows, trail.cols``, where it is on, the
    position along it) or None.

    A satellite or aircraft crossing during the exposure leaves a line of even brightness: within
    the trail's extent the light across the line is the same everywhere along it.  Its profile
    across is the median of the cut-out's pixels in half-pixel bins of distance from the axis
    (the median ignores the few stars riding on it).  Beyond the half width or past the ends the
    model is 0.
    """
    cut = sub[trail.rows, trail.cols]
    yy, xx = np.mgrid[trail.rows, trail.cols]
    c, s = np.cos(trail.theta), np.sin(trail.theta)
    dx, dy = xx - trail.x, yy - trail.y
    along, across = dx * c + dy * s, dy * c - dx * s
    on = (np.abs(across) <= trail.half_width) & (np.abs(along) <= trail.half_length)
    if np.count_nonzero(on) < 20:
        return None
    bins = np.round(across * 2.0).astype(int)
    model = np.zeros_like(cut)
    for k in np.unique(bins[on]):
        inside = on & (bins == k)
        model[inside] = np.median(cut[inside])
    return model, on, along


def _stars_on_trails(sep, sub: np.ndarray, noise: float, objects, options: DetectionOptions,
                     psf: PointSpread | None):
    """Stars merged into a trail's blob, found again: (objects with them added, the image to measure on).

    A trail flagged ``elongated`` takes every star it touches with it.  A trail is as narrow as a
    star (sep's ``b`` at most twice the PSF's sigma, when the PSF is known) and at least
    :data:`TRAIL_MIN_ASPECT` times longer than wide: a comet's tail, a cloud's edge, a branch or a
    knot of a treeline is no line of even brightness, and modelled as one it leaves its knots as
    "stars" (and the ring of a blob beside it, judged on the image with the model taken out, even).
    Its model
    (:func:`_trail_model`) is subtracted and the residual searched at the detection threshold, with
    the trail's own shot noise (the residual's robust spread on it) as the noise there; round
    blobs at least 4 px inside its ends and not found before are stars (appended; the trail stays
    one flagged blob),
    measured later on the image with the trails' light taken out, so their centroids are not
    pulled towards the line.  Residual pieces of an uneven trail are elongated and stay rejected.
    """
    if not len(objects):
        return objects, sub
    line = _is_elongated(objects, options, psf) & (objects["npix"] <= 50 * options.max_area_px)
    if psf is not None:
        line &= objects["b"] <= 2.0 * psf.sigma_px
    elongated = np.flatnonzero(line)
    if not len(elongated):
        return objects, sub
    clean = sub.copy()
    found = []
    for trail in _trails(objects, elongated[:options.max_split_per_frame], sub.shape):
        if trail.half_length < TRAIL_MIN_ASPECT * trail.half_width:
            continue  # a blob a few times longer than wide, no line of even brightness: a knot, an edge
        model = _trail_model(sub, trail)
        if model is None:
            continue
        light, on, along = model
        clean[trail.rows, trail.cols] -= light
        residual = np.ascontiguousarray(clean[trail.rows, trail.cols])
        on_noise = 1.4826 * float(np.median(np.abs(residual[on] - np.median(residual[on]))))
        err = np.where(on, max(noise, on_noise), noise).astype(np.float32)
        sep.set_extract_pixstack(SEP_PIXSTACK)
        try:
            parts = sep.extract(residual, options.threshold_sigma, err=err, minarea=options.min_area_px,
                                deblend_cont=0.005, clean=False)
        except Exception:  # noqa: BLE001 - a refinement only: the trail stays what it was
            continue
        px = np.clip(np.round(parts["x"]).astype(int), 0, residual.shape[1] - 1)
        py = np.clip(np.round(parts["y"]).astype(int), 0, residual.shape[0] - 1)
        parts = parts[(parts["a"] <= _elongation_limit(options, psf) * np.maximum(parts["b"], 1e-9))
                      & (parts["npix"] <= _star_area_limit(options, psf and psf.area_px))
                      & (np.abs(along[py, px]) <= trail.half_length - 4.0)]
        for name in ("x", "xmin", "xmax", "xpeak", "xcpeak"):
            parts[name] += trail.cols.start
        for name in ("y", "ymin", "ymax", "ypeak", "ycpeak"):
            parts[name] += trail.rows.start
        found.append(parts.astype(objects.dtype))
    found = np.concatenate(found) if found else objects[:0]
    # Blobs beside the trail were found on their own already: keep only the new ones.
    others = objects[np.setdiff1d(np.arange(len(objects)), elongated)]
    if len(found) and len(others):
        gap = np.hypot(found["x"][:, None] - others["x"][None, :], found["y"][:, None] - others["y"][None, :])
        found = found[gap.min(axis=1) > np.maximum(2.0, 2.0 * found["a"])]
    return (np.concatenate([objects, found]) if len(found) else objects), clean


def _neighbours(sub: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n, 4) the four edge neighbours of each (x, y), brightest first (outside the frame counts as -inf)."""
    height, width = sub.shape
    values = np.full((len(x), 4), -np.inf)
    for k, (dx, dy) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
        xx, yy = x + dx, y + dy
        inside = (xx >= 0) & (xx < width) & (yy >= 0) & (yy < height)
        values[inside, k] = sub[yy[inside], xx[inside]]
    return -np.sort(-values, axis=1)


def _max_around(data: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Largest raw value in the 3 x 3 box around each (x, y)."""
    height, width = data.shape
    best = np.full(len(x), -np.inf)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            xx, yy = np.clip(x + dx, 0, width - 1), np.clip(y + dy, 0, height - 1)
            best = np.maximum(best, data[yy, xx])
    return best


def _refine(sep, sub: np.ndarray, rms: float | np.ndarray, xy: np.ndarray, a: np.ndarray, isophotal: np.ndarray,
            psf: PointSpread | None, strong: np.ndarray):
    """Windowed centroids and aperture fluxes of star-like blobs: (xy, flux, snr).

    The window's sigma is the PSF's (sqrt(area / 2 pi)), the same for every star: a neighbour's
    light does not widen it, and the aperture fluxes compare.  Without a PSF, each blob's from its
    half-light radius (sigma = 2 / 2.35 r_half).  Only ``strong`` blobs are windowed: on a peak
    below :data:`WINDOW_PEAK_SIGMA` the window wanders in the noise for all its iterations (on a
    real frame, 140 faint blobs took 25 times the time of the 30 bright ones) and lands no closer
    than sep's barycentre, which they keep.  A blob with a neighbour at least a tenth as bright
    within four window sigmas keeps sep's barycentre and isophotal flux (its own deblended pixels):
    the window and the aperture would take in the neighbour's light (a faint knot beside a bright
    star got the star's aperture flux, and ranked second in its frame).
    """
    x, y = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1])
    if psf is not None:
        sig = np.full(len(x), float(np.clip(psf.sigma_px, 0.3, 10.0)))
    else:
        rmax = np.clip(6.0 * a, 3.0, 50.0)
        r_half, _ = sep.flux_radius(sub, x, y, rmax, 0.5, subpix=5)
        sig = np.clip(2.0 / 2.35 * np.nan_to_num(r_half, nan=1.0), 0.3, 10.0)
    xw, yw, wflag = x.copy(), y.copy(), np.ones(len(x), dtype=int)
    if strong.any():  # subpix 5: sep's 11 takes 5 times as long for the same centroids
        xw[strong], yw[strong], wflag[strong] = sep.winpos(sub, x[strong], y[strong], sig[strong], subpix=5)
    moved = np.hypot(xw - x, yw - y)
    crowded = _crowded(x, y, isophotal, np.maximum(4.0 * sig, 3.0))
    good = (wflag == 0) & np.isfinite(xw) & np.isfinite(yw) & (moved < 1.5) & ~crowded
    x = np.where(good, xw, x)
    y = np.where(good, yw, y)
    radius = np.clip(3.0 * sig, 2.5, 30.0)
    flux, flux_err, _ = sep.sum_circle(sub, x, y, radius, err=rms, subpix=5)
    flux = np.where(crowded, isophotal, flux)
    snr = np.where(flux_err > 0, flux / np.maximum(flux_err, 1e-12), 0.0)
    return np.column_stack([x, y]), flux, snr


def _crowded(x: np.ndarray, y: np.ndarray, flux: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Blobs with a neighbour at least a tenth as bright within ``reach`` px."""
    crowded = np.zeros(len(x), dtype=bool)
    if len(x) < 2:
        return crowded
    from scipy.spatial import cKDTree

    pairs = cKDTree(np.column_stack([x, y])).query_pairs(float(np.max(reach)), output_type="ndarray")
    for i, j in pairs:
        if np.hypot(x[i] - x[j], y[i] - y[j]) < reach[i] and flux[j] >= 0.1 * flux[i]:
            crowded[i] = True
        if np.hypot(x[i] - x[j], y[i] - y[j]) < reach[j] and flux[i] >= 0.1 * flux[j]:
            crowded[j] = True
    return crowded
