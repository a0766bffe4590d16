"""ISO 230-2:2014 evaluation of a bidirectional positioning test (pure functions).

The test (ISO 230-2:2014 §4, standard test cycle) approaches every target position P_i
(i = 1 … m) n times from below (↑) and n times from above (↓); each approach j gives the
positioning deviation x_ij = P_ij − P_i, actual position reached minus target position
(§2.5). This module takes those deviations and computes the parameters of §2.10 … §2.24
the way §5 (evaluation of results) and §7 (presentation of results) ask for them, and
derives target positions and the rows of a reference measurement for the PLC temperature
client (`geo_clients.plc_tempcomp`). What a commissioning makes of a test (LSEC table,
backlash) depends on the axis' parameters and lives in `geo_server.twin.measure`.

Units: target positions in mm (linear axes) or ° (rotary axes); deviations in µm, on
rotary axes in the twin's error unit 0.001° (`geo_server.twin.model`): both are ten CNC
increments, so columns named `_um` carry 0.001° on a rotary axis.

Per target position i (arrays of length m, ISO 230-2:2014 §2.10 … §2.17):

    x̄_i↑ = (1/n) Σ_j x_ij↑                     mean unidirectional positioning deviation (§2.10)
    x̄_i  = (x̄_i↑ + x̄_i↓) / 2                   mean bidirectional positioning deviation (§2.11)
    B_i  = x̄_i↑ − x̄_i↓                          reversal value (§2.12)
    s_i↑ = √( 1/(n−1) Σ_j (x_ij↑ − x̄_i↑)² )     estimator of the unidirectional standard
                                                uncertainty of positioning (§2.15)
    R_i↑ = 4 s_i↑                               unidirectional repeatability (§2.16)
    R_i  = max(2 s_i↑ + 2 s_i↓ + |B_i|; R_i↑; R_i↓)   bidirectional repeatability (§2.17)

(↓ likewise.) Of the axis (§2.13, §2.14, §2.18 … §2.24):

    B  = max |B_i|            reversal value of the axis (§2.13)
    B̄  = (1/m) Σ B_i          mean reversal value of the axis (§2.14), signed
    R↑ = max R_i↑, R↓ = max R_i↓, R = max R_i             repeatability (§2.18, §2.19)
    E↑ = max x̄_i↑ − min x̄_i↑, E↓ likewise                 unidirectional systematic
                                                          positioning error (§2.20)
    E  = max(x̄_i↑; x̄_i↓) − min(x̄_i↑; x̄_i↓)              bidirectional (§2.21)
    M  = max x̄_i − min x̄_i                                mean bidirectional
                                                          positioning error (§2.22)
    A↑ = max(x̄_i↑ + 2 s_i↑) − min(x̄_i↑ − 2 s_i↑), A↓ likewise   unidirectional
                                                          accuracy of positioning (§2.23)
    A  = max(x̄_i↑ + 2 s_i↑; x̄_i↓ + 2 s_i↓) − min(x̄_i↑ − 2 s_i↑; x̄_i↓ − 2 s_i↓)
                                                          bidirectional accuracy (§2.24)

`Evaluation` names its fields in words (`accuracy` for A, `reversal_i` for B_i, …);
`FIGURES` and `PER_TARGET` map each field to its symbol, name and clause.

The factor 2 is the coverage factor k = 2 of the expanded uncertainty (§2.8, §2.9).
Only the repeated test is evaluated (n ≥ 2 runs); the single-run test of long axes
(§5.2: linear axes over 2000 mm, rotary axes over 360°) has no estimator s.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: The edition every formula of this module follows.
STANDARD = "ISO 230-2:2014"

#: Header of the reference-measurement CSV that `geo_clients.plc_tempcomp` reads (its
#: measured-points form: positions in mm, deviations in µm, see `reference_rows`).
REFERENCE_HEADER = ("axis", "temperature_C", "position_mm", "deviation_um")

#: Header of the raw deviations CSV (`deviations_csv`).
DEVIATIONS_HEADER = ("run", "direction", "target_index", "target", "deviation_um")

FloatArray = NDArray[np.float64]

#: The axis figures in presentation order: (field, symbol, name, clause).
FIGURES: tuple[tuple[str, str, str, str], ...] = (
    ("accuracy_up", "A↑", "unidirectional accuracy of positioning, positive", "§2.23"),
    ("accuracy_down", "A↓", "unidirectional accuracy of positioning, negative", "§2.23"),
    ("accuracy", "A", "bidirectional accuracy of positioning", "§2.24"),
    ("repeatability_up", "R↑", "unidirectional repeatability of positioning, positive", "§2.18"),
    ("repeatability_down", "R↓", "unidirectional repeatability of positioning, negative", "§2.18"),
    ("repeatability", "R", "bidirectional repeatability of positioning", "§2.19"),
    ("systematic_up", "E↑", "unidirectional systematic positioning error, positive", "§2.20"),
    ("systematic_down", "E↓", "unidirectional systematic positioning error, negative", "§2.20"),
    ("systematic", "E", "bidirectional systematic positioning error", "§2.21"),
    ("mean_error", "M", "mean bidirectional positioning error", "§2.22"),
    ("reversal", "B", "reversal value", "§2.13"),
    ("mean_reversal", "B̄", "mean reversal value", "§2.14"),
)

#: The per-target arrays: (field, symbol, name, clause).
PER_TARGET: tuple[tuple[str, str, str, str], ...] = (
    ("mean_up", "x̄_i↑", "mean unidirectional positioning deviation, positive", "§2.10"),
    ("mean_down", "x̄_i↓", "mean unidirectional positioning deviation, negative", "§2.10"),
    ("mean", "x̄_i", "mean bidirectional positioning deviation", "§2.11"),
    ("reversal_i", "B_i", "reversal value", "§2.12"),
    ("s_up", "s_i↑", "estimator of the unidirectional standard uncertainty, positive", "§2.15"),
    ("s_down", "s_i↓", "estimator of the unidirectional standard uncertainty, negative", "§2.15"),
    ("repeatability_up_i", "R_i↑", "unidirectional repeatability, positive", "§2.16"),
    ("repeatability_down_i", "R_i↓", "unidirectional repeatability, negative", "§2.16"),
    ("repeatability_i", "R_i", "bidirectional repeatability", "§2.17"),
)


def _frozen(a: ArrayLike) -> FloatArray:
    out = np.array(a, dtype=np.float64)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class Evaluation:
    """The result of a bidirectional positioning test per ISO 230-2:2014 (module docstring).

    Arrays are read-only. Per target i: shape (m,); deviations x_ij: shape (n, m) with
    row j the run and column i the target. Axis figures are floats in the deviation unit
    (µm; 0.001° on rotary axes).
    """

    #: P_i, target positions (§2.3), strictly increasing; mm or °.
    targets: FloatArray
    #: x_ij↑, x_ij↓: positioning deviations (§2.5) of run j at target i, shape (n, m).
    up: FloatArray
    down: FloatArray
    #: x̄_i↑, x̄_i↓ (§2.10); x̄_i (§2.11).
    mean_up: FloatArray
    mean_down: FloatArray
    mean: FloatArray
    #: B_i = x̄_i↑ − x̄_i↓ (§2.12).
    reversal_i: FloatArray
    #: s_i↑, s_i↓ (§2.15), sample standard deviations (n − 1).
    s_up: FloatArray
    s_down: FloatArray
    #: R_i↑ = 4 s_i↑, R_i↓ = 4 s_i↓ (§2.16); R_i (§2.17).
    repeatability_up_i: FloatArray
    repeatability_down_i: FloatArray
    repeatability_i: FloatArray
    #: B = max |B_i| (§2.13); B̄ = mean of B_i, signed (§2.14).
    reversal: float
    mean_reversal: float
    #: R↑, R↓ (§2.18); R (§2.19).
    repeatability_up: float
    repeatability_down: float
    repeatability: float
    #: E↑, E↓ (§2.20); E (§2.21).
    systematic_up: float
    systematic_down: float
    systematic: float
    #: M (§2.22).
    mean_error: float
    #: A↑, A↓ (§2.23); A (§2.24).
    accuracy_up: float
    accuracy_down: float
    accuracy: float

    @property
    def n(self) -> int:
        """Number of runs (approaches per target and direction)."""
        return int(self.up.shape[0])

    @property
    def m(self) -> int:
        """Number of target positions."""
        return int(self.targets.shape[0])

    def figures(self) -> dict[str, float]:
        """The axis figures by field name (`FIGURES` order)."""
        return {name: float(getattr(self, name)) for name, *_ in FIGURES}

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: the standard, n, m, the targets, the axis figures, the standard's
        symbol of each field, the per-target values and the raw deviations (lists of
        floats; `deviations.up[j][i]` = x_ij↑)."""
        return {
            "standard": STANDARD,
            "n": self.n,
            "m": self.m,
            "targets": [float(p) for p in self.targets],
            "figures": self.figures(),
            "symbols": {name: symbol for name, symbol, *_ in (*FIGURES, *PER_TARGET)},
            "per_target": {
                name: [float(v) for v in getattr(self, name)] for name, *_ in PER_TARGET
            },
            "deviations": {
                "up": [[float(v) for v in row] for row in self.up],
                "down": [[float(v) for v in row] for row in self.down],
            },
        }

    def table_markdown(self, unit: str = "µm") -> str:
        """The axis figures as a Markdown table, one decimal, in `unit` (§7 presentation):
        one row per parameter, columns ↑, ↓ and bidirectional (↑↓)."""
        rows = (
            ("accuracy of positioning", "A", "§2.23, §2.24", "accuracy", True),
            ("repeatability of positioning", "R", "§2.18, §2.19", "repeatability", True),
            ("systematic positioning error", "E", "§2.20, §2.21", "systematic", True),
            ("mean bidirectional positioning error", "M", "§2.22", "mean_error", False),
            ("reversal value", "B", "§2.13", "reversal", False),
            ("mean reversal value", "B̄", "§2.14", "mean_reversal", False),
        )

        def cell(field: str) -> str:
            return f"{float(getattr(self, field)) + 0.0:.1f}"

        lines = [
            f"| parameter ({unit}) | symbol | {STANDARD} | ↑ | ↓ | ↑↓ |",
            "|---|---|---|---:|---:|---:|",
        ]
        for name, symbol, clause, field, directional in rows:
            up, down = (cell(field + "_up"), cell(field + "_down")) if directional else ("", "")
            lines.append(f"| {name} | {symbol} | {clause} | {up} | {down} | {cell(field)} |")
        return "\n".join(lines) + "\n"


