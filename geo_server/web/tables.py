"""Every configured compensation table of a machine in engineering units, as the web HMI
draws it (`GET /api/tables`, docs/web.md §2): curves for LSEC, cross and friction, grids
for the plane compensation and crosstalk mode 3.

Positions are in mm (° on a rotary axis), corrections in µm (°), friction velocities in
mm/s (°/s) (docs/design.md §3). Crosstalk mode 3 is sampled on a grid with the kernel's
own interpolation (`kernel.triangulation.evaluate`), so the map shows what the cycle
applies at the reference acceleration.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from geo_server.kernel.triangulation import Triangulation, evaluate, triangulate
from geo_server.model import (
    CROSSTALK_COLUMNS,
    CompList,
    CrossComp,
    CrosstalkComp,
    FrictComp,
    LsecComp,
    MachineConfig,
    PlaneComp,
)
from geo_server.units import UNITS_PER_MM, UNITS_PER_UM

#: crosstalk mode 3's correction columns as the page names them (000 §4.6)
COLUMN_TITLES = {
    "accelerate_dir_pos": "accelerating, + direction",
    "accelerate_dir_neg": "accelerating, − direction",
    "decelerate_dir_pos": "decelerating, + direction",
    "decelerate_dir_neg": "decelerating, − direction",
}
#: samples of the crosstalk mode-3 surface along its first / second master
SURFACE_SAMPLES = (48, 36)


class Units:
    """Engineering units of the axes of one machine."""

    def __init__(self, cfg: MachineConfig) -> None:
        self.cfg = cfg

    def rotary(self, axis: int) -> bool:
        return axis in self.cfg.axes and self.cfg.axes[axis].params.kind != "T"

    def name(self, axis: int) -> str:
        return self.cfg.axes[axis].params.name if axis in self.cfg.axes else f"axis {axis}"

    def pos_unit(self, axis: int) -> str:
        return "°" if self.rotary(axis) else "mm"

    def off_unit(self, axis: int) -> str:
        return "°" if self.rotary(axis) else "µm"

    def positions(self, v: Any) -> list[float]:
        """Positions (0.1 µm or 0.0001° increments) in mm or °."""
        return [round(float(x) / UNITS_PER_MM, 4) for x in np.ravel(v)]

    def offsets(self, axis: int, v: Any) -> list[float]:
        """Corrections of `axis`: µm on a linear axis, ° on a rotary one."""
        if self.rotary(axis):
            return [round(float(x) / UNITS_PER_MM, 5) for x in np.ravel(v)]
        return [round(float(x) / UNITS_PER_UM, 2) for x in np.ravel(v)]

    def master(self, prefix: str, axis: int) -> dict[str, Any]:
        """The fields naming the axis whose position marks the table (`x_…`, `y_…`)."""
        return {
            f"{prefix}_axis": axis,
            f"{prefix}_name": self.name(axis),
            f"{prefix}_unit": self.pos_unit(axis),
        }


def tables(cfg: MachineConfig, axes: tuple[int, ...]) -> list[dict[str, Any]]:
    """Every configured (valid) compensation table of `axes`, in the cycle's order."""
    u = Units(cfg)
    out: list[dict[str, Any]] = []
    for a in axes:
        comp = cfg.axes[a].comp
        if comp is not None:
            out.extend(_axis_tables(u, a, comp))
    return out


def _axis_tables(u: Units, a: int, comp: CompList) -> list[dict[str, Any]]:
    base = {"axis": a, "name": u.name(a)}
    found: list[dict[str, Any]] = []
    if comp.lsec is not None and comp.lsec.valid:
        found.append({**base, **_lsec(u, a, comp.lsec)})
    if comp.cross is not None and comp.cross.valid:
        found.append({**base, **_cross(u, a, comp.cross)})
    if comp.frict is not None and comp.frict.valid:
        found.append({**base, **_frict(u, a, comp.frict)})
    if comp.plane is not None and comp.plane.valid:
        found.append({**base, **_plane(u, a, comp.plane)})
    ct = comp.crosstalk
    if ct is not None and ct.valid and ct.dialect == "new" and ct.mode == 3 and len(ct.ax_1):
        found.append({**base, **_crosstalk(u, a, ct)})
    return found


