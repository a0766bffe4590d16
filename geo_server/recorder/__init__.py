"""Recorder and golden traces (docs/recorder.md): record chosen objects every N cycles
with a trigger, save and load traces (CSV, Parquet), record the machine's inputs, replay
them into a stepped run, and compare two traces with tolerances."""

from geo_server.recorder.compare import Comparison, compare, parse_tolerances
from geo_server.recorder.recorder import Recorder, RecordSpec
from geo_server.recorder.selection import Column, SelectionError, resolve_columns
from geo_server.recorder.trace import Trace, TraceFileError, load_trace

__all__ = [
    "Column",
    "Comparison",
    "RecordSpec",
    "Recorder",
    "SelectionError",
    "Trace",
    "TraceFileError",
    "compare",
    "load_trace",
    "parse_tolerances",
    "resolve_columns",
]