def evaluate(targets: ArrayLike, up: ArrayLike, down: ArrayLike) -> Evaluation:
    """Evaluate a bidirectional positioning test by ISO 230-2:2014 §2.10 … §2.24 (formulas:
    module docstring).

    `targets`: P_i, shape (m,), finite and strictly increasing (mm or °). `up`, `down`:
    x_ij↑ and x_ij↓, shape (n, m) each with n ≥ 2 runs, deviation = actual − target (µm).
    Raises ValueError on other shapes or non-finite values.
    """
    p = np.asarray(targets, dtype=np.float64)
    xu = np.asarray(up, dtype=np.float64)
    xd = np.asarray(down, dtype=np.float64)
    if p.ndim != 1 or p.size < 1:
        raise ValueError(f"targets must be one-dimensional and not empty, got shape {p.shape}")
    m = p.size
    for name, x in (("up", xu), ("down", xd)):
        if x.ndim != 2 or x.shape[1] != m:
            raise ValueError(f"{name} deviations must have shape (n, {m}), got {x.shape}")
    if xu.shape != xd.shape:
        raise ValueError(f"up and down need the same number of runs: {xu.shape} vs {xd.shape}")
    if xu.shape[0] < 2:
        raise ValueError("the estimator s_i (ISO 230-2:2014 §2.15) needs n ≥ 2 runs")
    if not (np.isfinite(p).all() and np.isfinite(xu).all() and np.isfinite(xd).all()):
        raise ValueError("targets and deviations must be finite")
    if m > 1 and not (np.diff(p) > 0).all():
        raise ValueError("targets must be strictly increasing")

    xbar_up = xu.mean(axis=0)
    xbar_down = xd.mean(axis=0)
    s_up = xu.std(axis=0, ddof=1)
    s_down = xd.std(axis=0, ddof=1)
    xbar = (xbar_up + xbar_down) / 2
    b_i = xbar_up - xbar_down
    r_up_i = 4 * s_up
    r_down_i = 4 * s_down
    r_i = np.maximum.reduce([2 * s_up + 2 * s_down + np.abs(b_i), r_up_i, r_down_i])
    hi_up, lo_up = xbar_up + 2 * s_up, xbar_up - 2 * s_up
    hi_down, lo_down = xbar_down + 2 * s_down, xbar_down - 2 * s_down
    both = np.concatenate([xbar_up, xbar_down])
    return Evaluation(
        targets=_frozen(p),
        up=_frozen(xu),
        down=_frozen(xd),
        mean_up=_frozen(xbar_up),
        mean_down=_frozen(xbar_down),
        mean=_frozen(xbar),
        reversal_i=_frozen(b_i),
        s_up=_frozen(s_up),
        s_down=_frozen(s_down),
        repeatability_up_i=_frozen(r_up_i),
        repeatability_down_i=_frozen(r_down_i),
        repeatability_i=_frozen(r_i),
        reversal=float(np.abs(b_i).max()),
        mean_reversal=float(b_i.mean()),
        repeatability_up=float(r_up_i.max()),
        repeatability_down=float(r_down_i.max()),
        repeatability=float(r_i.max()),
        systematic_up=float(xbar_up.max() - xbar_up.min()),
        systematic_down=float(xbar_down.max() - xbar_down.min()),
        systematic=float(both.max() - both.min()),
        mean_error=float(xbar.max() - xbar.min()),
        accuracy_up=float(hi_up.max() - lo_up.min()),
        accuracy_down=float(hi_down.max() - lo_down.min()),
        accuracy=float(max(hi_up.max(), hi_down.max()) - min(lo_up.min(), lo_down.min())),
    )


