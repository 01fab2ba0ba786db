"""Binning a frame larger than the detection budget, and bringing what is found back to its own pixels.

A photograph as it comes (20-50 Mpx, a phone's 8000 x 6000) holds more pixels than detection needs or
than one pass's time allows (:attr:`app.frames.images.FrameLimits.max_pixels_per_frame`, 16 Mpx).  Such
a frame is averaged over ``b`` x ``b`` blocks, ``b`` the smallest integer that brings its full blocks
within the budget (:func:`binning_factor`), read so (:func:`block_mean`, in :mod:`app.frames.images`), and
detection runs on the full blocks (:func:`detect_on_blocks`); the last ``width mod b`` columns and
``height mod b`` rows, less than a block, are not searched.

Geometry (the project's convention, docs/conventions.md: (0, 0) is the centre of the top-left pixel):
block ``i`` covers pixels ``b*i .. b*i + b - 1``, whose centre is at ``b*i + (b - 1) / 2``.  A position
``u`` in block pixels is therefore ``x = b*u + (b - 1) / 2`` in the frame's own pixels: exact, and linear
in ``u``, so a centroid (a light-weighted mean position) maps to the centroid of the same light
(:func:`in_frame_pixels`).  Everything downstream (the sources, the camera, the hot-pixel map) is in
the frame's own pixels.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from app.frames.detect import DetectionOptions, Detections, PointSpread, detect


def binning_factor(width: int, height: int, max_pixels: int) -> int:
    """The smallest integer ``b >= 1`` whose full ``b`` x ``b`` blocks, ``(width // b) * (height // b)``,
    number at most ``max_pixels`` (1 for a frame within the budget)."""
    if max_pixels < 1:
        raise ValueError(f"the pixel budget must be at least 1, got {max_pixels}")
    b = 1
    while (width // b) * (height // b) > max_pixels:
        b += 1
    return b


def block_mean(values: np.ndarray, b: int) -> np.ndarray:
    """``values`` averaged over ``b`` x ``b`` blocks, float32, ``ceil(height / b)`` x ``ceil(width / b)``:
    block (i, j) is the mean of pixels ``b*i .. b*i + b - 1`` (rows) by ``b*j .. b*j + b - 1`` (columns),
    the last row and column of blocks over the pixels the frame has there.

    Summed as ``b * b`` strided slices (``values[k::b, l::b]`` holds one pixel of every block), each
    added to a float32 array of the blocks' size: no full-size temporary is made (a 48 Mpx 8-bit frame
    is never 192 MB of float32), and it runs at memory speed (about 0.1 s for 48 Mpx at b = 2).  The
    sums of integer pixels are exact in float32 (below 2^24 up to 16-bit data and b = 16), so each
    mean is the correctly rounded one.
    """
    if b < 1:
        raise ValueError(f"the block size must be at least 1, got {b}")
    height, width = values.shape
    if b == 1:
        return np.array(values, dtype=np.float32)  # a copy of its own: writable whatever the source
    rows, cols = -(-height // b), -(-width // b)
    sums = np.zeros((rows, cols), dtype=np.float32)
    for k in range(b):
        for l in range(b):
            part = values[k::b, l::b]
            sums[:part.shape[0], :part.shape[1]] += part
    per_row = np.minimum(b, height - b * np.arange(rows)).astype(np.float32)
    per_col = np.minimum(b, width - b * np.arange(cols)).astype(np.float32)
    sums /= np.outer(per_row, per_col)
    return sums


def detect_on_blocks(means: np.ndarray, b: int, options: DetectionOptions, *, integer_values: bool,
                     saturation: float | None, hot_pixels: list[tuple[int, int]]) -> Detections:
    """Detect the stars of a frame on the means of its full ``b`` x ``b`` blocks (``means``, ``b`` 1: the
    frame itself); the detections in the frame's own pixels (:func:`in_frame_pixels`).

    The detector sets its noise floor at 0.3 units for integer-valued frames (the quantisation of stored
    integers, 1 / sqrt(12)) and at 1e-4 of the range otherwise.  The means of ``b * b`` integers are
    multiples of 1 / b^2: their floor fell to nothing, and on skies clipped at 0 (dark 8-bit photographs,
    where the spread measured is the quantisation's alone) the threshold with it: xmas-image4 upscaled
    2x as a JPEG and binned 2 x 2 gave 490 blobs, none of the 32 reported within 1 px of a star found on
    the frame itself.  The quantisation of the mean of ``b * b`` integers is 1 / (b sqrt(12)), so when
    the stored values are integers (``integer_values``) detection is given the means in units of 1 / b,
    rounded: integers whose quantisation, 1 / sqrt(12), is the one the detector assumes.  The rounding
    adds as much again in quadrature (0.29 / b stored units): nothing beside a sky noise above the
    quantisation, sqrt(2) times the floor on a clipped sky.  The same frame then gave 23 of 32 within
    1 px, the first 16 all.  Float frames (FITS, TIFF) are given the means as they are.
    """
    if b == 1:
        return detect(means, options, saturation=saturation, hot_pixels=hot_pixels)
    unit = 1.0 / b if integer_values else 1.0
    values = np.rint(means * np.float32(b)) if integer_values else means
    found = detect(values, options, saturation=None if saturation is None else saturation / unit,
                   hot_pixels=in_block_pixels(hot_pixels, b))
    return in_frame_pixels(found, b, unit, hot_pixels)


def in_frame_pixels(found: Detections, b: int, unit: float = 1.0,
                    hot_pixels: list[tuple[int, int]] | None = None) -> Detections:
    """Detections made on the ``b`` x ``b`` block means of a frame, given to detection in ``unit`` s of the
    frame's own values (:func:`detect_on_blocks`), in the frame's own pixels and values.

    * ``xy``: ``b * u + (b - 1) / 2`` (exact, see the module);
    * ``peak_pixel``: the frame pixel at the block's centre (``b * i + (b - 1) // 2``: the upper-left of
      the four central pixels when b is even), so that a hot pixel seen in a block is counted at one
      place of the camera's map whatever frame of the camera shows it;
    * ``flux``: times ``unit * b * b``: the block means' sum times the pixels each stands for is the sum
      of the frame's pixels, the flux an unbinned detection would measure;
    * ``npix``: times ``b * b``, the frame pixels the blob covers; the PSF's effective area times ``b * b``
      too (its sigma and radius times ``b``);
    * ``peak``, ``background``, ``noise``: times ``unit``, those of the block means (the mean of b * b
      pixels keeps the level; its noise is the pixels' over ``b`` for white noise, less reduced for the
      correlated noise of demosaiced and compressed photographs);
    * ``still_hot``: the given ``hot_pixels`` (frame pixels) whose block is still hot;
    * unchanged: the signal-to-noise ratios, peak sigmas, elongations and flags (ratios and shapes).
    """
    if b == 1 and unit == 1.0:
        return found
    area = b * b
    blocks_still_hot = set(found.still_hot)
    psf = found.psf
    return dataclasses.replace(
        found,
        xy=found.xy * b + (b - 1) / 2.0,
        flux=found.flux * (area * unit),
        peak=found.peak * unit,
        peak_pixel=found.peak_pixel * b + (b - 1) // 2,
        npix=found.npix * area,
        background=found.background * unit,
        noise=found.noise * unit,
        still_hot=tuple(p for p in sorted(set(hot_pixels or [])) if (p[0] // b, p[1] // b) in blocks_still_hot),
        psf=None if psf is None else PointSpread(area_px=psf.area_px * area, elongation=psf.elongation,
                                                 stars=psf.stars))


def in_block_pixels(points: list[tuple[int, int]], b: int) -> list[tuple[int, int]]:
    """Frame pixels (e.g. the camera's hot pixels) -> the blocks that hold them, each once."""
    if b == 1:
        return list(points)
    return sorted({(int(x) // b, int(y) // b) for x, y in points})
