"""Detecting and centroiding stars in a frame with ``sep`` (Source Extractor as a library).

Why sep: measured against photutils on rendered frames with known truth
(``python -m app bench --suite frames``, docs/frames.md): the same
completeness and centroid accuracy at a fraction of the time per megapixel.

Steps, per frame:

1. known hot pixels (the camera's map, :mod:`app.frames.hotpixels`) are
   replaced by the median of their neighbours;
2. background and noise estimated locally: ``sep.Background`` on a mesh of
   ``background_box_px`` boxes (median-filtered 3 x 3), subtracted; the noise
   map is its RMS;
3. ``sep.extract`` finds connected pixels ``threshold_sigma`` times the local
   noise above the background (matched 3 x 3 filter, deblending);
4. every blob is classified: ``hot_pixel`` (one sharp pixel: its four
   neighbours stay below ``max(2.5 sigma, 15 %)`` of its peak, which no PSF of
   sigma >= 0.6 px does), ``elongated`` (a / b above ``max_elongation``: trails
   of satellites, aircraft, meteors), ``extended`` (more pixels than
   ``max_area_px``: the Moon, the Earth's limb, glare), ``saturated`` (its
   peak at the saturation level), ``edge`` (cut by the frame's border);
   hot pixels, elongated and extended blobs are not stars; saturated round
   blobs are bright stars and stay, flagged;
   close pairs the filter merged are split again from an unfiltered look at 10 sigma;
   stars a trail ran over or beside are looked for again once the trail is modelled and
   subtracted (:func:`_stars_on_trails`);
5. positions: windowed centroids (``sep.winpos``, SExtractor's XWIN/YWIN,
   Gaussian window from the half-light radius), which at SNR 50 land within
   a few hundredths of a pixel; brightness = flux in a circular aperture of
   ~3 window sigmas, background subtracted.

Pixel convention: sep puts (0, 0) at the centre of the first pixel of the
array, the array's row 0 is the sensor's top row (:mod:`app.frames.images`),
so sep's (x, y) are this project's (x, y) unchanged (tests/test_frames_detect.py
checks a single bright pixel at (x, y) comes back at (x, y)).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

#: sep's default 3 x 3 detection filter [[1,2,1],[2,4,2],[1,2,1]] / 16 scales white noise by sqrt(36)/16.
FILTER_NOISE_GAIN = 6.0 / 16.0
#: Threshold (sigma, unfiltered) at which merged close pairs are looked for again.
SPLIT_SIGMA = 10.0
#: Noise maps whose largest and smallest values differ by less than this are taken as even.
UNIFORM_NOISE_RATIO = 1.3
#: A sharp blob is a hot-pixel candidate for the camera's map when its peak is this many sigma high.
CANDIDATE_SIGMA = 10.0
#: Flags that make a blob "not a star".
REJECTING_FLAGS = ("hot_pixel", "elongated", "extended")
#: Every flag a detection may carry.
FLAGS = ("hot_pixel", "elongated", "extended", "saturated", "edge")
#: sep's internal buffer of object pixels: its default, enough for star fields; sep allocates it on
#: every call (3 million cost ~150 ms), so a larger one is used only when a frame overflows it.
SEP_PIXSTACK = 300_000
SEP_PIXSTACK_LARGE = 4_000_000


class DetectionError(ValueError):
    """A frame where detection cannot work (e.g. nothing but noise features: sep's buffers overflow)."""


@dataclass(frozen=True)
class DetectionOptions:
    """How sources are found and which are kept (defaults suit star cameras of 0.5-16 Mpx)."""

    threshold_sigma: float = 5.0
    min_area_px: int = 3
    background_box_px: int = 64
    #: Sources reported per frame, brightest first (a TUBSAT sensor reports ~10, others 16).
    max_sources: int = 16
    max_elongation: float = 2.0
    #: Elongation is judged only on blobs with at least this many pixels (shape noise of tiny blobs).
    min_area_for_shape_px: int = 10
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
    box = int(max(8, min(options.background_box_px, min(data.shape) // 2)))
    try:
        background = sep.Background(data, bw=box, bh=box, fw=3, fh=3)
    except Exception as exc:  # noqa: BLE001 - sep raises plain Exceptions for its own limits
        raise DetectionError(f"the background cannot be estimated ({exc})") from None
    sub = data.copy()
    background.subfrom(sub)
    floor = _noise_floor(data)
    rms = np.maximum(background.rms(), floor)
    still_hot = tuple((int(x), int(y)) for x, y in sorted(set(map(tuple, hot_pixels or [])))
                      if 0 <= x < data.shape[1] and 0 <= y < data.shape[0]
                      and raw[y, x] - data[y, x] > max(5.0 * float(rms[y, x]), 0.0))
    sample = rms[:: max(1, rms.shape[0] // 32), :: max(1, rms.shape[1] // 32)]
    uniform = float(sample.max()) <= UNIFORM_NOISE_RATIO * float(sample.min())
    objects = _extract(sep, sub, float(np.median(sample)) if uniform else rms, options)
    objects = _split_blends(sep, sub, float(np.median(sample)), objects, options)
    objects, measured = _stars_on_trails(sep, sub, float(np.median(sample)), objects, options)
    if len(objects) > options.max_candidates:
        order = np.argsort(-objects["flux"], kind="stable")[:options.max_candidates]
        objects = objects[np.sort(order)]
    n = len(objects)
    height, width = data.shape
    xpeak = np.clip(objects["xpeak"].astype(int), 0, width - 1)
    ypeak = np.clip(objects["ypeak"].astype(int), 0, height - 1)
    peak = sub[ypeak, xpeak]
    local_noise = rms[ypeak, xpeak]
    a, b = objects["a"].astype(float), objects["b"].astype(float)
    elongation = np.where(b > 0, a / np.maximum(b, 1e-9), np.inf)
    neighbours = _max_neighbour(sub, xpeak, ypeak)
    hot = (peak > 0) & (neighbours < np.maximum(2.5 * local_noise, options.hot_neighbour_fraction * peak))
    if saturation is not None:
        top = _max_around(raw, xpeak, ypeak)
        saturated = top >= 0.995 * saturation
    else:
        saturated = np.zeros(n, dtype=bool)
    trunc = (objects["flag"] & sep.OBJ_TRUNC) != 0
    flags = []
    for k in range(n):
        f = []
        if hot[k]:
            f.append("hot_pixel")
        if objects["npix"][k] >= options.min_area_for_shape_px and elongation[k] > options.max_elongation:
            f.append("elongated")
        if objects["npix"][k] > options.max_area_px:
            f.append("extended")
        if saturated[k]:
            f.append("saturated")
        if trunc[k]:
            f.append("edge")
        flags.append(tuple(f))
    xy = np.column_stack([objects["x"], objects["y"]]).astype(float) if n else np.zeros((0, 2))
    flux = objects["flux"].astype(float).copy()
    snr = np.zeros(n)
    measure = np.array([not any(x in REJECTING_FLAGS for x in f) for f in flags], dtype=bool)
    if measure.any():
        xy[measure], flux[measure], snr[measure] = _refine(sep, measured, rms, xy[measure], a[measure])
    xy[:, 0] = np.clip(xy[:, 0], -0.5, width - 0.5)
    xy[:, 1] = np.clip(xy[:, 1], -0.5, height - 0.5)
    flux = np.maximum(flux, 0.0)
    order = np.argsort(-flux, kind="stable")
    return Detections(xy=xy[order], flux=flux[order], snr=snr[order], peak=peak[order],
                      peak_pixel=np.column_stack([xpeak, ypeak])[order] if n else np.zeros((0, 2), int),
                      npix=objects["npix"][order].astype(int), elongation=elongation[order],
                      flags=tuple(flags[k] for k in order), background=float(background.globalback),
                      noise=float(max(background.globalrms, floor)), still_hot=still_hot,
                      peak_sigma=(peak / np.maximum(local_noise, 1e-12))[order])


def _noise_floor(data: np.ndarray) -> float:
    """Smallest noise assumed: the quantisation of integer data (0.3 units), a tiny fraction of the range else."""
    sample = data[:: max(1, data.shape[0] // 64), :: max(1, data.shape[1] // 64)]
    if np.all(sample == np.round(sample)):
        return 0.3
    span = float(np.ptp(sample)) if sample.size else 0.0
    return max(1e-6, 1e-4 * span)


def _extract(sep, sub: np.ndarray, rms: np.ndarray | float, options: DetectionOptions):
    """sep.extract; when its buffers overflow, again with a larger buffer, then at twice the threshold.

    ``rms`` a map: sep's matched filter thresholds at ``threshold_sigma`` times the *filtered* image's
    local noise.  ``rms`` one number (a frame with even noise): the same threshold, written on the
    unfiltered scale (times the filter's noise gain), which sep applies twice as fast.
    """
    base = options.threshold_sigma * (1.0 if isinstance(rms, np.ndarray) else FILTER_NOISE_GAIN)
    attempts = ((SEP_PIXSTACK, base), (SEP_PIXSTACK_LARGE, base), (SEP_PIXSTACK_LARGE, 2 * base))
    error = None
    for stack, threshold in attempts:
        sep.set_extract_pixstack(stack)
        try:
            # clean=False: SExtractor's cleaning treats everything within a bright trail's huge
            # second moments as its wings and drops whole star fields beside a satellite trail.
            return sep.extract(sub, threshold, err=rms, minarea=options.min_area_px, deblend_cont=0.005,
                               clean=False)
        except Exception as exc:  # noqa: BLE001 - sep raises plain Exceptions ("internal pixel buffer full")
            error = exc
        finally:
            sep.set_extract_pixstack(SEP_PIXSTACK)
    raise DetectionError(f"too many blobs to separate even at {attempts[-1][1]:g} sigma ({error}); "
                         "is this a star field?")


def _split_blends(sep, sub: np.ndarray, noise: float, objects, options: DetectionOptions):
    """Close pairs the detection filter merged, split again.

    The matched filter that finds faint stars also fills the saddle between two stars a few pixels
    apart, so sep's deblending sees one blob with its centroid between them.  Unfiltered, at
    :data:`SPLIT_SIGMA`, bright stars separate: a filtered blob holding two or more unfiltered
    ones is replaced by them (nothing changes when each holds one); elongated and extended blobs
    (trails, glare) are never split.
    """
    if not len(objects) or options.max_split_per_frame <= 0:
        return objects
    sep.set_extract_pixstack(SEP_PIXSTACK)
    try:
        sharp = sep.extract(sub, SPLIT_SIGMA, err=noise, minarea=options.min_area_px, filter_kernel=None,
                            deblend_cont=0.005, clean=False)
    except Exception:  # noqa: BLE001 - a refinement only: keep what the filtered pass found
        return objects
    if len(sharp) < 2:
        return objects
    d = np.hypot(sharp["x"][:, None] - objects["x"][None, :], sharp["y"][:, None] - objects["y"][None, :])
    owner = np.argmin(d, axis=1)
    near = d[np.arange(len(sharp)), owner] <= np.maximum(3.0 * objects["a"][owner], 3.0)
    trail = _is_trail(objects, options)  # a trail's pieces are no stars: it stays one flagged blob
    split = [k for k in np.unique(owner[near]) if np.count_nonzero(near & (owner == k)) >= 2 and not trail[k]]
    split = split[:options.max_split_per_frame]
    if not split:
        return objects
    parts = sharp[np.isin(owner, split) & near]
    keep = np.ones(len(objects), dtype=bool)
    keep[split] = False
    return np.concatenate([objects[keep], parts.astype(objects.dtype)])


def _is_trail(objects, options: DetectionOptions) -> np.ndarray:
    """Blobs that are no stars by shape: elongated (trails) or larger than any star image."""
    a, b, npix = objects["a"], objects["b"], objects["npix"]
    return ((npix >= options.min_area_for_shape_px) & (a > options.max_elongation * np.maximum(b, 1e-9))) \
        | (npix > options.max_area_px)


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


def _stars_on_trails(sep, sub: np.ndarray, noise: float, objects, options: DetectionOptions):
    """Stars merged into a trail's blob, found again: (objects with them added, the image to measure on).

    A trail flagged ``elongated`` takes every star it touches with it.  Its model
    (:func:`_trail_model`) is subtracted and the residual searched at the detection threshold, with
    the trail's own shot noise (the residual's robust spread on it) as the noise there; round
    blobs at least 4 px inside its ends and not found before are stars (appended; the trail stays
    one flagged blob),
    measured later on the image with the trails' light taken out, so their centroids are not
    pulled towards the line.  Residual pieces of an uneven trail are elongated and stay rejected.
    """
    if not len(objects):
        return objects, sub
    elongated = np.flatnonzero(_is_trail(objects, options) & (objects["npix"] <= 50 * options.max_area_px))
    if not len(elongated):
        return objects, sub
    clean = sub.copy()
    found = []
    for trail in _trails(objects, elongated[:options.max_split_per_frame], sub.shape):
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
        parts = parts[(parts["a"] <= options.max_elongation * np.maximum(parts["b"], 1e-9))
                      & (parts["npix"] <= options.max_area_px)
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


def _max_neighbour(sub: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Largest of the four edge neighbours of each (x, y) (outside the frame counts as -inf)."""
    height, width = sub.shape
    best = np.full(len(x), -np.inf)
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        xx, yy = x + dx, y + dy
        inside = (xx >= 0) & (xx < width) & (yy >= 0) & (yy < height)
        values = np.full(len(x), -np.inf)
        values[inside] = sub[yy[inside], xx[inside]]
        best = np.maximum(best, values)
    return best


def _max_around(data: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Largest raw value in the 3 x 3 box around each (x, y)."""
    height, width = data.shape
    best = np.full(len(x), -np.inf)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            xx, yy = np.clip(x + dx, 0, width - 1), np.clip(y + dy, 0, height - 1)
            best = np.maximum(best, data[yy, xx])
    return best


def _refine(sep, sub: np.ndarray, rms: np.ndarray, xy: np.ndarray, a: np.ndarray):
    """Windowed centroids and aperture fluxes of star-like blobs: (xy, flux, snr)."""
    x, y = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1])
    rmax = np.clip(6.0 * a, 3.0, 50.0)
    r_half, _ = sep.flux_radius(sub, x, y, rmax, 0.5, subpix=5)
    sig = np.clip(2.0 / 2.35 * np.nan_to_num(r_half, nan=1.0), 0.3, 10.0)
    xw, yw, wflag = sep.winpos(sub, x, y, sig)
    moved = np.hypot(xw - x, yw - y)
    # The window of a star with a close neighbour takes in the neighbour's light: such stars keep
    # sep's barycentre of their own (deblended) pixels.
    if len(x) > 1:
        gap = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
        np.fill_diagonal(gap, np.inf)
        crowded = gap.min(axis=1) < np.maximum(4.0 * sig, 3.0)
    else:
        crowded = np.zeros(len(x), dtype=bool)
    good = (wflag == 0) & np.isfinite(xw) & np.isfinite(yw) & (moved < 1.5) & ~crowded
    x = np.where(good, xw, x)
    y = np.where(good, yw, y)
    radius = np.clip(3.0 * sig, 2.5, 30.0)
    flux, flux_err, _ = sep.sum_circle(sub, x, y, radius, err=rms, subpix=5)
    snr = np.where(flux_err > 0, flux / np.maximum(flux_err, 1e-12), 0.0)
    return np.column_stack([x, y]), flux, snr
