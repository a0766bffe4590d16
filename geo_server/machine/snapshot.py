"""Moved to `geo_server.snapshot` (kept while the transports are being moved)."""

from geo_server.snapshot import ObjectLayout, Snapshot, to_python

__all__ = ["ObjectLayout", "Snapshot", "to_python"]
