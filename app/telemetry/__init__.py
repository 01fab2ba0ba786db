"""Telemetry: the `tubsat-snapshots/1` formats (JSON and CSV) and their validation."""

from app.telemetry.model import FORMAT_NAME, Sequence, Snapshot

__all__ = ["FORMAT_NAME", "Sequence", "Snapshot"]