def targets_iso(
    start: float,
    end: float,
    count: int,
    seed: int = 0,
    *,
    equidistant: bool = False,
    r_max: float | None = None,
    decimals: int | None = 3,
) -> FloatArray:
    """Target positions P_i, i = 1 … m (`count`), over the measurement travel [start, end].

    ISO 230-2:2014 §4.2 (selection of target positions): P_i = (i − 1)·p + r, with p the
    interval of a uniform spacing over the measurement travel and r a different random
    value at each target, so that periodic errors (screw pitch, scale pitch) are not all
    sampled at the same phase. Here r is uniform in [−r_max, +r_max] (default r_max = p/4,
    at most < p/2 so the targets keep their order), drawn from `numpy.random.default_rng
    (seed)`: the same seed gives the same targets. The first and last target stay at
    `start` and `end` (r = 0): they delimit the measurement travel (§2.2).

    `equidistant=True`: r = 0 everywhere, P_i = start + (i − 1)·p, for an equidistant LSEC
    table at fixed spacing. `decimals`: targets rounded to this many decimals (default 3:
    1 µm, 0.001°), None keeps them unrounded. ISO 230-2:2014 §4.3 asks for at least five
    targets per metre and five overall on linear axes up to 2000 mm; that is the caller's.
    """
    if count < 2:
        raise ValueError("at least two target positions are needed")
    if not (math.isfinite(start) and math.isfinite(end)) or end <= start:
        raise ValueError(f"need finite start < end, got {start} … {end}")
    p = (end - start) / (count - 1)
    i = np.arange(count, dtype=np.float64)
    r = np.zeros(count)
    if not equidistant:
        bound = p / 4 if r_max is None else float(r_max)
        if not 0 <= bound < p / 2:
            raise ValueError(f"r_max must be in [0, p/2) = [0, {p / 2:g}), got {bound:g}")
        rng = np.random.default_rng(seed)
        r[1:-1] = rng.uniform(-bound, bound, count - 2)
    out = start + i * p + r
    out[0], out[-1] = start, end
    if decimals is not None:
        out = np.round(out, decimals)
    out.setflags(write=False)
    return out


