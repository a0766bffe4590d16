"""A recording in memory and on disk (docs/recorder.md §3): CSV with a `#` header of
metadata, or Parquet (pyarrow, the `parquet` extra) with the same metadata in its schema.

Columns: `cycle` (the GEO cycle the sample shows), `time_s` (cycle · cycle time), then
one per recorded value, labelled `NAME@axis` (`NAME` for machine-wide objects), in the
object's own unit (the value a read returns: increments, µm/m, …; booleans 0/1).
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geo_server.dictionary import round_half_away
from geo_server.errors import GeoError

MAGIC = "geo-server trace 1"
FIXED = ("cycle", "time_s")


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
        """Write by suffix: `.parquet` (pyarrow) or anything else as CSV."""
        p = Path(path)
        if p.suffix.lower() == ".parquet":
            _write_parquet(self, p)
        else:
            p.write_text(self.to_csv(), encoding="utf-8")
        return p

    def to_csv(self) -> str:
        buf = io.StringIO()
        buf.write(f"# {MAGIC}\n")
        for key, value in {**self.meta, **self._columns_meta()}.items():
            buf.write(f"# {key}: {value}\n")
        w = csv.writer(buf, lineterminator="\n")
        w.writerow([*FIXED, *self.labels])
        for row in self.rows():
            w.writerow([_cell(v) for v in row])
        return buf.getvalue()

    def _columns_meta(self) -> dict[str, str]:
        return {
            "types": json.dumps(self.types),
            "units": json.dumps(self.units, ensure_ascii=False),
        }


def _cell(v: Any) -> str:
    if isinstance(v, bool):
        return "1" if v else "0"
    return repr(v) if isinstance(v, float) else str(v)


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


def _write_parquet(trace: Trace, path: Path) -> None:
    pa, pq = _pyarrow()
    arrays = [pa.array(trace.cycles), pa.array(trace.data[:, 1])]
    arrays += [pa.array(trace.data[:, 2 + i]) for i in range(len(trace.labels))]
    meta = {"magic": MAGIC, **trace.meta, **trace._columns_meta()}
    schema_meta = {k.encode(): v.encode() for k, v in meta.items()}
    table = pa.Table.from_arrays(arrays, names=[*FIXED, *trace.labels])
    pq.write_table(table.replace_schema_metadata(schema_meta), path)


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
