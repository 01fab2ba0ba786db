"""What an input file is, by its name and its kind: the one rule for every interface.

The telemetry (``.json``, ``.csv``), the frames (FITS, PNG, JPEG, TIFF) and
their sidecars, the simulator's truth files that lie beside them and are
never telemetry, and the paths that are no files at all to read (a device,
a FIFO, a socket).  ``python -m app upload`` runs on machines with only the
standard library, so this module needs nothing else.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

#: Spot-list telemetry.
SPOT_LIST_SUFFIXES = (".json", ".csv")
#: Frames, by their file name's ending (lower case).
FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz", ".fit.gz")
PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
IMAGE_SUFFIXES = FITS_SUFFIXES + PICTURE_SUFFIXES
#: A folder of frames' sidecar; a single image's is ``<stem>.frames.json`` (:func:`image_sidecar`).
FOLDER_SIDECAR = "frames.json"
SIDECAR_SUFFIX = ".frames.json"
#: The simulator's answers beside its telemetry (``<id>.truth.json``): never telemetry.
TRUTH_SUFFIX = ".truth.json"
#: What a path that is neither a regular file nor a folder is, by its ``stat`` type, for the operator.
SPECIAL_FILES = ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                 (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"))


def special_file(path: str | os.PathLike) -> str | None:
    """What ``path`` is when it is neither a regular file nor a folder (``"a character device"``), else None
    (a symbolic link is what it points to; a missing path is None: it is reported when read).

    Taken from ``os.stat``, before the file is opened: a device or FIFO has no size to check against
    the limit (``st_size`` is 0), reading ``/dev/zero`` never ends, and opening a FIFO waits for a
    writer that may never come.
    """
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    return next((kind for is_kind, kind in SPECIAL_FILES if is_kind(mode)), None)


def passes_of_folder(entries: list[Path]) -> list[list[Path]]:
    """The passes of frames among a folder's files (``entries``, in name order): all its images as one pass when
    it holds a ``frames.json`` or only FITS frames (a camera's pass: FITS carry their times), else each picture a
    pass of its own (photographs kept together, as ``solve a.jpg b.jpg`` and the console take them: two skies read
    as one pass made every star a ghost, and a folder of unrelated photographs no match at all)."""
    images = [p for p in entries if p.name.lower().endswith(IMAGE_SUFFIXES)]
    if not images:
        return []
    if any(p.name == FOLDER_SIDECAR for p in entries) or all(p.name.lower().endswith(FITS_SUFFIXES) for p in images):
        return [images]
    return [[p] for p in images]


def image_sidecars(entries: list[Path]) -> set[Path]:
    """The ``<stem>.frames.json`` of each of ``entries``' images, present or not (read with their image, never as
    spot lists)."""
    return {image_sidecar(p) for p in entries if p.name.lower().endswith(IMAGE_SUFFIXES)}


def image_sidecar(image: Path) -> Path:
    """A single image's own sidecar, ``<stem>.frames.json`` beside it (the stem: the name less its image
    suffix, ``.fits.gz`` whole)."""
    base = image.name
    for suffix in sorted(IMAGE_SUFFIXES, key=len, reverse=True):
        if base.lower().endswith(suffix):
            base = base[: -len(suffix)]
            break
    return image.with_name(base + SIDECAR_SUFFIX)
