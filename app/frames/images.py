"""Reading star-camera frames: FITS (astropy) and PNG/JPEG/TIFF, 8 and 16 bit, TIFF also 32-bit float (Pillow).

:func:`read_frames` turns one file's bytes into :class:`Frame` objects, one per
image: a FITS file gives one frame per image HDU (a multi-extension FITS is a
whole pass), a multi-page TIFF one per page, anything else one.  Frames are
produced lazily, one at a time, so a pass of many large frames never sits in
memory decoded all at once.

Bad input never escapes as a library exception: every problem becomes a
:class:`~app.telemetry.errors.ImageError` located at the file (and HDU
or page), e.g. ``frames/b.png: not a readable image (cannot identify image
file)`` or ``pass.fits[3]: 3-D image (NAXIS = 3); a frame is 2-D``.

Pixel convention (docs/conventions.md): the returned ``pixels[row, col]``
has row 0 at the top of the sensor, so pixel (x=col, y=row) has its centre at
(x, y) and (0, 0) is the centre of the top-left pixel.  PNG, JPEG and TIFF
store the top row first.  FITS images are stored bottom row first *by display
convention*, but cameras write their first read-out (top) row first and say
so with ``ROWORDER = 'TOP-DOWN'``; a frame with ``ROWORDER = 'BOTTOM-UP'`` is
flipped.  A missing ROWORDER is taken as TOP-DOWN (what star-camera capture
software writes).  A mirrored frame is not a rotated sky: identification
would fail, so this matters.  A PNG, JPEG or TIFF whose EXIF (or TIFF) ``Orientation`` says
how it is to be shown (a phone or camera held upright stores its image turned a quarter) is read as
that upright image, as Pillow's ``ImageOps.exif_transpose`` shows it and as a gallery does: sources,
previews and annotations are then in the picture the operator knows, and its width and height are the
upright image's (a note says so).

Why Pillow (not imageio): it is the library imageio itself uses for these
formats, already installed with this project (viser -> imageio -> Pillow),
reads 16-bit greyscale PNG and TIFF natively (modes ``I;16``), and gives the
image size from the header before decoding, so oversized frames are refused
before any pixel is decoded (its own decompression-bomb guard stays on).

Large frames (photographs of 20-120 Mpx): a frame with more pixels than the
detection budget (:attr:`FrameLimits.max_pixels_per_frame`, 16 Mpx) is read
as the means of ``b`` x ``b`` blocks of its luminance, ``b`` the smallest
integer that brings its full blocks within the budget
(:mod:`app.frames.binning`); only a frame beyond
:attr:`FrameLimits.max_decoded_pixels_per_frame` (120 Mpx) is refused, from its
header.  The blocks are summed from the decoded 8- or 16-bit data a strip of
rows at a time (:func:`_by_strips`), so the whole frame never exists as
float32 (480 MB at 120 Mpx), nor as luminance beside its colour; a colour JPEG
is decoded straight to its luminance (JPEG stores it: its Y channel, the same
ITU-R 601 weights as Pillow's RGB -> L, equal to within 2 levels on sky
photographs), so no 32-bit RGB image of it is made either.
"""

from __future__ import annotations

import hashlib
import io
import math
import os
import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone

import numpy as np

from app.config import MAX_SNAPSHOTS
from app.filenames import FITS_SUFFIXES, IMAGE_SUFFIXES
from app.frames.binning import binning_factor, block_mean
from app.frames.lens import exif_lens
from app.frames.times import exif_time
from app.telemetry.errors import ImageError

_FITS_MAGIC = b"SIMPLE  ="
#: Pixels of a PNG, JPEG or TIFF turned into greyscale values at a time (:func:`_by_strips`).
STRIP_PIXELS = 2_000_000
_GZIP_MAGIC = b"\x1f\x8b"


def _env_int(name: str, default: int) -> int:
    try:
        return int(os.environ.get(name, default))
    except ValueError:
        return default


def _env_float(name: str, default: float) -> float:
    try:
        return float(os.environ.get(name, default))
    except ValueError:
        return default