# ============================================================================ writers


def _num(v: float, decimals: int) -> str:
    """`v` with at most `decimals` decimals, trailing zeros dropped, no '-0'."""
    text = f"{round(v, decimals) + 0.0:.{decimals}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return "0" if text == "-0" else text


def deviations_csv(evaluation: Evaluation) -> str:
    """The raw deviations x_ij↑, x_ij↓ (ISO 230-2:2014 §2.5) as CSV text.

    Columns `run, direction, target_index, target, deviation_um`: run j = 1 … n,
    direction `+` (↑) or `-` (↓), target index i = 1 … m, target P_i (mm or °), deviation
    actual − target (µm). Rows in the order of the standard test cycle: per run the targets
    ascending moving positive, then descending moving negative.
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(DEVIATIONS_HEADER)
    m = evaluation.m
    for j in range(evaluation.n):
        for direction, x, order in (
            ("+", evaluation.up, range(m)),
            ("-", evaluation.down, range(m - 1, -1, -1)),
        ):
            for i in order:
                w.writerow(
                    [j + 1, direction, i + 1, _num(evaluation.targets[i], 6), _num(x[j, i], 4)]
                )
    return buf.getvalue()


def reference_rows(
    axis: int, temperature_C: float, evaluation: Evaluation
) -> list[tuple[int, float, float, float]]:
    """Rows `(axis, temperature_C, position_mm, deviation_um)` of a reference measurement
    (TF5200 manual 000 §3.2) for `geo_clients.plc_tempcomp` (`REFERENCE_HEADER`).

    One row per target: position P_i and deviation −x̄_i, the negative of the mean
    bidirectional positioning deviation (ISO 230-2:2014 §2.11), because that file's
    `deviation` is what the compensation must ADD at the position (the client's
    convention), while x̄_i is actual − target. On a rotary axis the same columns carry °
    and 0.001° (both are 10⁴ and 10 increments, as the client scales them).
    """
    return [
        (int(axis), float(temperature_C), float(p), -float(x) + 0.0)
        for p, x in zip(evaluation.targets, evaluation.mean, strict=True)
    ]


def reference_csv(
    rows: Iterable[tuple[int, float, float, float]], comments: Sequence[str] = ()
) -> str:
    """CSV text of reference rows (`reference_rows`, any number of axes and temperatures)
    under `REFERENCE_HEADER`, `comments` first as `#` lines."""
    buf = io.StringIO()
    for c in comments:
        buf.write(f"# {c}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(REFERENCE_HEADER)
    for axis, temp, pos, dev in rows:
        w.writerow([axis, _num(temp, 6), _num(pos, 6), _num(dev, 4)])
    return buf.getvalue()


__all__ = [
    "DEVIATIONS_HEADER",
    "FIGURES",
    "PER_TARGET",
    "REFERENCE_HEADER",
    "STANDARD",
    "Evaluation",
    "deviations_csv",
    "evaluate",
    "reference_csv",
    "reference_rows",
    "targets_iso",
]
