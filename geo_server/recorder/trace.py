"""A recording in memory and on disk (docs/recorder.md §3): CSV with a `#` header of
metadata, or Parquet (pyarrow, the `parquet` extra) with the same metadata in its schema.

Columns: `cycle` (the GEO cycle the sample shows), `time_s` (cycle · cycle time), then
one per recorded value, labelled `NAME@axis` (`NAME` for machine-wide objects), in the
object's own unit (the value a read returns: increments, µm/m, …; booleans 0/1).

Files are written by `TraceWriter`, piece by piece (a recording streams its rows while it
records, docs/recorder.md §8), into a temporary file beside the target that replaces it
atomically at the end (`listfile.writer.AtomicFile`, as `save` replaces a list): a crash
leaves the old file or the whole new one.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geo_server.dictionary import round_half_away
from geo_server.errors import GeoError
from geo_server.listfile.writer import AtomicFile

MAGIC = "geo-server trace 1"
FIXED = ("cycle", "time_s")
#: Rows formatted at once when a whole trace is saved (bounds the text held in memory).
SAVE_ROWS = 4096


class TraceFileError(GeoError, ValueError):
    """A trace file that cannot be read: file, line and what is wrong."""


@dataclass
class Trace:
    """`data[row] = (cycle, time_s, value…)`; `types[i]`/`units[i]` of value column i."""

    labels: list[str]
    data: np.ndarray
    types: list[str] = field(default_factory=list)
    units: list[str] = field(default_factory=list)
    meta: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.types = self.types or ["REAL64"] * len(self.labels)
        self.units = self.units or [""] * len(self.labels)

    def __len__(self) -> int:
        return int(self.data.shape[0])

    @property
    def cycles(self) -> np.ndarray:
        return self.data[:, 0].astype(np.int64)

    def column(self, label: str) -> np.ndarray:
        """The values of one column (KeyError names the known ones)."""
        if label not in self.labels:
            raise KeyError(f"no column {label!r} (columns: {', '.join(self.labels)})")
        return self.data[:, 2 + self.labels.index(label)]

    def value(self, label: str, row: int) -> Any:
        """One value as a reader of the object sees it (bool, int or float)."""
        v = float(self.column(label)[row])
        t = self.types[self.labels.index(label)]
        if t == "BOOLEAN":
            return bool(v)
        return v if t == "REAL64" else round_half_away(v)

    def rows(self) -> list[list[Any]]:
        """Every row with typed values (cycle int, time_s float, then each column)."""
        out = []
        for r in range(len(self)):
            out.append(
                [int(self.data[r, 0]), float(self.data[r, 1])]
                + [self.value(lab, r) for lab in self.labels]
            )
        return out

    # ------------------------------------------------------------------ files

    def save(self, path: str | Path) -> Path:
        """Write by suffix: `.parquet` (pyarrow) or anything else as CSV; atomically
        (a temporary file beside `path` replaces it once complete)."""
        p = Path(path)
        w = TraceWriter(p, self.labels, self.types, self.units)
        try:
            for start in range(0, len(self), SAVE_ROWS):
                w.write(self.data[start : start + SAVE_ROWS], self.meta)
            w.commit(self.meta)
        except BaseException:
            w.abort()
            raise
        return p

    def to_csv(self) -> str:
        return csv_header(self.labels, self.types, self.units, self.meta) + format_rows(
            self.data, self.types
        )


def _columns_meta(types: list[str], units: list[str]) -> dict[str, str]:
    return {"types": json.dumps(types), "units": json.dumps(units, ensure_ascii=False)}


def csv_header(labels: list[str], types: list[str], units: list[str], meta: dict[str, str]) -> str:
    """The `#` lines and the header row of a CSV trace."""
    buf = io.StringIO()
    buf.write(f"# {MAGIC}\n")
    for key, value in {**meta, **_columns_meta(types, units)}.items():
        buf.write(f"# {key}: {value}\n")
    csv.writer(buf, lineterminator="\n").writerow([*FIXED, *labels])
    return buf.getvalue()


def format_rows(data: np.ndarray, types: list[str]) -> str:
    """CSV lines of `data` (cycle, time_s, values), each value as `Trace.value` gives it
    (booleans 0/1, integers rounded half away from zero, REAL64 in `repr`), formatted
    column by column: numbers never need quoting."""
    if not len(data):
        return ""
    cols: list[list[str]] = [
        [str(c) for c in data[:, 0].astype(np.int64).tolist()],
        [repr(t) for t in data[:, 1].tolist()],
    ]
    cols += [_format_column(data[:, 2 + i], t) for i, t in enumerate(types)]
    return "".join(",".join(row) + "\n" for row in zip(*cols, strict=True))


def _format_column(v: np.ndarray, type_name: str) -> list[str]:
    if type_name == "BOOLEAN":
        return ["1" if x else "0" for x in (v != 0).tolist()]
    if type_name == "REAL64":
        return [repr(x) for x in v.tolist()]
    if not np.isfinite(v).all():  # (not from a recording: a hand-made Trace)
        return [str(round_half_away(x)) if math.isfinite(x) else repr(x) for x in v.tolist()]
    rounded = np.copysign(np.floor(np.abs(v) + 0.5), v).astype(np.int64)
    return [str(x) for x in rounded.tolist()]


class TraceWriter:
    """A trace file written in pieces (docs/recorder.md §3, §8): `write` appends rows
    (CSV lines, or a Parquet row group each), `commit` puts the file in place atomically,
    `abort` removes it. The header (the metadata) is written with the first rows, so
    what is known only when the trigger fires is in it. `path` must be a writable place
    the caller has checked (a recording: `recorder.paths`)."""

    def __init__(self, path: Path, labels: list[str], types: list[str], units: list[str]) -> None:
        self.path = path
        self.labels, self.types, self.units = labels, types, units
        self.rows = 0
        self._parquet = path.suffix.lower() == ".parquet"
        self._pq: Any = None
        self._started = False
        if self._parquet:
            _pyarrow()  # refused before a file is made when pyarrow is missing
        self._file = AtomicFile(path)

    def _start(self, meta: dict[str, str]) -> None:
        self._started = True
        if not self._parquet:
            self._file.fh.write(csv_header(self.labels, self.types, self.units, meta).encode())
            return
        pa, pq = _pyarrow()
        full = {"magic": MAGIC, **meta, **_columns_meta(self.types, self.units)}
        fields = [pa.field("cycle", pa.int64()), pa.field("time_s", pa.float64())]
        fields += [pa.field(label, pa.float64()) for label in self.labels]
        schema = pa.schema(fields, metadata={k.encode(): v.encode() for k, v in full.items()})
        self._pq = pq.ParquetWriter(self._file.fh, schema)

    def write(self, data: np.ndarray, meta: dict[str, str]) -> None:
        """Append `data` (typed rows: cycle, time_s, values); `meta` is used by the first
        call only."""
        if not self._started:
            self._start(meta)
        if not len(data):
            return
        if self._parquet:
            pa, _pq = _pyarrow()
            arrays = [pa.array(data[:, 0].astype(np.int64)), pa.array(data[:, 1])]
            arrays += [pa.array(data[:, 2 + i]) for i in range(len(self.labels))]
            self._pq.write_table(pa.Table.from_arrays(arrays, schema=self._pq.schema))
        else:
            self._file.fh.write(format_rows(data, self.types).encode())
        self.rows += len(data)

    def commit(self, meta: dict[str, str]) -> None:
        if not self._started:
            self._start(meta)
        if self._pq is not None:
            self._pq.close()
        self._file.commit()

    def abort(self) -> None:
        if self._pq is not None:
            with contextlib.suppress(Exception):
                self._pq.close()
        self._file.abort()


def load_trace(path: str | Path) -> Trace:
    """Read a trace written by `Trace.save` (CSV or Parquet)."""
    p = Path(path)
    if p.suffix.lower() == ".parquet":
        return _read_parquet(p)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise TraceFileError(f"{p}: cannot read: {exc}") from None
    return parse_csv(text, str(p))


def parse_csv(text: str, where: str = "<trace>") -> Trace:
    lines = text.splitlines()
    if not lines or lines[0] != f"# {MAGIC}":
        raise TraceFileError(f"{where}:1: not a geo-server trace (expected '# {MAGIC}')")
    meta: dict[str, str] = {}
    n = 1
    while n < len(lines) and lines[n].startswith("#"):
        key, sep, value = lines[n][1:].strip().partition(":")
        if not sep:
            raise TraceFileError(f"{where}:{n + 1}: metadata line without 'key: value'")
        meta[key.strip()] = value.strip()
        n += 1
    if n >= len(lines):
        raise TraceFileError(f"{where}:{n + 1}: no header row")
    header = next(csv.reader([lines[n]]))
    if tuple(header[:2]) != FIXED:
        raise TraceFileError(f"{where}:{n + 1}: the header must start with cycle,time_s")
    labels = header[2:]
    rows = []
    for k, line in enumerate(lines[n + 1 :], start=n + 2):
        if not line.strip():
            continue
        cells = next(csv.reader([line]))
        if len(cells) != len(header):
            raise TraceFileError(f"{where}:{k}: {len(cells)} cells, the header has {len(header)}")
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            bad = next(c for c in cells if not _is_number(c))
            raise TraceFileError(f"{where}:{k}: {bad!r} is not a number") from None
    types, units = _columns(meta, len(labels), where)
    data = np.array(rows, dtype=float).reshape(len(rows), len(header))
    return Trace(labels, data, types, units, meta)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _columns(meta: dict[str, str], n: int, where: str) -> tuple[list[str], list[str]]:
    try:
        types = json.loads(meta.pop("types", "[]")) or ["REAL64"] * n
        units = json.loads(meta.pop("units", "[]")) or [""] * n
    except ValueError:
        raise TraceFileError(f"{where}: types/units metadata is not JSON") from None
    if len(types) != n or len(units) != n:
        raise TraceFileError(f"{where}: types/units name {len(types)} columns, there are {n}")
    return [str(t) for t in types], [str(u) for u in units]


# ---------------------------------------------------------------------- Parquet


def _pyarrow() -> Any:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise TraceFileError(
            "Parquet needs pyarrow: pip install 'geo-server[parquet]' (or save as .csv)"
        ) from None
    return pa, pq


def _read_parquet(path: Path) -> Trace:
    pa, pq = _pyarrow()
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowInvalid) as exc:
        raise TraceFileError(f"{path}: cannot read Parquet: {exc}") from None
    raw = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
    if raw.pop("magic", "") != MAGIC:
        raise TraceFileError(f"{path}: not a geo-server trace (no '{MAGIC}' metadata)")
    names = table.column_names
    if tuple(names[:2]) != FIXED:
        raise TraceFileError(f"{path}: the columns must start with cycle,time_s")
    labels = names[2:]
    types, units = _columns(raw, len(labels), str(path))
    data = np.column_stack([table.column(c).to_numpy().astype(float) for c in names])
    return Trace(labels, data.reshape(table.num_rows, len(names)), types, units, raw)