@dataclass(frozen=True)
class FrameLimits:
    """Bounds on the work one pass of frames may cause (environment variables in brackets)."""

    #: Pixels detection works on in one frame (STARID_FRAMES_MAX_PIXELS; 16 Mpx: a 4k x 4k sensor); a
    #: larger frame is binned to fit (:mod:`app.frames.binning`).
    max_pixels_per_frame: int = field(default_factory=lambda: _env_int("STARID_FRAMES_MAX_PIXELS", 16_000_000))
    #: Pixels of one frame that are decoded at all (STARID_FRAMES_MAX_DECODED_PIXELS; 120 Mpx): what
    #: bounds the memory of reading a frame.  120 Mpx holds the largest photographs users have (108 Mpx
    #: phones, 12000 x 9000; 102 Mpx medium format, 11648 x 8736).  Reading a 48 Mpx frame (8000 x 6000,
    #: binned 2 x 2) took, over its file's bytes, 101 MB as a colour JPEG, 154 MB as a 16-bit greyscale PNG
    #: and 245 MB as a colour PNG (Pillow holds RGB in 4 bytes a pixel): at 120 Mpx (binned 3 x 3) about
    #: 0.2, 0.3 and 0.55 GB, against 0.48 GB for its float32 pixels alone.  A larger frame is refused from
    #: its header, before any pixel is decoded (Pillow's own guard refuses 179 Mpx and more at opening).
    max_decoded_pixels_per_frame: int = field(
        default_factory=lambda: _env_int("STARID_FRAMES_MAX_DECODED_PIXELS", 120_000_000))
    #: Frames of one pass: a sequence holds at most as many snapshots.
    max_frames: int = MAX_SNAPSHOTS
    #: Pixels of all frames of one pass, as stored (STARID_FRAMES_MAX_TOTAL_PIXELS): decoding is the work.
    max_total_pixels: int = field(
        default_factory=lambda: _env_int("STARID_FRAMES_MAX_TOTAL_PIXELS", 128_000_000))
    #: Bytes of all files of one upload (STARID_FRAMES_MAX_BYTES; 128 MiB).
    max_bytes: int = field(default_factory=lambda: _env_int("STARID_FRAMES_MAX_BYTES", 128 * 1024 * 1024))
    #: Wall-clock budget of reading and detecting one pass, seconds (STARID_FRAMES_TIMEOUT_S).
    timeout_s: float = field(default_factory=lambda: _env_float("STARID_FRAMES_TIMEOUT_S", 60.0))


