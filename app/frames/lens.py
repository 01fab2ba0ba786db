"""The lens a photograph's EXIF names, as a focal length in the image's pixels: a hint, not a declaration.

A camera or a phone writes its lens's focal length into the Exif IFD (CIPA DC-008):

* ``FocalLengthIn35mmFilm`` (0xA405, mm): the focal length that gives the same angle of view on a 36 x 24 mm
  frame, which cameras compute through the diagonal (the crop factor, 43.27 mm over the sensor's diagonal).
  The image's diagonal of ``D`` pixels then spans what 43.27 mm spans on film, and
  ``f_px = f35 * D / 43.27``. It survives resizing (the image's own diagonal is used), not cropping.
* ``FocalLength`` (0x920A, mm) with ``FocalPlaneXResolution`` (0xA20E, pixels per ``FocalPlaneResolutionUnit``
  0xA210 of 2 inch, 3 cm, 4 mm, on the sensor, for an image of ``PixelXDimension`` 0xA002 pixels across):
  ``f_px = f_mm * pixels_per_mm * width / PixelXDimension``.

A photograph may have been cropped, or taken through a converter or a telescope that the camera does not know,
so the focal length is searched first, within :func:`app.frames.assemble.fov_focal_tolerance` of it, and the
whole range of fields of view after it (:mod:`app.identification.scale_free`). A value that gives a field of
view outside that range, or that is no positive number, is no hint.
"""

from __future__ import annotations

import math

from app.frames.times import EXIF_IFD

FOCAL_LENGTH = 0x920A
FOCAL_LENGTH_35MM = 0xA405
FOCAL_PLANE_X_RESOLUTION = 0xA20E
FOCAL_PLANE_RESOLUTION_UNIT = 0xA210
PIXEL_X_DIMENSION = 0xA002
#: The diagonal of a 36 x 24 mm frame, mm.
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
#: FocalPlaneResolutionUnit: millimetres in one unit (2 inch, the default, 3 centimetre, 4 millimetre).
_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0}


def exif_lens(image, width: int, height: int, location: str) -> dict:
    """``{"focal_length_hint_px": f, "optics_from": text}`` from a Pillow image's EXIF for an image ``width`` x
    ``height`` pixels as stored, or ``{}`` when it names no usable lens (an unreadable EXIF block too: a
    photograph needs no lens to be solved)."""
    try:
        tags = image.getexif().get_ifd(EXIF_IFD)
    except Exception:  # noqa: BLE001 - Pillow raises many kinds for a corrupt EXIF block
        return {}
    f35 = _positive(tags.get(FOCAL_LENGTH_35MM))
    if f35 is not None:
        focal = f35 * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM
        return {"focal_length_hint_px": focal,
                "optics_from": f"{location}: EXIF FocalLengthIn35mmFilm {f35:g} mm"}
    f_mm = _positive(tags.get(FOCAL_LENGTH))
    per_unit = _positive(tags.get(FOCAL_PLANE_X_RESOLUTION))
    unit = _MM_PER_UNIT.get(_integer(tags.get(FOCAL_PLANE_RESOLUTION_UNIT), 2))
    if f_mm is None or per_unit is None or unit is None:
        return {}
    sensor_width = _positive(tags.get(PIXEL_X_DIMENSION)) or width
    focal = f_mm * per_unit / unit * width / sensor_width
    return {"focal_length_hint_px": focal,
            "optics_from": f"{location}: EXIF FocalLength {f_mm:g} mm at FocalPlaneXResolution {per_unit:g} "
                           f"px per {unit:g} mm"}


def _positive(value) -> float | None:
    """An EXIF number (an int, a rational) as a positive finite float, else None (0 is EXIF's "unknown")."""
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if math.isfinite(number) and number > 0 else None


def _integer(value, default: int) -> int:
    try:
        return int(value)
    except (TypeError, ValueError):
        return default
