"""One compensation's model as the compiled law reads it (`geo_server.volcomp.law`).

`Evaluator` packs a `VolModel` once (`law.pack`) and is the Python face of the compiled
law: `correction_one` for one position, `correction` and `forward` for many (the same
compiled functions in a loop — no second copy of the law). The GEO cycle does not go
through this class: `geo_server.volcomp.step` reads the packed arrays of every
compensation of a machine directly. The plain reference (`geo_server.volcomp.reference`)
is the oracle both are tested against.
"""

from __future__ import annotations

import numpy as np

from geo_server.volcomp import law
from geo_server.volcomp.law import STEPS
from geo_server.volcomp.model import VolModel


class Evaluator:
    """The packed model of one compensation and its law at programmed positions."""

    def __init__(self, model: VolModel) -> None:
        self.model = model
        self.n = len(model.chain)
        #: the model's floats and integers (`law.pack`)
        self.tf, self.ti = law.pack(model)

    def correction_one(self, q: list[float], tip: tuple[float, float, float]) -> list[float]:
        """[Δx, Δy, Δz] (mm) at one programmed position (chain order, mm and °) for the
        tool point `tip` (mm, in the frame of the last axis)."""
        out = np.zeros(3)
        law.correction(
            self.tf, self.ti, 0, 0, np.asarray(q, dtype=float), tip[0], tip[1], tip[2], out
        )
        return [float(out[0]), float(out[1]), float(out[2])]

    def correction(self, q: np.ndarray, tip: np.ndarray) -> np.ndarray:
        """[b, 3] Δx, Δy, Δz (mm) at programmed positions q [b, n] (mm, °)."""
        q = np.ascontiguousarray(q, dtype=float).reshape(-1, self.n)
        out = np.zeros((q.shape[0], 3))
        law.corrections(self.tf, self.ti, q, np.asarray(tip, dtype=float).reshape(3), out)
        return out

    def forward(self, q: np.ndarray, tip: np.ndarray, errors: bool = True) -> np.ndarray:
        """[b, 3] tool tip relative to the workpiece at model positions q [b, n] (IDk
        included), on the imperfect machine (`errors`) or the ideal one."""
        q = np.ascontiguousarray(q, dtype=float).reshape(-1, self.n)
        out = np.zeros((q.shape[0], 3))
        law.forwards(self.tf, self.ti, q, np.asarray(tip, dtype=float).reshape(3), errors, out)
        return out


__all__ = ["STEPS", "Evaluator"]
