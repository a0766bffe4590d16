"""Friction compensation (000 §4.5 p.64–79; docs/design.md §6.6): the value a cycle writes
into the delay line, written once for a single cycle (`Kernel.step`) and a pass of steady
cycles (`KernelBatch.run`).

The base value sign(v)·scaling_factor/1000·table(|v|) comes from the merged 1-D lookup
(`tables.interpolate`, a row per axis) times its factor in the target vector; `weigh`
applies the reversal weights. The tables of a load are `FrictionTables`, the delay line and
the path since the last reversal `FrictionState` (kept across reloads).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from geo_server.kernel.common import FRICT, VEL
from geo_server.model import AxisConfig

if TYPE_CHECKING:
    from geo_server.kernel.inputs import Gather, SourceVector

RING = 249  # friction delay line length: delay_cycles < 249 (000 p.79)


def _i64(values: list | np.ndarray) -> np.ndarray:
    return np.array(values, dtype=np.int64).reshape(-1)


def _f64(values: list | np.ndarray) -> np.ndarray:
    return np.array(values, dtype=float).reshape(-1)


@dataclass(slots=True, eq=False)
class FrictionState:
    """Friction (000 §4.5 p.64–79; docs/design.md §6.6) state kept across reloads: the
    delay line of every axis (one row per cycle; rows of axes without friction carry
    zeros, as in the reference's per-axis delay lines) and the path since the last
    reversal."""

    ring: np.ndarray  # [RING, n]
    ring_flat: np.ndarray
    ring_rows: list[np.ndarray]  # ring[i], for every write position i
    ring_pos: int
    path: np.ndarray
    dpos: np.ndarray  # |pos − previous pos|
    target: np.ndarray  # the friction column of the kernel's arrays (views)
    actual: np.ndarray
    effective: np.ndarray

    @classmethod
    def create(cls, target: np.ndarray, actual: np.ndarray, eff: np.ndarray) -> FrictionState:
        n = len(target)
        ring = np.zeros((RING, n))
        return cls(
            ring=ring,
            ring_flat=ring.reshape(-1),
            ring_rows=list(ring),
            ring_pos=0,
            path=np.full(n, np.inf),
            dpos=np.zeros(n),
            target=target[:, FRICT],
            actual=actual[:, FRICT],
            effective=eff[:, FRICT],
        )


@dataclass(frozen=True, slots=True, eq=False)
class FrictionTables:
    """Friction (000 §4.5 p.64–79; docs/design.md §6.6) parameters of one load.

    base = sign(v)·scaling_factor/1000·table(|v|) (the table is a row of the merged 1-D
    lookup; sign·scale is its factor in the target vector); weighted before a reversal by
    r/(lookahead + 1) (`wpre`, from the merged lookup) and after it by min(1, path /
    position_delay) (`wpost`); the output is the value written `delay_cycles` ago.
    """

    any: bool  # some axis has friction
    slots: np.ndarray
    scale: np.ndarray  # scaling_factor/1000
    sign: np.ndarray  # sign(v): a view of the gather's signs
    fac: np.ndarray  # sign·scale: a view of the target vector's factors
    wpre_in: np.ndarray  # pre-reversal weights: a view of the target vector
    wpre: np.ndarray  # [n], 1 on axes without friction
    pd: np.ndarray  # position_delay (0: no post-reversal weight)
    has_pd: np.ndarray
    any_pd: bool
    wpost: np.ndarray  # [n]
    ridx_rows: list[np.ndarray]  # per write position: read index of every axis
    rv: np.ndarray  # [n] scratch

    @classmethod
    def build(
        cls,
        axes: list[AxisConfig],
        rows: list[int],
        src: SourceVector,
        g: Gather,
        part: slice,
        fac: np.ndarray,
        wpre_in: np.ndarray,
    ) -> FrictionTables:
        n = len(axes)
        slots = _i64(rows)
        g.src[part] = src.index(VEL, slots)
        pd = np.zeros(n)
        delay = np.zeros(n, dtype=np.int64)
        for i in rows:
            fr = axes[i].comp.frict
            pd[i] = float(fr.position_delay)
            delay[i] = int(fr.delay_cycles)
        has_pd = pd > 0
        # read index of every axis for every write position: (pos − delay) mod RING
        pos = np.arange(RING)[:, None]
        ridx = ((pos - delay[None, :]) % RING) * n + np.arange(n)[None, :]
        return cls(
            any=bool(rows),
            slots=slots,
            scale=_f64([axes[i].comp.frict.scaling_factor / 1000.0 for i in rows]),
            sign=g.sign[part],
            fac=fac,
            wpre_in=wpre_in,
            wpre=np.ones(n),
            pd=pd,
            has_pd=has_pd,
            any_pd=bool(has_pd.any()),
            wpost=np.ones(n),
            ridx_rows=list(ridx),
            rv=np.zeros(n),
        )


def weigh(
    target: np.ndarray,
    wpre: np.ndarray | None,
    path: np.ndarray,
    pd: np.ndarray | None,
    has_pd: np.ndarray | None,
    wpost: np.ndarray,
    out: np.ndarray,
) -> None:
    """out = target × the pre-reversal weight r/(lookahead + 1) while 0 ≤ r ≤ lookahead
    (`wpre`, None when no axis has a friction table) × the post-reversal weight
    min(1, path / position_delay) (`pd`, None when no axis has a position delay), with
    `path` the path since the last reversal."""
    if wpre is not None:
        np.multiply(target, wpre, out)
    else:
        np.copyto(out, target)
    if pd is not None:
        np.divide(path, pd, wpost, where=has_pd)
        np.minimum(wpost, 1.0, out=wpost)
        np.multiply(out, wpost, out)
