"""Telemetry: the `tubsat-snapshots/1` formats (JSON and CSV) and their validation."""

from app.telemetry.errors import Problem, TelemetryError
from app.telemetry.formats import dump_csv, dump_json, load_telemetry_file, parse_telemetry
from app.telemetry.model import FORMAT_NAME, Sequence, Snapshot

__all__ = ["FORMAT_NAME", "Problem", "Sequence", "Snapshot", "TelemetryError", "dump_csv",
           "dump_json", "load_telemetry_file", "parse_telemetry"]
