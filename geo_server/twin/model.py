"""The twin's parameters: what is wrong with the machine, and how it warms up (pure data).

Units of the twin file and of these classes ("SI-style", docs/twin.md):

- positions in mm on linear axes, in ° on rotary axes;
- errors in µm on linear axes and in 0.001° (millidegrees) on rotary axes — both are ten
  increments of the CNC, so one error scale serves every axis;
- temperatures in °C, times in s, expansion coefficients in µm/m/K, squareness in µrad.

An error is what the machine adds to where the drive put it: true position = drive
(output) position + error. The compensations exist to make the true position equal the
programmed one, so a compensation is right when it adds minus the error.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Curve:
    """An error over one position: linear interpolation, edge values held outside."""

    positions: tuple[float, ...]  # mm or °
    errors: tuple[float, ...]  # µm or 0.001°


@dataclass(frozen=True)
class Grid:
    """An error over two positions (of axes `over1`, `over2`): bilinear, edges held.

    `errors[j][i]` is the error at (start1 + i·step1, start2 + j·step2)."""

    over1: str
    over2: str
    start1: float
    step1: float
    start2: float
    step2: float
    errors: tuple[tuple[float, ...], ...]


@dataclass(frozen=True)
class Straightness:
    """The error of this axis as a function of another axis' position (sag of a beam,
    straightness of a guide): what cross compensation corrects."""

    over: str
    curve: Curve


@dataclass(frozen=True)
class Expansion:
    """Linear thermal expansion of the axis about a reference point: error =
    coefficient · (T − T_ref) · (position − reference) with T the node's temperature."""

    node: str
    coefficient: float  # µm/m/K
    reference: float = 0.0  # mm or °


@dataclass(frozen=True)
class AxisTwin:
    """The errors of one axis."""

    name: str
    #: Linear positioning (scale) error at the reference temperature:
    #: offset + slope · (position − reference).
    linear_offset: float = 0.0  # µm
    linear_slope: float = 0.0  # µm/m
    linear_reference: float = 0.0  # mm
    #: Pitch error of the drive (leadscrew), both directions.
    pitch: Curve | None = None
    #: Pitch error when moving negative, where it differs from positive (a bilateral
    #: error: `pitch` then holds the positive-direction curve).
    pitch_negative: Curve | None = None
    #: Cyclic error of the screw (one period per lead): amplitude · sin(2π·pos / period).
    periodic_amplitude: float = 0.0  # µm
    periodic_period: float = 0.0  # mm
    #: Reversal error: the lost motion when the axis moves against `reference_direction`
    #: (+1 or −1): error = −direction · reversal while moving against it.
    reversal: float = 0.0  # µm
    reference_direction: int = 1
    straightness: tuple[Straightness, ...] = ()
    grids: tuple[Grid, ...] = ()
    #: Squareness to other axes: error += angle · position of that axis.
    squareness: tuple[tuple[str, float], ...] = ()  # (axis, µrad)
    expansion: Expansion | None = None
    #: Friction the drive must overcome: sign(v) · (coulomb + viscous · |v|).
    friction_coulomb: float = 0.0  # drive units
    friction_viscous: float = 0.0  # drive units per mm/s (per °/s rotary)
    #: Random positioning scatter of each approach (the machine's repeatability).
    scatter: float = 0.0  # µm, one standard deviation


@dataclass(frozen=True)
class ThermalNode:
    """A first-order lumped thermal mass: dT/dt = (T_target − T)/τ with T_target =
    ambient + heat sources (steady-state rises)."""

    name: str
    tau: float  # s
    initial: float  # °C
    motion_axis: str = ""  # heated by this axis' motion
    motion_gain: float = 0.0  # K steady-state rise at 1 m/s (1000 °/s rotary)
    spindle_gain: float = 0.0  # K steady-state rise while the spindle runs


@dataclass(frozen=True)
class Sensor:
    """A temperature sensor on a node: noise and resolution, sampled every `period`."""

    name: str
    node: str
    axis: str = ""  # shown as TWIN::sensor_temperature of this axis
    noise: float = 0.0  # °C, one standard deviation
    resolution: float = 0.01  # °C
    period: float = 0.1  # s of simulated time


#: The rigid-body errors of a three-axis machine (ISO 230-1): six component errors of
#: each linear axis over its own travel (004 p.29-30 names) ...
RIGID_COMPONENTS = tuple(f"E{d}{a}" for a in "XYZ" for d in "XYZABC")
#: ... and the orientation (squareness) errors of the axes (004 p.30 position errors;
#: with X as the reference, C0Y, B0Z, A0Z are the three of ISO 230-1).
RIGID_SQUARENESS = tuple(f"{d}0{a}" for a in "XYZ" for d in "ABC")


@dataclass(frozen=True)
class RigidBody:
    """The rigid-body errors of the linear axes X, Y, Z (docs/twin.md §2.1): composed
    along `chain` (workpiece → tool, as in a VOLC list) with the model of docs/
    volumetric.md §2, the tool tip at `tool` (mm, in the frame of the last carriage).
    Component errors are curves over the axis' own position: µm for EX?, EY?, EZ?,
    µrad for EA?, EB?, EC?; squareness in µrad."""

    chain: str = "YXZ"
    workpiece_axes: int = 0
    tool: tuple[float, float, float] = (0.0, 0.0, 0.0)
    squareness: tuple[tuple[str, float], ...] = ()
    components: tuple[tuple[str, Curve], ...] = ()


@dataclass(frozen=True)
class TwinConfig:
    """Everything the twin file says (validated)."""

    path: str = ""
    reference_temperature: float = 20.0  # °C
    time_scale: float = 1.0  # simulated seconds per real second
    seed: int = 1
    ambient: tuple[tuple[float, float], ...] = ((0.0, 20.0),)  # (s, °C), held outside
    nodes: tuple[ThermalNode, ...] = ()
    sensors: tuple[Sensor, ...] = ()
    axes: dict[str, AxisTwin] = field(default_factory=dict)
    rigid_body: RigidBody | None = None


__all__ = [
    "RIGID_COMPONENTS",
    "RIGID_SQUARENESS",
    "AxisTwin",
    "Curve",
    "Expansion",
    "Grid",
    "RigidBody",
    "Sensor",
    "Straightness",
    "ThermalNode",
    "TwinConfig",
]
