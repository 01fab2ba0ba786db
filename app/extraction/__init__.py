"""Extraction: tracked stars vs ghosts, hot pixels and outliers.

``extract(sequence)`` links each source to the same star in the other
snapshots through the robustly estimated inter-snapshot rotation and
returns an :class:`Extraction`: per-source track ids or rejection reasons,
the tracks, the motion into the reference snapshot, and two patterns for
identification (the seed's reference-snapshot pattern and the better
averaged one).  ``build_pattern`` applies an operator's edits.

Modules: ``model`` (data classes and parameters), ``motion`` (robust
snapshot-to-snapshot rotation), ``linking`` (the method: sources linked into
tracks, see its docstring), ``pattern`` (patterns from tracks).
"""

from app.extraction.linking import extract
from app.extraction.model import (DEFAULT_SIGHTING_SIGMA_PX, EXTRACTION_VERSION, GHOST, HOT_PIXEL, OUTLIER, REASONS, Extraction,
                                  ExtractionParameters, Pattern, Track, assumed_sighting_noise_px)
from app.extraction.pattern import (PatternError, build_pattern, carried_tracks, describe_track_ids, seed_pattern,
                                    tracks_pattern, unknown_tracks)

__all__ = ["DEFAULT_SIGHTING_SIGMA_PX", "EXTRACTION_VERSION", "GHOST", "HOT_PIXEL", "OUTLIER", "REASONS", "Extraction", "ExtractionParameters",
           "Pattern", "PatternError", "Track", "assumed_sighting_noise_px", "build_pattern", "carried_tracks", "describe_track_ids", "extract",
           "seed_pattern", "tracks_pattern", "unknown_tracks"]
