"""In-memory form of a validated TUBSAT snapshot sequence.

Everything downstream (extraction, identification, storage) works on these
immutable objects; the parsers in :mod:`app.telemetry.formats` are the only
way to build one from untrusted bytes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime

import numpy as np

from app.camera import Camera
from app.catalogue import MEAN_PLACE
from app.timefmt import utc_text

FORMAT_NAME = "tubsat-snapshots/1"


@dataclass(frozen=True, eq=False)
class Snapshot:
    """One snapshot: the light sources the sensor reported at one instant.

    ``xy`` is (n, 2) pixel positions, ``brightness`` (n,), both in the order
    of the input file (sources are not sorted).
    """

    index: int
    time: datetime  # timezone-aware, UTC
    xy: np.ndarray
    brightness: np.ndarray

    @property
    def n_sources(self) -> int:
        return int(self.xy.shape[0])


@dataclass(frozen=True, eq=False)
class Sequence:
    """A "picture": a time-ordered sequence of snapshots from one camera."""

    sequence_id: str
    spacecraft: str | None
    camera: Camera
    snapshots: tuple[Snapshot, ...]
    # Optional spacecraft velocity w.r.t. the Earth's centre in GCRS, km/s,
    # used for the orbital part of stellar aberration.
    velocity_km_s: tuple[float, float, float] | None = None
    extra: dict = field(default_factory=dict)
    # True: the snapshot times are not known but assumed (frames that carried none: J2000.0 and 1 s
    # steps), so the stars are placed without aberration and planets are not looked for (:attr:`observer`).
    time_assumed: bool = False

    @property
    def times(self) -> list[datetime]:
        return [s.time for s in self.snapshots]

    @property
    def observer(self):
        """Whom the stars' places are made for, as the ``velocity_km_s`` argument of
        :meth:`app.catalogue.Catalogue.apparent_vectors`: the spacecraft's velocity (None: the Earth's
        centre), or :data:`app.catalogue.MEAN_PLACE` when the time is assumed: the aberration depends on
        the Earth's velocity at the real time, and an assumed one would add an error of up to 41"
        (twice 20.5"), where the mean place is off by at most the real aberration and is what star
        atlases and astrometry.net give."""
        return MEAN_PLACE if self.time_assumed else self.velocity_km_s

    def to_json_dict(self) -> dict:
        """The `tubsat-snapshots/1` JSON form of this sequence.

        Unknown top-level keys kept in ``extra`` are written back after the
        format's own keys, which always win.
        """
        doc = {
            "format": FORMAT_NAME,
            "sequence_id": self.sequence_id,
            "spacecraft": self.spacecraft,
            "camera": self.camera.to_dict(),
            "snapshots": [
                {
                    "index": s.index,
                    "time": utc_text(s.time),
                    "sources": [
                        {"x": float(x), "y": float(y), "brightness": float(b)}
                        for (x, y), b in zip(s.xy, s.brightness)
                    ],
                }
                for s in self.snapshots
            ],
        }
        if self.velocity_km_s is not None:
            doc["velocity_km_s"] = list(self.velocity_km_s)
        if self.time_assumed:
            doc["time_assumed"] = True
        for key, value in self.extra.items():
            doc.setdefault(key, value)
        return doc
