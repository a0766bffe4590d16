"""The volumetric model against closed-form rigid-body results (docs/volumetric.md §2).

Every expectation here is derived by hand in the test (a comment gives the derivation
from the doc's definitions), never computed by the code under test. One error at a time,
at several positions. The doc's model is first-order by definition (Ω(e) = I + [e]×, no
second-order terms claimed), so within the model the closed forms below are exact; the
tolerance is 1e-9 mm throughout.

Conventions used (docs/volumetric.md §2):

- linear axis at q: p ↦ s·q·Ω(ε0)·u + δ(q) + Ω(ε(q))·p;
- rotary axis at θ (default): p ↦ c + δ0 + δ(θ) + Ω(ε0 + ε(θ))·Rot(u, s·θ)·(p − c);
- rotary axis (alternative): p ↦ c′ + δ(θ) + Ω(ε(θ))·Rot(u′, s·θ)·(p − c′), c′ = c + δ0;
- s = +1 on the tool side, −1 for the first `workpiece_axes` axes of the chain;
- tool side composed from the base in chain order, workpiece side in reverse order;
  p = T_wp⁻¹ · T_tool · t, t = P0 + ℓ·N0;
- Ω(a, b, c) = [[1, −c, b], [c, 1, −a], [−b, a, 1]] (I + [e]×);
- correction Δ on the linear axes: p_act(q + Δ) = p_nom(q), tables at q + Δ.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from geo_server.volcomp.model import VolModel, build_model
from geo_server.volcomp.reference import correction, forward
from geo_server.volcomp.tables import ParamTable

TOL = 1e-9  # mm

#: positions (x, y, z) in mm, inside and across the travel
POSITIONS = [
    (0.0, 0.0, 0.0),
    (250.0, -120.0, 80.0),
    (1000.0, 400.0, -300.0),
    (-35.5, 710.25, 12.0),
    (612.3, 55.5, -499.9),
]
TOOL_LENGTHS = [0.0, 150.0]


def const(name: str, value: float) -> ParamTable:
    """A parameter without arguments (a constant)."""
    return ParamTable(name, (), (), np.array(float(value)))


def table(name: str, arg: str, xs: list[float], vs: list[float]) -> ParamTable:
    """A 1-D GRID table over `arg`."""
    return ParamTable(name, (arg,), (np.array(xs, dtype=float),), np.array(vs, dtype=float))


def make(chain: str, workpiece_axes: int = 0, *tables: ParamTable, **kw: bool) -> VolModel:
    return build_model(chain, workpiece_axes, {t.name: t for t in tables}, **kw)


def q3(x: float, y: float, z: float, **more: float) -> dict[str, float]:
    return {"X": x, "Y": y, "Z": z, **more}


def assert_vec(actual: np.ndarray, expected: tuple[float, ...], tol: float = TOL) -> None:
    np.testing.assert_allclose(np.asarray(actual), np.array(expected), rtol=0.0, atol=tol)


def assert_corr(actual: dict[str, float], expected: dict[str, float], tol: float = TOL) -> None:
    assert set(actual) == set(expected)
    for axis, value in expected.items():
        assert actual[axis] == pytest.approx(value, rel=0.0, abs=tol), axis


def tool(**p0: float) -> list[ParamTable]:
    """P0X..P0Z as given (0 otherwise) and N0 = (0, 0, −1) (the doc's example, 004 p.15)."""
    return [*(const(f"P0{d}", p0.get(d, 0.0)) for d in "XYZ"), const("N0Z", -1.0)]


# --- 1. the ideal machine ----------------------------------------------------------


@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("errors", [True, False])
def test_ideal_forward_is_the_axis_values(pos, errors):
    # "YXZ", tool side only: T_tool = Tr(y·e_y)·Tr(x·e_x)·Tr(z·e_z), t = 0 → (x, y, z)
    m = make("YXZ")
    p = forward(m, q3(*pos), 0.0, errors=errors)
    assert np.array_equal(p, np.array(pos))


@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("length", [0.0, 50.0, 213.5])
def test_ideal_forward_with_tool_zero_and_length(pos, length):
    # t = P0 + ℓ·N0 = (P0X, P0Y, P0Z − ℓ) with N0 = (0, 0, −1); pure translations:
    # p = (x + P0X, y + P0Y, z + P0Z − ℓ)
    p0 = {"X": 12.5, "Y": -7.25, "Z": 40.0}
    m = make("YXZ", 0, *tool(**p0))
    x, y, z = pos
    expected = (x + 12.5, y - 7.25, z + 40.0 - length)
    assert_vec(forward(m, q3(*pos), length), expected)
    assert_vec(forward(m, q3(*pos), length, errors=False), expected)
    # nothing to correct: p_act ≡ p_nom, the Newton step is exactly zero
    assert correction(m, q3(*pos), length) == {"X": 0.0, "Y": 0.0, "Z": 0.0}


# --- 2. a pure X positioning error --------------------------------------------------

K = 2e-5  # EXX(x) = K·x: a table from (0, 0) to (1000, K·1000 = 0.02)


def exx_model(k: float = K) -> VolModel:
    return make("YXZ", 0, table("EXX", "X", [0.0, 1000.0], [0.0, k * 1000.0]))


@pytest.mark.parametrize("pos", [*POSITIONS[:3], (400.0, 3.0, -4.0), (999.0, -1.0, 1.0)])
def test_exx_linear_forward_and_correction(pos):
    x, y, z = pos
    m = exx_model()
    # X carriage at x: translation x·e_x + δ(x) = (x + K·x, 0, 0), no rotation
    assert_vec(forward(m, q3(*pos)), (x + K * x, y, z))
    # (x + Δ) + K·(x + Δ) = x  →  Δ = −K·x / (1 + K); Y and Z see no error
    assert_corr(correction(m, q3(*pos)), {"X": -K * x / (1 + K), "Y": 0.0, "Z": 0.0})


@pytest.mark.parametrize("x", [-200.0, -0.5])
def test_exx_held_below_the_table(x):
    # below the first grid point EXX holds its edge value EXX(0) = 0: no error at all
    m = exx_model()
    assert_vec(forward(m, q3(x, 10.0, 20.0)), (x, 10.0, 20.0))
    assert_corr(correction(m, q3(x, 10.0, 20.0)), {"X": 0.0, "Y": 0.0, "Z": 0.0})


@pytest.mark.parametrize("x", [1200.0, 1500.0, 5000.0])
def test_exx_held_beyond_the_table(x):
    # beyond the last grid point EXX holds EXX(1000) = 0.02 mm: p_x = x + 0.02, and the
    # corrected position x − 0.02 is still beyond the table, so Δ = −0.02 exactly
    m = exx_model()
    assert_vec(forward(m, q3(x, -5.0, 7.0)), (x + 0.02, -5.0, 7.0))
    assert_corr(correction(m, q3(x, -5.0, 7.0)), {"X": -0.02, "Y": 0.0, "Z": 0.0})


def test_exx_looked_up_at_the_corrected_position():
    # x = 1000.01 is beyond the table (forward: x + 0.02), but the corrected position
    # x/(1 + K) = 999.99… is inside it, where EXX = K·(x + Δ): Δ = −K·x/(1 + K), not −0.02
    x = 1000.01
    m = exx_model()
    assert_vec(forward(m, q3(x, 0.0, 0.0)), (x + 0.02, 0.0, 0.0))
    assert x / (1 + K) < 1000.0
    assert_corr(correction(m, q3(x, 0.0, 0.0)), {"X": -K * x / (1 + K), "Y": 0.0, "Z": 0.0})


# --- 3. squareness ------------------------------------------------------------------

SQ = 50e-6  # rad


@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("length", TOOL_LENGTHS)
def test_squareness_c0y(pos, length):
    # Y travels along Ω(0, 0, C0Y)·e_y = (−C0Y, 1, 0): p = (x − C0Y·y, y, z − ℓ)
    # (the carriage is not turned, so the tool length does not matter);
    # (x + Δx) − C0Y·(y + Δy) = x, y + Δy = y  →  Δx = +C0Y·y
    x, y, z = pos
    m = make("YXZ", 0, const("C0Y", SQ), *tool())
    assert_vec(forward(m, q3(*pos), length), (x - SQ * y, y, z - length))
    assert_corr(correction(m, q3(*pos), length), {"X": SQ * y, "Y": 0.0, "Z": 0.0})


@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("length", TOOL_LENGTHS)
def test_squareness_b0z(pos, length):
    # Z travels along Ω(0, B0Z, 0)·e_z = (B0Z, 0, 1): p = (x + B0Z·z, y, z − ℓ);
    # Δz = 0, Δx = −B0Z·z
    x, y, z = pos
    m = make("YXZ", 0, const("B0Z", SQ), *tool())
    assert_vec(forward(m, q3(*pos), length), (x + SQ * z, y, z - length))
    assert_corr(correction(m, q3(*pos), length), {"X": -SQ * z, "Y": 0.0, "Z": 0.0})


@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("length", TOOL_LENGTHS)
def test_squareness_a0z(pos, length):
    # Z travels along Ω(A0Z, 0, 0)·e_z = (0, −A0Z, 1): p = (x, y − A0Z·z, z − ℓ);
    # Δz = 0, Δy = +A0Z·z
    x, y, z = pos
    m = make("YXZ", 0, const("A0Z", SQ), *tool())
    assert_vec(forward(m, q3(*pos), length), (x, y - SQ * z, z - length))
    assert_corr(correction(m, q3(*pos), length), {"X": 0.0, "Y": SQ * z, "Z": 0.0})


@pytest.mark.parametrize("name", ["X0X", "Y0X", "Z0Y", "X0Z", "Z0Z"])
@pytest.mark.parametrize("pos", POSITIONS[:3])
def test_position_shift_of_a_linear_axis_is_ignored(name, pos):
    # doc §2 (004 p.28): "position deviation is only relevant for rotary axes"
    m = make("YXZ", 0, const(name, 0.3))
    assert_vec(forward(m, q3(*pos)), pos)
    assert_corr(correction(m, q3(*pos)), {"X": 0.0, "Y": 0.0, "Z": 0.0})


# --- 4. angular errors of a carriage with a tool offset -----------------------------

ANG = 1e-4  # rad: big enough that the second-order coupling terms (ANG²·100 mm = 1e-6
# mm) are far above the 1e-9 mm tolerance, so the exact solutions are told apart from
# their first-order approximations


def angular(name: str, form: str) -> ParamTable:
    """The constant `name` = ANG, as a constant or as a 1-D table over X with equal
    values (the X carriage's own argument)."""
    if form == "constant":
        return const(name, ANG)
    return table(name, "X", [-500.0, 0.0, 1500.0], [ANG, ANG, ANG])


@pytest.mark.parametrize("form", ["constant", "table"])
@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("length", TOOL_LENGTHS)
def test_roll_of_x_carriage(form, pos, length):
    # "YXZ": the X carriage carries Z and the tool. Relative to it the tool tip is
    # v = z·e_z + t = (0, 0, z − ℓ); Ω(a, 0, 0)·v = v + a·e_x × v = (0, −a(z − ℓ), z − ℓ).
    # p = (x, y − a(z − ℓ), z − ℓ). Correction: z-component z + Δz − ℓ = z − ℓ → Δz = 0;
    # y + Δy − a(z − ℓ) = y → Δy = a(z − ℓ); Δx = 0 (Y is first in the chain, error-free)
    x, y, z = pos
    a = ANG
    m = make("YXZ", 0, angular("EAX", form), *tool())
    assert_vec(forward(m, q3(*pos), length), (x, y - a * (z - length), z - length))
    assert_corr(correction(m, q3(*pos), length), {"X": 0.0, "Y": a * (z - length), "Z": 0.0})


@pytest.mark.parametrize("form", ["constant", "table"])
@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("length", TOOL_LENGTHS)
def test_roll_of_x_carriage_with_a_y_tool_offset(form, pos, length):
    # t = (0, P, −ℓ), v = (0, P, z − ℓ); Ω(a, 0, 0)·v = (0, P − a(z − ℓ), a·P + z − ℓ).
    # p = (x, y + P − a(z − ℓ), z − ℓ + a·P).
    # z: z + Δz − ℓ + a·P = z − ℓ → Δz = −a·P (the coupling through the Z axis)
    # y: y + Δy + P − a(z + Δz − ℓ) = y + P → Δy = a(z − ℓ − a·P) = a(z − ℓ) − a²·P
    x, y, z = pos
    a, big_p = ANG, 100.0
    m = make("YXZ", 0, angular("EAX", form), *tool(Y=big_p))
    assert_vec(
        forward(m, q3(*pos), length), (x, y + big_p - a * (z - length), z - length + a * big_p)
    )
    assert_corr(
        correction(m, q3(*pos), length),
        {"X": 0.0, "Y": a * (z - length) - a * a * big_p, "Z": -a * big_p},
    )


@pytest.mark.parametrize("form", ["constant", "table"])
@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("length", TOOL_LENGTHS)
def test_pitch_of_x_carriage(form, pos, length):
    # t = (P, 0, −ℓ), v = (P, 0, z − ℓ); Ω(0, b, 0)·v = (P + b(z − ℓ), 0, z − ℓ − b·P).
    # p = (x + P + b(z − ℓ), y, z − ℓ − b·P).
    # z: z + Δz − ℓ − b·P = z − ℓ → Δz = b·P
    # x: x + Δx + P + b(z + Δz − ℓ) = x + P → Δx = −b(z − ℓ + b·P) = −b(z − ℓ) − b²·P
    # With P = 0 this is the plain Δx = −b(z − ℓ), Δz = 0 (checked separately below).
    x, y, z = pos
    b, big_p = ANG, 100.0
    m = make("YXZ", 0, angular("EBX", form), *tool(X=big_p))
    assert_vec(
        forward(m, q3(*pos), length), (x + big_p + b * (z - length), y, z - length - b * big_p)
    )
    assert_corr(
        correction(m, q3(*pos), length),
        {"X": -b * (z - length) - b * b * big_p, "Y": 0.0, "Z": b * big_p},
    )


@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("length", TOOL_LENGTHS)
def test_pitch_of_x_carriage_without_offset(pos, length):
    # P = 0: v = (0, 0, z − ℓ) → p = (x + b(z − ℓ), y, z − ℓ); Δx = −b(z − ℓ), Δz = 0
    x, y, z = pos
    b = ANG
    m = make("YXZ", 0, const("EBX", b), *tool())
    assert_vec(forward(m, q3(*pos), length), (x + b * (z - length), y, z - length))
    assert_corr(correction(m, q3(*pos), length), {"X": -b * (z - length), "Y": 0.0, "Z": 0.0})


@pytest.mark.parametrize("pos", POSITIONS)
def test_yaw_of_y_carriage_acts_over_the_x_lever(pos):
    # "YXZ": the Y carriage carries X, Z and the tool: v = (x, 0, z) (t = 0);
    # Ω(0, 0, c)·v = (x, c·x, z): p = (x, y + c·x, z).
    # x: x + Δx = x → Δx = 0; y: y + Δy + c·x = y → Δy = −c·x
    x, y, z = pos
    c = ANG
    m = make("YXZ", 0, const("ECY", c))
    assert_vec(forward(m, q3(*pos)), (x, y + c * x, z))
    assert_corr(correction(m, q3(*pos)), {"X": 0.0, "Y": -c * x, "Z": 0.0})


# --- 5. a linear axis on the workpiece side -----------------------------------------


@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("length", TOOL_LENGTHS)
def test_workpiece_side_x_ideal(pos, length):
    # "XYZ", workpiece_axes 1: X moves the table by s·x = −x: T_wp = Tr(−x·e_x),
    # T_tool = Tr(y·e_y + z·e_z); p = T_wp⁻¹·T_tool·t = (x, y, z − ℓ)
    x, y, z = pos
    m = make("XYZ", 1, *tool())
    assert_vec(forward(m, q3(*pos), length), (x, y, z - length))
    assert_vec(forward(m, q3(*pos), length, errors=False), (x, y, z - length))
    assert_corr(correction(m, q3(*pos), length), {"X": 0.0, "Y": 0.0, "Z": 0.0})


@pytest.mark.parametrize("pos", [*POSITIONS[:2], (400.0, 3.0, -4.0), (999.0, 1.0, 2.0)])
def test_workpiece_side_x_positioning_error(pos):
    # EXX(x) = K·x on the workpiece side: the table is at −x + δ(x) (s = −1, the shift
    # δ added as it is); T_wp⁻¹ = Tr((x − δ)·e_x): p = (x − K·x, y, z).
    # Correction: (x + Δ)(1 − K) = x → Δ = x/(1 − K) − x = K·x/(1 − K)
    # (valid while x/(1 − K) ≤ 1000, the end of the table)
    x, y, z = pos
    m = make("XYZ", 1, table("EXX", "X", [0.0, 1000.0], [0.0, K * 1000.0]))
    assert x / (1 - K) <= 1000.0
    assert_vec(forward(m, q3(*pos)), (x - K * x, y, z))
    assert_corr(correction(m, q3(*pos)), {"X": K * x / (1 - K), "Y": 0.0, "Z": 0.0})


@pytest.mark.parametrize("x", [1000.0, 1200.0])
def test_workpiece_side_x_positioning_error_held(x):
    # the corrected position x + Δ lies beyond the table (x/(1 − K) > 1000), where
    # EXX = 0.02 is held: (x + Δ) − 0.02 = x → Δ = +0.02 (and x + Δ > 1000 indeed).
    # At x itself (≥ 1000) EXX(x) = 0.02 as well: p_x = x − 0.02
    m = make("XYZ", 1, table("EXX", "X", [0.0, 1000.0], [0.0, K * 1000.0]))
    assert_vec(forward(m, q3(x, 0.0, 0.0)), (x - 0.02, 0.0, 0.0))
    assert_corr(correction(m, q3(x, 0.0, 0.0)), {"X": 0.02, "Y": 0.0, "Z": 0.0})


# --- 6. a rotary axis ---------------------------------------------------------------


def rot_z(deg: float, v: tuple[float, float, float]) -> tuple[float, float, float]:
    """Rotation about +Z by `deg`, written out: (x cos − y sin, x sin + y cos, z)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    x, y, z = v
    return (x * c - y * s, x * s + y * c, z)


@pytest.mark.parametrize("pos", POSITIONS)
def test_rotary_table_ideal_at_90(pos):
    # "CYXZ", workpiece_axes 1: the table turns by s·θ = −θ about c = 0:
    # T_wp = Rot(e_z, −θ), so p = Rot(e_z, +θ)·(x, y, z). At 90°: (−y, x, z)
    x, y, z = pos
    m = make("CYXZ", 1)
    assert_vec(forward(m, q3(*pos, C=90.0)), (-y, x, z))
    assert_vec(forward(m, q3(*pos, C=0.0)), (x, y, z))
    assert_corr(correction(m, q3(*pos, C=90.0)), {"X": 0.0, "Y": 0.0, "Z": 0.0})


@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("theta", [30.0, -30.0, 135.0])
def test_rotary_table_ideal_at_angle(pos, theta):
    # as above: p = (x cos θ − y sin θ, x sin θ + y cos θ, z); θ = 30°: cos = √3/2, sin = ½
    x, y, z = pos
    m = make("CYXZ", 1)
    if theta == 30.0:
        h = math.sqrt(3.0) / 2.0
        expected = (x * h - y * 0.5, x * 0.5 + y * h, z)
    else:
        expected = rot_z(theta, pos)
    assert_vec(forward(m, q3(*pos, C=theta)), expected)


@pytest.mark.parametrize("pos", POSITIONS)
def test_rotary_table_about_a_centre(pos):
    # centre c = (cx, cy, cz): p = c + Rot(e_z, θ)·(q − c); at 90°, Rot(v) = (−v_y, v_x, v_z):
    # p = (cx − (y − cy), cy + (x − cx), cz + (z − cz)) = (cx + cy − y, cy − cx + x, z)
    x, y, z = pos
    cx, cy, cz = 100.0, -40.0, 25.0
    m = make("CYXZ", 1, const("PXC", cx), const("PYC", cy), const("PZC", cz))
    assert_vec(forward(m, q3(*pos, C=90.0)), (cx + cy - y, cy - cx + x, z))
    assert_vec(forward(m, q3(*pos, C=0.0)), (x, y, z))


D = 0.05  # mm


@pytest.mark.parametrize("pos", POSITIONS)
def test_rotary_table_position_shift_x0c(pos):
    # default model: T_wp: p ↦ c + δ0 + Rot(e_z, −θ)(p − c), c = 0, δ0 = (d, 0, 0):
    # p = Rot(e_z, θ)·(q − δ0).
    # θ = 0:  p = (x − d, y, z)
    # θ = 90°: p = Rot90(x − d, y, z) = (−y, x − d, z)
    # Correction at any θ: Rot(θ)(q + Δ − δ0) = Rot(θ)(q) → Δ = δ0 = (d, 0, 0)
    # (the table sits d further in X of the base; the tool follows it)
    x, y, z = pos
    m = make("CYXZ", 1, const("X0C", D))
    assert_vec(forward(m, q3(*pos, C=0.0)), (x - D, y, z))
    assert_vec(forward(m, q3(*pos, C=90.0)), (-y, x - D, z))
    for theta in (0.0, 90.0, 30.0):
        assert_corr(correction(m, q3(*pos, C=theta)), {"X": D, "Y": 0.0, "Z": 0.0})


@pytest.mark.parametrize("pos", POSITIONS)
def test_rotary_table_position_shift_y0c(pos):
    # δ0 = (0, e, 0): θ = 90°: p = Rot90(x, y − e, z) = (e − y, x, z); Δ = (0, e, 0)
    x, y, z = pos
    m = make("CYXZ", 1, const("Y0C", D))
    assert_vec(forward(m, q3(*pos, C=90.0)), (D - y, x, z))
    assert_corr(correction(m, q3(*pos, C=90.0)), {"X": 0.0, "Y": D, "Z": 0.0})


@pytest.mark.parametrize("pos", POSITIONS)
def test_rotary_table_position_shift_alternative_model(pos):
    # alternative model: c′ = c + δ0 = (d, 0, 0): T_wp: p ↦ c′ + Rot(−θ)(p − c′), so
    # p = c′ + Rot(θ)(q − c′).
    # θ = 0: p = q — a shifted axis does not show until it turns; Δ = 0.
    # θ = 90°: q − c′ = (x − d, y, z) → (−y, x − d, z) → + c′ = (d − y, x − d, z).
    # Correction: c′ + Rot90(q + Δ − c′) = Rot90(q) → Rot90(Δ) = Rot90(c′) − c′
    # → Δ = c′ − Rot(−90°)(c′) = (d, 0, 0) − (0, −d, 0) = (d, d, 0)
    x, y, z = pos
    m = make("CYXZ", 1, const("X0C", D), alternative=True)
    assert_vec(forward(m, q3(*pos, C=0.0)), (x, y, z))
    assert_corr(correction(m, q3(*pos, C=0.0)), {"X": 0.0, "Y": 0.0, "Z": 0.0})
    assert_vec(forward(m, q3(*pos, C=90.0)), (D - y, x - D, z))
    assert_corr(correction(m, q3(*pos, C=90.0)), {"X": D, "Y": D, "Z": 0.0})


@pytest.mark.parametrize("pos", POSITIONS)
@pytest.mark.parametrize("theta", [0.0, 30.0, 90.0])
def test_rotary_head_on_tool_side(pos, theta):
    # "YXZC", no workpiece axis: the tool tip t = (r, 0, −ℓ) turns with C (s = +1, c = 0):
    # p = (x, y, z) + Rot(e_z, θ)·t = (x + r cos θ, y + r sin θ, z − ℓ).
    # With X0C = d (default model): p gains +δ0 = (d, 0, 0) → Δ = (−d, 0, 0) at any θ
    x, y, z = pos
    r, length = 30.0, 120.0
    c, s = math.cos(math.radians(theta)), math.sin(math.radians(theta))
    ideal = make("YXZC", 0, *tool(X=r))
    assert_vec(forward(ideal, q3(*pos, C=theta), length), (x + r * c, y + r * s, z - length))
    shifted = make("YXZC", 0, const("X0C", D), *tool(X=r))
    assert_vec(forward(shifted, q3(*pos, C=theta), length), (x + r * c + D, y + r * s, z - length))
    assert_corr(correction(shifted, q3(*pos, C=theta), length), {"X": -D, "Y": 0.0, "Z": 0.0})


# --- 7. the Newton iteration --------------------------------------------------------


@pytest.mark.parametrize("pos", [p for p in POSITIONS if p[0] >= 0] + [(850.0, -10.0, 10.0)])
def test_newton_with_a_steep_table(pos):
    # EXX(x) = k·x with k = 1e-3 (slope 1e-3, corrections up to 1 mm), 0 ≤ x ≤ 1000 so
    # that x + Δ = x/(1 + k) stays inside the table: Δx = −k·x/(1 + k) closed form, and
    # the corrected position really lands on p_nom
    k = 1e-3
    x, _, _ = pos
    m = exx_model(k)
    d = correction(m, q3(*pos))
    assert_corr(d, {"X": -k * x / (1 + k), "Y": 0.0, "Z": 0.0})
    moved = {a: pos["XYZ".index(a)] + d[a] for a in "XYZ"}
    miss = forward(m, moved) - forward(m, q3(*pos), errors=False)
    assert float(np.abs(miss).max()) <= 1e-12


@pytest.mark.parametrize("pos", [*POSITIONS, (850.0, -10.0, 10.0)])
@pytest.mark.parametrize("length", TOOL_LENGTHS)
def test_newton_with_steep_coupled_errors(pos, length):
    # several errors at once with a kinked steep table (slopes ±1e-3): no closed form
    # asserted, only the defining property p_act(q + Δ) = p_nom(q) to 1e-12 mm
    m = make(
        "YXZ",
        0,
        table("EXX", "X", [0.0, 500.0, 1000.0], [0.0, 0.5, 0.0]),
        table("EYX", "X", [0.0, 1000.0], [0.0, -0.4]),
        table("EAX", "X", [0.0, 1000.0], [0.0, 2e-4]),
        table("EBY", "Y", [-200.0, 800.0], [1e-4, -1e-4]),
        const("C0Y", SQ),
        const("B0Z", -SQ),
        *tool(X=20.0, Y=-15.0),
    )
    d = correction(m, q3(*pos), length)
    moved = {a: pos["XYZ".index(a)] + d[a] for a in "XYZ"}
    miss = forward(m, moved, length) - forward(m, q3(*pos), length, errors=False)
    assert float(np.abs(miss).max()) <= 1e-12