@dataclass(frozen=True, eq=False)
class Frame:
    """One image: pixels (float32, row 0 on top) and what its file says about it.

    ``pixels`` are the stored image's own (``binned`` 1) or, for a frame larger than the detection
    budget, the means of its ``binned`` x ``binned`` blocks, ``ceil(height / binned)`` x
    ``ceil(width / binned)`` (the last row and column of blocks over the pixels the image has there:
    what a preview shows); :attr:`detection_pixels` are the full blocks only.  ``width`` and
    ``height`` are always the stored image's.
    """

    pixels: np.ndarray
    #: Where it came from, for messages: ``a.png``, ``pass.fits[2]``, ``scan.tiff[page 1]``.
    location: str
    #: The file name alone (the sidecar names files, not HDUs).
    file: str
    #: HDU number (FITS) or page (TIFF) within the file, None for single-image files.
    part: int | None
    #: Mid-exposure time from the file's own metadata (FITS header, EXIF), None when it has none.
    time: datetime | None
    #: Pixel value at and above which a pixel is saturated (None: unknown, e.g. float images).
    saturation: float | None
    #: Bits per pixel of the stored data (8, 16, 32, -32 for float...).
    bits: int
    #: What the header says about the optics and the pass (focal_length_px, spacecraft, sequence_id...).
    meta: dict = field(default_factory=dict)
    #: Side of the blocks ``pixels`` are the means of (1: the image's own pixels).
    binned: int = 1
    #: (width, height) of the stored image; None: the pixels' own (an unbinned frame).
    stored_size: tuple[int, int] | None = None
    #: The stored values are integers (8-, 16-, 32-bit images, FITS integers unscaled): the detection of
    #: block means follows their quantisation (:func:`app.frames.binning.detect_on_blocks`).
    integer_values: bool = False

    @property
    def width(self) -> int:
        return int(self.stored_size[0] if self.stored_size else self.pixels.shape[1])

    @property
    def height(self) -> int:
        return int(self.stored_size[1] if self.stored_size else self.pixels.shape[0])

    @property
    def detection_pixels(self) -> np.ndarray:
        """What detection searches: the full blocks (the last ``width mod binned`` columns and ``height mod
        binned`` rows, less than a block, are left out; all of ``pixels`` when unbinned)."""
        b = self.binned
        return self.pixels if b == 1 else self.pixels[: self.height // b, : self.width // b]


def looks_like_image(name: str, head: bytes = b"") -> bool:
    """True for a file name ending like an image, or bytes starting like FITS, PNG, JPEG or TIFF."""
    lower = name.lower()
    if lower.endswith(IMAGE_SUFFIXES):
        return True
    return head.startswith((_FITS_MAGIC, b"\x89PNG", b"\xff\xd8\xff", b"II*\x00", b"MM\x00*"))


def file_sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def read_frames(data: bytes, name: str, limits: FrameLimits | None = None) -> Iterator[Frame]:
    """The frames of one file, lazily.  Raises ImageError (located at ``name``) for anything unreadable."""
    limits = limits or FrameLimits()
    raw = bytes(data)
    if not raw:
        raise ImageError.at(name, "the file is empty")
    lower = name.lower()
    if raw.startswith(_FITS_MAGIC) or (lower.endswith(FITS_SUFFIXES) and not raw.startswith(_GZIP_MAGIC)):
        yield from _fits_frames(raw, name, limits)
    elif raw.startswith(_GZIP_MAGIC) and lower.endswith(FITS_SUFFIXES):
        raise ImageError.at(name, "compressed (.gz) FITS files are not accepted: send the .fits itself")
    else:
        yield from _pillow_frames(raw, name, limits)


# ---------------------------------------------------------------------------
# FITS
# ---------------------------------------------------------------------------

def _fits_frames(raw: bytes, name: str, limits: FrameLimits) -> Iterator[Frame]:
    from astropy.io import fits

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            hdul = fits.open(io.BytesIO(raw), memmap=False, lazy_load_hdus=True)
    except Exception as exc:  # noqa: BLE001 - astropy raises OSError, ValueError, TypeError... for bad files
        raise ImageError.at(name, f"not a readable FITS file ({_reason(exc)})") from None
    found = 0
    try:
        primary: dict = {}
        index = 0
        while True:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    hdu = hdul[index]
            except IndexError:
                break
            except Exception as exc:  # noqa: BLE001 - a truncated or corrupt HDU
                raise ImageError.at(f"{name}[{index}]", f"unreadable HDU ({_reason(exc)})") from None
            header = hdu.header
            if index == 0:
                primary = {key: header[key] for key in header if key}
            location = f"{name}[{index}]"
            naxis = int(header.get("NAXIS", 0) or 0)
            is_image = hdu.is_image if hasattr(hdu, "is_image") else False
            if is_image and naxis > 0:
                shape = [int(header.get(f"NAXIS{k}", 0) or 0) for k in range(1, naxis + 1)]
                extra_axes = [n for n in shape[2:] if n != 1]
                if naxis < 2 or extra_axes:
                    raise ImageError.at(location, f"{naxis}-D image (NAXIS = {naxis}, sizes {shape}); "
                                                      "a frame is 2-D")
                width, height = shape[0], shape[1]
                binned = _binning(width, height, location, limits)
                found += 1
                if found > limits.max_frames:
                    raise ImageError.at(name, f"more than {limits.max_frames} frames in one file")
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        values = np.asarray(hdu.data).reshape(height, width)
                except Exception as exc:  # noqa: BLE001 - truncated data, bad BSCALE...
                    raise ImageError.at(location, f"the image data cannot be read ({_reason(exc)})") from None
                merged = {**primary, **{key: header[key] for key in header if key}}
                order = str(merged.get("ROWORDER", "TOP-DOWN")).strip().upper()
                if order == "BOTTOM-UP":
                    values = values[::-1]
                elif order != "TOP-DOWN":
                    raise ImageError.at(location, f"ROWORDER = {order!r}; expected 'TOP-DOWN' or 'BOTTOM-UP'")
                pixels, integer_values = _frame_pixels(values, binned, location), values.dtype.kind in "iub"
                del values
                bits = int(header.get("BITPIX", -32))
                yield Frame(pixels=pixels, location=location, file=name, part=index,
                            time=_fits_time(merged, location), saturation=_fits_saturation(merged, bits),
                            bits=bits, meta=_fits_meta(merged, location), binned=binned,
                            stored_size=(width, height), integer_values=integer_values)
                hdu.data = None  # free the decoded pixels before the next HDU
            index += 1
    finally:
        hdul.close()
    if not found:
        raise ImageError.at(name, "the FITS file holds no 2-D image")


def _fits_time(header: dict, location: str) -> datetime | None:
    """Mid-exposure UTC time: DATE-AVG, else DATE-OBS (+ TIME-OBS) + EXPTIME/2, else MJD-AVG, MJD-OBS + EXPTIME/2."""
    exptime = header.get("EXPTIME", header.get("EXPOSURE"))
    half = 0.0
    if isinstance(exptime, (int, float)) and not isinstance(exptime, bool) and math.isfinite(exptime):
        if not 0 <= exptime <= 86400:
            raise ImageError.at(f"{location}.EXPTIME", f"must be 0 to 86400 s, got {exptime:g}")
        half = exptime / 2.0
    if "DATE-AVG" in header:
        return _header_time(header["DATE-AVG"], f"{location}.DATE-AVG")
    if "DATE-OBS" in header:
        text = str(header["DATE-OBS"]).strip()
        if "T" not in text and "TIME-OBS" in header:
            text = f"{text}T{str(header['TIME-OBS']).strip()}"
        return _header_time(text, f"{location}.DATE-OBS") + timedelta(seconds=half)
    for key, offset in (("MJD-AVG", 0.0), ("MJD-OBS", half)):
        value = header.get(key)
        if value is not None:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 15020 <= value < 88069:
                raise ImageError.at(f"{location}.{key}", f"must be a modified Julian date in 1900-2099, got {value!r}")
            return datetime(1858, 11, 17, tzinfo=timezone.utc) + timedelta(days=float(value), seconds=offset)
    return None


def _header_time(value, location: str) -> datetime:
    text = str(value).strip().removesuffix("Z")
    try:
        t = datetime.fromisoformat(text)
    except ValueError:
        raise ImageError.at(location, f"not an ISO 8601 time: {text[:40]!r}") from None
    t = t.replace(tzinfo=timezone.utc) if t.tzinfo is None else t.astimezone(timezone.utc)
    if not 1900 <= t.year <= 2099:
        raise ImageError.at(location, f"time {text} is outside the supported years 1900 to 2099")
    return t


def _fits_saturation(header: dict, bits: int) -> float | None:
    value = header.get("SATURATE")
    if isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0:
        return float(value)
    if bits == 8:
        return 255.0
    if bits == 16:  # BZERO 32768 is the usual way of storing unsigned 16-bit data
        return 65535.0 if float(header.get("BZERO", 0) or 0) == 32768.0 else 32767.0
    return None


def _fits_meta(header: dict, location: str) -> dict:
    """Optics and naming the header gives: focal length in pixels (FOCALLEN + XPIXSZ, or the WCS scale)."""
    meta: dict = {}
    focal_mm = header.get("FOCALLEN")
    pixel_um = header.get("XPIXSZ", header.get("PIXSIZE1"))
    if _positive(focal_mm) and _positive(pixel_um):
        meta["focal_length_px"] = float(focal_mm) * 1000.0 / float(pixel_um)
        meta["optics_from"] = f"{location}: FOCALLEN {float(focal_mm):g} mm / XPIXSZ {float(pixel_um):g} um"
    else:
        scale = None
        if all(_number(header.get(k)) for k in ("CD1_1", "CD1_2", "CD2_1", "CD2_2")):
            det = header["CD1_1"] * header["CD2_2"] - header["CD1_2"] * header["CD2_1"]
            scale = math.sqrt(abs(det)) if det else None
        elif _number(header.get("CDELT1")) and _number(header.get("CDELT2")):
            scale = math.sqrt(abs(header["CDELT1"] * header["CDELT2"])) or None
        unit = str(header.get("CUNIT1", "deg")).strip().lower()
        if scale and unit in ("deg", "") and 1e-6 < scale < 1.0:
            meta["focal_length_px"] = 1.0 / math.tan(math.radians(scale))
            meta["optics_from"] = f"{location}: WCS scale {scale * 3600:.3f} arcsec/px"
    for key, meta_key in (("SPACECRA", "spacecraft"), ("SEQID", "sequence_id")):
        value = header.get(key)
        if isinstance(value, str) and value.strip():
            meta[meta_key] = value.strip()
    return meta


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _positive(value) -> bool:
    return _number(value) and value > 0


# ---------------------------------------------------------------------------
# PNG, JPEG, TIFF
# ---------------------------------------------------------------------------

def _pillow_frames(raw: bytes, name: str, limits: FrameLimits) -> Iterator[Frame]:
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # DecompressionBombWarning: our own size check follows
            image = Image.open(io.BytesIO(raw))
    except Image.DecompressionBombError as exc:  # over twice Pillow's MAX_IMAGE_PIXELS: said as a size
        raise ImageError.at(name, f"the image is too large to decode: at most "
                                      f"{limits.max_decoded_pixels_per_frame} pixels per frame "
                                      f"(STARID_FRAMES_MAX_DECODED_PIXELS; {_reason(exc)})") from None
    except Exception as exc:  # noqa: BLE001 - UnidentifiedImageError, OSError...
        raise ImageError.at(name, f"not a readable image: FITS, PNG, JPEG or TIFF expected "
                                      f"({_reason(exc)})") from None
    with image:
        if image.format not in ("PNG", "JPEG", "TIFF", "MPO"):
            raise ImageError.at(name, f"{image.format} images are not accepted: FITS, PNG, JPEG or TIFF")
        pages = int(getattr(image, "n_frames", 1) or 1)
        if image.format != "TIFF":
            pages = 1  # animated PNGs and MPO pairs: the first image only
        if pages > limits.max_frames:
            raise ImageError.at(name, f"{pages} pages; at most {limits.max_frames} frames per file")
        for page in range(pages):
            location = name if pages == 1 else f"{name}[page {page}]"
            try:
                image.seek(page)
            except Exception as exc:  # noqa: BLE001
                raise ImageError.at(location, f"cannot read this page ({_reason(exc)})") from None
            width, height = image.size
            binned = _binning(width, height, location, limits)
            if image.format in ("JPEG", "MPO") and image.mode == "RGB":
                image.draft("L", None)  # decode the stored luminance (Y) alone: see the module
            pixels, integer_values, bits, saturation = _pillow_pixels(image, binned, location)
            when, zone_note = exif_time(image, location)
            meta = {**exif_lens(image, width, height, location), **({"time_note": zone_note} if zone_note else {})}
            orientation = _orientation(image)
            if orientation != 1:
                pixels, (width, height) = _upright(pixels, orientation, binned, (width, height))
                meta["orientation_note"] = (f"{location}: turned upright as its EXIF Orientation ({orientation}) says; "
                                            f"pixel positions are the upright image's")
            yield Frame(pixels=pixels, location=location, file=name, part=page if pages > 1 else None,
                        time=when, saturation=saturation, bits=bits, meta=meta, binned=binned,
                        stored_size=(width, height), integer_values=integer_values)


#: EXIF and TIFF ``Orientation`` (tag 274): how the stored rows and columns become the upright image, as numpy
#: operations on the stored array (row 0 at the top).  2, 4, 5 and 7 mirror; 6 and 8 are a phone or camera held
#: upright (turned a quarter), 3 upside down.
_ORIENT = {2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1, :], 5: lambda a: a.T,
           6: lambda a: np.rot90(a, -1), 7: lambda a: a[::-1, ::-1].T, 8: lambda a: np.rot90(a, 1)}