def _lsec(u: Units, a: int, t: LsecComp) -> dict[str, Any]:
    """The measured leadscrew errors (the cycle applies their negative, 000 §4.4)."""
    series = (
        {"+ direction": u.offsets(a, t.pos), "− direction": u.offsets(a, t.neg)}
        if t.bilateral
        else {"error": u.offsets(a, t.pos)}
    )
    return {
        "kind": "lsec",
        "comp": "LSEC",
        "title": f"{u.name(a)} leadscrew error (LSEC)",
        "x": u.positions(t.setpoint),
        **u.master("x", a),
        "series": series,
        "y_label": f"measured error [{u.off_unit(a)}]",
    }


def _cross(u: Units, a: int, t: CrossComp) -> dict[str, Any]:
    m = t.master_ax_nr
    return {
        "kind": "cross",
        "comp": "CROSS",
        "title": f"{u.name(a)} cross compensation over {u.name(m)} (CROSSC)",
        "x": u.positions(t.setpoint),
        **u.master("x", m),
        "series": {"correction": u.offsets(a, t.correction)},
        "y_label": f"correction of {u.name(a)} [{u.off_unit(a)}]",
    }


def _frict(u: Units, a: int, t: FrictComp) -> dict[str, Any]:
    """Additive current over |velocity| (velocities in µm/s or 0.001°/s, 000 §4.5)."""
    return {
        "kind": "frict",
        "comp": "FRICT",
        "title": f"{u.name(a)} friction compensation (FRICT)",
        "x": [round(float(v) / 1000.0, 4) for v in t.vin],
        "x_axis": a,
        "x_name": f"|v| {u.name(a)}",
        "x_unit": u.pos_unit(a) + "/s",
        "series": {"additive current": [float(v) for v in t.out]},
        "y_label": "current [drive units]",
    }


def _plane(u: Units, a: int, p: PlaneComp) -> dict[str, Any]:
    """The grid nodes; the cycle interpolates bilinearly between them (000 §4.3)."""
    ny, nx = p.table.shape
    m1, m2 = p.master1_ax_nr, p.master2_ax_nr
    return {
        "kind": "plane",
        "comp": "PLANE",
        "title": f"{u.name(a)} plane compensation over {u.name(m1)}/{u.name(m2)} (CC2)",
        **u.master("x", m1),
        **u.master("y", m2),
        "x": u.positions(p.start_position_master1 + p.interval1 * np.arange(nx)),
        "y": u.positions(p.start_position_master2 + p.interval2 * np.arange(ny)),
        "layers": {"correction": [u.offsets(a, row) for row in p.table]},
        "z_unit": u.off_unit(a),
    }


def _crosstalk(u: Units, a: int, ct: CrosstalkComp) -> dict[str, Any]:
    """The test points and their four corrections, and each column's surface sampled
    on a grid over the points' bounding box (000 §4.6 p.84)."""
    corr = np.atleast_2d(np.asarray(ct.corrections, dtype=float))
    n = min(len(ct.ax_1), len(ct.ax_2), corr.shape[0])
    px, py = np.asarray(ct.ax_1[:n], float), np.asarray(ct.ax_2[:n], float)
    tri = triangulate(tuple(zip(px.tolist(), py.tolist(), strict=True)))
    gx = np.linspace(px.min(), px.max(), SURFACE_SAMPLES[0])
    gy = np.linspace(py.min(), py.max(), SURFACE_SAMPLES[1])
    names = [COLUMN_TITLES[c] for c in CROSSTALK_COLUMNS]
    m1, m2 = ct.master_pos1_ax_nr, ct.master_pos2_ax_nr
    return {
        "kind": "crosstalk",
        "comp": "CROSSTALK",
        "title": f"{u.name(a)} crosstalk mode 3 over {u.name(m1)}/{u.name(m2)}",
        **u.master("x", m1),
        **u.master("y", m2),
        "x": u.positions(gx),
        "y": u.positions(gy),
        "layers": {
            name: [u.offsets(a, _surface_row(tri, corr[:n, c], gx, y)) for y in gy]
            for c, name in enumerate(names)
        },
        "points": {
            "x": u.positions(px),
            "y": u.positions(py),
            "layers": {name: u.offsets(a, corr[:n, c]) for c, name in enumerate(names)},
        },
        "z_unit": u.off_unit(a),
    }


def _surface_row(tri: Triangulation, values: np.ndarray, xs: np.ndarray, y: float) -> list[float]:
    v = values.tolist()
    return [evaluate(tri, v, float(x), float(y)) for x in xs]
