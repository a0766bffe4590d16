"""The volumetric model evaluated plainly: the oracle the kernel is tested against.

docs/volumetric.md §2 defines the model; this module is that text in code, one 4×4
homogeneous matrix per axis, no shortcut:

- small rotations (the angular errors, rad) are Ω(a, b, c) = I + [(a, b, c)]×, the
  first-order rigid-body matrix of ISO 230-1 (its Annex on error motions), so the model is
  the same whatever the order of the three angles;
- a linear axis at q (mm): p ↦ s·q·Ω(ε0)·u + δ(q) + Ω(ε(q))·p — its squareness ε0
  (A0k, B0k, C0k) tilts the direction of travel, its component errors shift (EXk, EYk,
  EZk) and tilt (EAk, EBk, ECk) the carriage;
- a rotary axis at θ (°), default model (004 p.16: "the rotation takes place around an
  ideal axis and afterwards the motion is subjected to location and component errors"):
  p ↦ c + δ0 + δ(θ) + Ω(ε0 + ε(θ))·Rot(u, s·θ)·(p − c);
  alternative model (`alternative_model 1`: "the main rotation actually takes place about
  a distorted axis"): u' = Ω(ε0)·u, c' = c + δ0, p ↦ c' + δ(θ) + Ω(ε(θ))·Rot(u', s·θ)·(p − c');
- the chain runs from the workpiece to the tool (004 p.13); the tool side is composed
  from the machine base outwards, the workpiece side likewise (its axes in reverse
  order), and the tool tip P0 + length·N0 (004 p.15) is expressed in the workpiece's
  frame: p = T_wp⁻¹ · T_tool · tip;
- the correction (004 p.8: "only compensates for tool position") moves the linear axes
  by Δ so that the imperfect machine puts the tool where the ideal one would:
  p_act(q + Δ) = p_nom(q), solved by Newton steps with the ideal machine's Jacobian.
"""

from __future__ import annotations

import math

import numpy as np

from geo_server.volcomp.model import AxisModel, VolModel
from geo_server.volcomp.tables import evaluate

#: the reference iterates until a Newton step is below this (mm)
TOLERANCE = 1e-13
MAX_STEPS = 50


def small_rotation(e: np.ndarray) -> np.ndarray:
    """Ω(e) = I + [e]×: the rotation by the small angles e (rad) about X, Y, Z."""
    a, b, c = (float(x) for x in e)
    return np.array([[1.0, -c, b], [c, 1.0, -a], [-b, a, 1.0]])


def rotation(u: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by `angle` (rad) about the unit vector `u` (Rodrigues)."""
    x, y, z = (float(v) for v in u)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def _homogeneous(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def _errors(model: VolModel, ax: AxisModel, point: dict[str, float]) -> tuple[np.ndarray, ...]:
    """δ (mm) and ε (rad) of `ax` at `point`: its component-error tables, 0 where none;
    then δ0 and ε0: its position errors, the constants and the tables over arguments
    (004 p.32: "typically (but not necessarily) constant")."""

    def value(name: str) -> float:
        table = model.tables.get(name)
        return 0.0 if table is None else evaluate(table, point)

    def varying(name: str) -> float:
        table = model.tables.get(name)
        return 0.0 if table is None or not table.arguments else evaluate(table, point)

    return (
        np.array([value(n) for n in ax.component("shift")]),
        np.array([value(n) for n in ax.component("tilt")]),
        ax.position_shift + np.array([varying(n) for n in ax.position("shift")]),
        ax.position_tilt + np.array([varying(n) for n in ax.position("tilt")]),
    )


def axis_transform(
    model: VolModel, ax: AxisModel, point: dict[str, float], errors: bool
) -> np.ndarray:
    """The 4×4 transform of one axis at `point` (model values: programmed + IDk)."""
    q = point[ax.letter]
    u = ax.direction
    if not errors:
        if not ax.rotary:
            return _homogeneous(np.eye(3), ax.sign * q * u)
        r = rotation(u, math.radians(ax.sign * q))
        return _homogeneous(r, ax.centre - r @ ax.centre)
    d, e, d0, e0 = _errors(model, ax, point)
    if not ax.rotary:
        return _homogeneous(small_rotation(e), ax.sign * q * (small_rotation(e0) @ u) + d)
    angle = math.radians(ax.sign * q)
    if model.alternative:
        u2 = small_rotation(e0) @ u
        u2 = u2 / np.linalg.norm(u2)
        c2 = ax.centre + d0
        r = small_rotation(e) @ rotation(u2, angle)
        return _homogeneous(r, c2 + d - r @ c2)
    r = small_rotation(e0 + e) @ rotation(u, angle)
    return _homogeneous(r, ax.centre + d0 + d - r @ ax.centre)


def forward(
    model: VolModel, q: dict[str, float], tool_length: float = 0.0, errors: bool = True
) -> np.ndarray:
    """The tool tip relative to the workpiece (mm) at the programmed axis values `q`
    (mm, °), on the imperfect machine (`errors`) or the ideal one."""
    point = {a: q.get(a, 0.0) + model.axes[a].offset for a in model.chain}
    w = model.workpiece_axes
    tool = np.eye(4)
    for letter in model.chain[w:]:
        tool = tool @ axis_transform(model, model.axes[letter], point, errors)
    work = np.eye(4)
    for letter in reversed(model.chain[:w]):
        work = work @ axis_transform(model, model.axes[letter], point, errors)
    tip = np.append(model.tool_point(tool_length), 1.0)
    return (np.linalg.inv(work) @ tool @ tip)[:3]


def correction(model: VolModel, q: dict[str, float], tool_length: float = 0.0) -> dict[str, float]:
    """Δ of each linear axis (mm) with p_act(q + Δ) = p_nom(q), to `TOLERANCE`."""
    linear = model.linear
    target = forward(model, q, tool_length, errors=False)
    jac = np.empty((3, len(linear)))
    for i, a in enumerate(linear):
        moved = dict(q)
        moved[a] = q.get(a, 0.0) + 1.0
        jac[:, i] = forward(model, moved, tool_length, errors=False) - target
    delta = np.zeros(len(linear))
    for _ in range(MAX_STEPS):
        moved = dict(q)
        for i, a in enumerate(linear):
            moved[a] = q.get(a, 0.0) + delta[i]
        miss = target - forward(model, moved, tool_length)
        step = np.linalg.lstsq(jac, miss, rcond=None)[0]
        delta += step
        if float(np.abs(step).max()) < TOLERANCE:
            break
    return {a: float(delta[i]) for i, a in enumerate(linear)}


__all__ = ["axis_transform", "correction", "forward", "rotation", "small_rotation"]