ORIENTATION_TAG = 0x0112


def _orientation(image) -> int:
    """The image's EXIF or TIFF Orientation, 1 (as stored) when it has none or an unknown one."""
    try:
        value = int(image.getexif().get(ORIENTATION_TAG, 1))
    except Exception:  # noqa: BLE001 - Pillow raises many kinds for a corrupt EXIF block
        return 1
    return value if value in _ORIENT else 1


def _upright(pixels: np.ndarray, orientation: int, binned: int,
             size: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int]]:
    """``pixels`` (the stored image's, or its ``binned`` blocks') as the upright image, and its (width, height).

    Binned frames keep their whole blocks only (the last partial column and row of blocks would otherwise
    land on the top or the left), and their size is that of the whole blocks."""
    width, height = size
    if binned > 1:
        pixels = pixels[: height // binned, : width // binned]
        width, height = width // binned * binned, height // binned * binned
    turned = np.ascontiguousarray(_ORIENT[orientation](pixels))
    return turned, ((height, width) if orientation >= 5 else (width, height))


def _pillow_pixels(image, binned: int, location: str) -> tuple[np.ndarray, bool, int, float | None]:
    """The frame's float32 pixels (the means of ``binned`` x ``binned`` blocks when ``binned`` > 1), whether
    its stored values are integers, their bit depth and the saturation level.

    8- and 16-bit images, greyscale or colour, are turned into values a strip of rows at a time
    (:func:`_by_strips`); 32-bit integer and float images (rare, and 4 bytes a pixel as stored) whole.
    """
    mode = image.mode
    values = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            image.load()
            if mode in ("I;16", "I;16L", "I;16B", "I;16N"):
                return _by_strips(image, np.asarray, binned), True, 16, 65535.0
            if mode in ("L", "1", "P", "LA", "PA", "RGB", "RGBA", "RGBX", "CMYK", "YCbCr", "LAB", "HSV"):
                def luminance(strip):  # ITU-R 601 luma, Pillow's RGB -> L
                    return np.asarray(strip if mode == "L" else strip.convert("L"))
                return _by_strips(image, luminance, binned), True, 8, 255.0
            if mode in ("I", "F"):  # 32-bit integer, 32-bit float (TIFF SampleFormat 3)
                values = np.asarray(image)
    except Exception as exc:  # noqa: BLE001 - truncated files, broken compression
        raise ImageError.at(location, f"the image data cannot be decoded ({_reason(exc)})") from None
    if values is None:
        raise ImageError.at(location, f"pixel mode {mode!r} is not supported: greyscale or RGB, 8 or 16 bit, "
                                          "or greyscale 32-bit integer or float")
    if mode == "F":
        return _frame_pixels(values, binned, location), False, -32, None
    top = int(values.max()) if values.size else 0
    return _frame_pixels(values, binned, location), True, 32, 65535.0 if 0 <= top <= 65535 else None


def _by_strips(image, values_of, binned: int) -> np.ndarray:
    """:func:`app.frames.binning.block_mean` of ``values_of(image)``, a strip of whole blocks of rows (about
    :data:`STRIP_PIXELS`) at a time: the luminance of a colour image and the arrays Pillow copies its data
    into (twice: ``np.asarray`` goes through ``tobytes``) exist for one strip, never for the whole frame.
    Reading a 48 Mpx colour JPEG took 185 MB over its file's bytes converted whole (3.9 bytes a pixel),
    a colour PNG 321 MB (6.7); strip by strip, see :attr:`FrameLimits.max_decoded_pixels_per_frame`."""
    width, height = image.size
    rows = max(1, STRIP_PIXELS // (width * binned)) * binned
    pixels = np.empty((-(-height // binned), -(-width // binned)), dtype=np.float32)
    for top in range(0, height, rows):
        strip = values_of(image.crop((0, top, width, min(height, top + rows))))
        pixels[top // binned: top // binned + -(-strip.shape[0] // binned)] = block_mean(strip, binned)
    return pixels


def _frame_pixels(values: np.ndarray, binned: int, location: str) -> np.ndarray:
    """A frame's float32 pixels from its stored values: the values themselves (``binned`` 1) or the means of
    their ``binned`` x ``binned`` blocks (:func:`app.frames.binning.block_mean`), NaN and infinite values
    replaced first (and values beyond float32 after).

    Always an array of its own: ``np.asarray`` of a Pillow image is a read-only view of Pillow's buffer,
    and the detector (sep) takes the frame as a writable buffer (a float TIFF failed with "buffer source
    array is read-only").
    """
    if values.dtype.kind == "f":
        values = _finite(values, location)
    return _finite(block_mean(values, binned), location)


# ---------------------------------------------------------------------------
# shared checks
# ---------------------------------------------------------------------------

def _binning(width: int, height: int, location: str, limits: FrameLimits) -> int:
    """The side of the blocks a frame of this size is read as (1: its own pixels; see the module), from its
    header's size; ImageError for a frame too small, or too large to decode."""
    if width < 16 or height < 16:
        raise ImageError.at(location, f"{width} x {height} pixels is too small for a star camera frame "
                                          "(at least 16 x 16)")
    if width * height > limits.max_decoded_pixels_per_frame:
        raise ImageError.at(location, f"{width} x {height} = {width * height} pixels; at most "
                                          f"{limits.max_decoded_pixels_per_frame} per frame "
                                          "(STARID_FRAMES_MAX_DECODED_PIXELS)")
    budget = max(1, limits.max_pixels_per_frame)
    binned = binning_factor(width, height, budget)
    if width // binned < 16 or height // binned < 16:
        raise ImageError.at(location, f"{width} x {height} pixels binned {binned} x {binned} to fit {budget} "
                                          f"pixels (STARID_FRAMES_MAX_PIXELS) leaves {width // binned} x "
                                          f"{height // binned}, too small to search (at least 16 x 16)")
    return binned


def _finite(pixels: np.ndarray, location: str) -> np.ndarray:
    """NaN or infinite pixels (blanked in float FITS) become the frame's median; mostly blank is refused."""
    bad = ~np.isfinite(pixels)
    n_bad = int(np.count_nonzero(bad))
    if not n_bad:
        return pixels
    if n_bad > pixels.size // 2:
        raise ImageError.at(location, f"{n_bad} of {pixels.size} pixels are NaN or infinite")
    pixels = pixels.copy()
    pixels[bad] = np.median(pixels[~bad])
    return pixels


def _reason(exc: Exception) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    text = re.sub(r"\s*<_io\.BytesIO object at 0x[0-9a-f]+>", "", text)  # Pillow names our in-memory stream
    return text[:160]


def peek_frame(data: bytes, name: str) -> tuple[int, int, dict] | None:
    """(width, height, header meta) of a file's first image from its header alone, or None when that
    cannot be told cheaply (the full read reports the problem)."""
    raw = bytes(data)
    try:
        if raw.startswith(_FITS_MAGIC):
            from astropy.io import fits

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                with fits.open(io.BytesIO(raw), memmap=False, lazy_load_hdus=True) as hdul:
                    primary = {key: hdul[0].header[key] for key in hdul[0].header if key}
                    index = 0
                    while True:
                        try:
                            hdu = hdul[index]
                        except IndexError:
                            return None
                        header = hdu.header
                        if getattr(hdu, "is_image", False) and int(header.get("NAXIS", 0) or 0) >= 2:
                            merged = {**primary, **{key: header[key] for key in header if key}}
                            return (int(header["NAXIS1"]), int(header["NAXIS2"]),
                                    _fits_meta(merged, f"{name}[{index}]"))
                        index += 1
        from PIL import Image

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(io.BytesIO(raw)) as image:
                width, height = int(image.size[0]), int(image.size[1])
                return (height, width, {}) if _orientation(image) >= 5 else (width, height, {})
    except Exception:  # noqa: BLE001 - a peek only; read_frames says what is wrong
        return None
