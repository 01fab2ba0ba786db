"""Identification: from an extracted pattern to ranked attitude candidates.

``solve_sequence`` is the one function the CLI, the API and the benchmarks
call: extraction (unless given) -> pattern (unless given) -> identification
at the reference snapshot's time, with planets labelled.
"""

from __future__ import annotations

from dataclasses import dataclass

from app.extraction import Extraction, Pattern, extract
from app.identification.engine import SearchOptions, Sky, classify, identify
from app.identification.result import (AMBIGUOUS, IDENTIFIED, NO_MATCH, Candidate, PlanetMatch, Solution,
                                       StarMatch)
from app.telemetry import Sequence

__all__ = ["AMBIGUOUS", "IDENTIFIED", "NO_MATCH", "Candidate", "PlanetMatch", "SearchOptions", "Sky",
           "Solution", "SolvedSequence", "StarMatch", "classify", "identify", "solve_sequence"]


@dataclass(frozen=True, eq=False)
class SolvedSequence:
    sequence: Sequence
    extraction: Extraction
    pattern: Pattern
    solution: Solution

    @property
    def reference_time(self):
        return self.sequence.snapshots[self.extraction.reference].time


def solve_sequence(sequence: Sequence, sky: Sky, *, options: SearchOptions = SearchOptions(),
                   extraction: Extraction | None = None, pattern: Pattern | None = None,
                   with_planets: bool = True) -> SolvedSequence:
    """Extract (unless ``extraction`` is given) and identify ``pattern`` (default: the averaged one)."""
    from app.planets import planet_vectors

    extraction = extraction if extraction is not None else extract(sequence)
    pattern = pattern if pattern is not None else extraction.pattern
    t = sequence.snapshots[extraction.reference].time
    planets = planet_vectors(t) if with_planets else None
    solution = identify(pattern, sequence.camera, t, sky, velocity_km_s=sequence.velocity_km_s,
                        options=options, planets=planets)
    return SolvedSequence(sequence=sequence, extraction=extraction, pattern=pattern, solution=solution)
