"""Extraction: tracked stars vs ghosts, hot pixels and outliers (issue 2, item 3).

``extract(sequence)`` links each source to the same star in the other
snapshots through the robustly estimated inter-snapshot rotation and
returns an :class:`Extraction`: per-source track ids or rejection reasons,
the tracks, the motion into the reference snapshot, and two patterns for
identification (the seed's reference-snapshot pattern and the better
averaged one).  ``build_pattern`` applies an operator's edits.

Modules: ``model`` (data classes and parameters), ``motion`` (robust
snapshot-to-snapshot rotation), ``tracking`` (the method, see its
docstring), ``pattern`` (patterns and the JSON form).
"""

from app.extraction.model import (GHOST, HOT_PIXEL, OUTLIER, REASONS, Extraction, ExtractionParameters,
                                  Pattern, Track)
from app.extraction.pattern import build_pattern, extraction_to_json, pattern_to_json
from app.extraction.tracking import extract

__all__ = ["GHOST", "HOT_PIXEL", "OUTLIER", "REASONS", "Extraction", "ExtractionParameters", "Pattern",
           "Track", "build_pattern", "extract", "extraction_to_json", "pattern_to_json"]
