"""Typed machine configuration: the contract between the list-file loader and the kernel.

The loader (`geo_server.listfile`) turns a start-up list plus the axis parameter lists
[AXIS] and compensation value lists [COMP] it names into one `MachineConfig`. The
machine and the compensation kernel only ever see these objects, never list-file text.

Units (docs/design.md §3): positions in internal units, 0.1 µm for linear (T) axes and 0.0001° for
rotary (R) and spindle (S) axes; one increment [Incr.] is one internal unit, so the
`unit` flag of the compensation lists (0 increments, 1 = 0.1 µm) changes nothing.
Velocities in internal units per second (µm/s of the manuals = 10 units/s),
accelerations in mm/s² (rotary: °/s²) as the manuals give them.

Every parameter keeps the file and line it came from (`Source`) so that diagnostics can
name them and `save` can rewrite exactly that token.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from enum import IntFlag
from pathlib import Path
from typing import Any

import numpy as np

from geo_server.twin.model import TwinConfig


class CompKind(IntFlag):
    """The bit mask of `lr_param.prog_movement_requires_compensations` (000 §5.3, p.97).

    FRICT and CROSSTALK have no bit in the manual; they get emulator bits above the
    documented ones so that one mask type can name every compensation.
    """

    BACKLASH = 0x1
    LEAD = 0x2
    TEMP = 0x4
    CROSS = 0x8
    PLANE = 0x10
    FRICT = 0x100
    CROSSTALK = 0x200


NO_COMP = CompKind(0)

#: Name of each compensation as used in diagnostics, COMP commands and the kernel.
COMP_NAMES: dict[CompKind, str] = {
    CompKind.BACKLASH: "BACKLASH",
    CompKind.LEAD: "LEAD",
    CompKind.TEMP: "TEMP",
    CompKind.CROSS: "CROSS",
    CompKind.PLANE: "PLANE",
    CompKind.FRICT: "FRICT",
    CompKind.CROSSTALK: "CROSSTALK",
}
#: The object that shows whether a compensation is selected (NC `COMP ON/OFF`, 000 §5.1).
SELECTED_OBJECTS: dict[CompKind, str] = {
    CompKind.BACKLASH: "SIM::backlash_selected",
    CompKind.TEMP: "TEMPC::activated",
    CompKind.CROSS: "CROSSC::activated",
    CompKind.PLANE: "CC2::activated",
    CompKind.LEAD: "ssfk activated",
    CompKind.FRICT: "SIM::friction_selected",
    CompKind.CROSSTALK: "CROSSTALK::activated",
}


class Sealed:
    """A part of a loaded configuration: built field by field by the loader, then sealed
    (`seal`) and read-only from there on — for the machine and for every interface that
    reads it (`ObjectService.info.config`) alike. A reload or a save makes a new
    configuration and the machine swaps it whole at a cycle boundary (docs/design.md
    §4.4-4.5), so whoever holds one holds a snapshot that never changes under it.
    (`dataclasses.replace` makes an unsealed copy, to change and seal.)"""

    def __setattr__(self, name: str, value: Any) -> None:
        if self.__dict__.get("_sealed", False):
            raise AttributeError(
                f"{type(self).__name__}.{name} is read-only: a loaded configuration does "
                "not change (a reload or a save makes a new one)"
            )
        object.__setattr__(self, name, value)


def seal(part: Any) -> None:
    """Make `part` and every `Sealed` part it holds (in its fields, lists, tuples and
    dicts) read-only."""
    if isinstance(part, Sealed):
        if part.__dict__.get("_sealed", False):
            return
        object.__setattr__(part, "_sealed", True)
        for value in list(vars(part).values()):
            seal(value)
    elif isinstance(part, list | tuple):
        for item in part:
            seal(item)
    elif isinstance(part, dict):
        for item in part.values():
            seal(item)


@dataclass(frozen=True)
class Source:
    """Where a value came from: list file and 1-based line number."""

    file: str
    line: int

    def __str__(self) -> str:
        return f"{self.file}:{self.line}"


@dataclass
class Diagnostic:
    """A warning or error found while loading lists (docs/design.md §4).

    `error_id` is one of the IDs the manual lists for the affected compensation (see the
    check table in the README); 0 for plain warnings such as unknown entries.
    `deactivated` names the compensation that had to be switched off for `axis`.
    """

    severity: str  # "warning" | "error"
    message: str
    file: str = ""
    line: int = 0
    entry: str = ""
    error_id: int = 0
    axis: int = 0
    deactivated: CompKind | None = None
    #: the entry's value could not be used and its default stands in its place
    replaced: bool = False

    def describe(self) -> str:
        """`file:line: [id] entry: message (axis N)` without the severity word: what went
        wrong and where (the error list's one-line text, `SIM::last_error`)."""
        where = f"{self.file}:{self.line}: " if self.file and self.line else ""
        if self.file and not self.line:
            where = f"{self.file}: "
        ident = f"[{self.error_id}] " if self.error_id else ""
        entry = f"{self.entry}: " if self.entry else ""
        axis = f" (axis {self.axis})" if self.axis else ""
        return f"{where}{ident}{entry}{self.message}{axis}"

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}: " if self.file else ""
        ident = f"[{self.error_id}] " if self.error_id else ""
        entry = f"{self.entry}: " if self.entry else ""
        tail = ""
        if self.deactivated is not None:
            tail = f" -> {COMP_NAMES[self.deactivated]} deactivated for axis {self.axis}"
        return f"{self.severity}: {where}{ident}{entry}{self.message}{tail}"


# --------------------------------------------------------------------------- [AXIS]


@dataclass
class AxisParams(Sealed):
    """Axis parameter list [AXIS] (`achsmd*.lis`) entries the emulator uses."""

    log_nr: int
    name: str = ""
    kind: str = "T"  # "T" linear, "R" rotary, "S" spindle (kenngr.achs_typ 1/2/4)
    modulo: bool = False  # kenngr.modulo_calc
    modulo_period: float = 3_600_000.0  # kenngr.modulo_wert, internal units (360°)
    v_max: float = 100_000.0 * 10  # getriebe[0].vb_max, µm/s in the list -> units/s
    a_max: float = 1000.0  # getriebe[0].a_max, mm/s² (rotary °/s²)
    homed: bool = False  # emulator: sim.homed, axis referenced at start-up
    start_position: float = 0.0  # emulator: sim.start_position, internal units
    # backlash (000 §2): P-AXIS-00103, 00021, 00243
    lose: int = 0
    anwahl_losekomp: int = 0
    n_backlash_cyc: int = 0
    # temperature (000 §3): P-AXIS-00271..00275, 00482
    temp_comp: bool = False
    temp_comp_position_0: int = 0
    temp_comp_offset_0: int = 0
    temp_comp_coefficient: float = 0.0
    temp_comp_n_cycles: int = 0
    temp_comp_manual_activation: bool = False
    # selection of the list-based compensations
    crosscomp: bool = False  # P-AXIS-00047
    crosscomp2: bool = False  # P-AXIS-00174
    ssfk: bool = False  # P-AXIS-00175
    frict_comp: bool = False  # P-AXIS-00522
    crosstalk: bool = False  # P-AXIS-00789
    prog_movement_requires_compensations: CompKind = NO_COMP  # P-AXIS-00465
    #: P-AXIS-00525 lr_param.vol_comp.s_limit (004 p.14): the largest volumetric
    #: correction of the axis, 0.1 µm; 0 = not defined (activation is refused then)
    vol_comp_s_limit: int = 0
    #: parameter name (as written in the list, lower-case first segment) -> source
    sources: dict[str, Source] = field(default_factory=dict)
    path: str = ""


# --------------------------------------------------------------------------- [COMP]


@dataclass
class CrossComp(Sealed):
    """`kw.crosscomp.*` (000 §4.2): slave offset over one master's command position."""

    master_ax_nr: int
    setpoint: np.ndarray  # float64 [n], ascending, internal units of the master
    correction: np.ndarray  # float64 [n], internal units of the slave
    n_cycles: int = 0
    manual_activation: bool = False
    max_points: int = 1001
    unit: int = 1
    valid: bool = True


@dataclass
class PlaneComp(Sealed):
    """`kw.crosscomp2.*` (000 §4.3): bilinear grid over two masters.

    `table[j, i]`: j indexes master 2, i indexes master 1 (000 p.43). Unassigned points
    are 0.
    """

    master1_ax_nr: int
    master2_ax_nr: int
    start_position_master1: float
    start_position_master2: float
    interval1: float  # master 1 spacing (QUADRATIC: both equal `interval`)
    interval2: float
    table: np.ndarray  # float64 [last_index_master2+1, last_index_master1+1]
    grid: str = "QUADRATIC"
    n_cycles: int = 0
    manual_activation: bool = False
    max_points: int = 10201
    unit: int = 1
    valid: bool = True


@dataclass
class LsecComp(Sealed):
    """`kw.ssfk.*` (000 §4.4): leadscrew error table.

    `setpoint` holds the interpolation points (computed from kw_startpos + i·interval when
    equidistant). `pos`/`neg` are the *measured errors* Δs = s_ist − s_soll; the kernel
    applies −Δs (docs/design.md §6). `neg` equals `pos` for unilateral tables.
    """

    setpoint: np.ndarray  # float64 [kw_nr_max]
    pos: np.ndarray
    neg: np.ndarray
    bilateral: bool = False
    modulo: bool = False
    set_pos_without_comp: bool = False
    manual_activation: bool = False
    interval: int = 0
    kw_startpos: int = 0
    max_points: int = 1500
    unit: int = 1
    valid: bool = True


@dataclass
class FrictComp(Sealed):
    """`frict_comp.*` (000 §4.5): additive current over |velocity|."""

    vin: np.ndarray  # float64 [table_entries], µm/s (rotary 0.001°/s), ascending >= 0
    out: np.ndarray  # float64 [table_entries], drive current units
    mode: int = 3
    position_delay: int = 0  # 0.1 µm of path for the build-up after a reversal
    reversal_lookahead: int = 0  # cycles of decay before a reversal
    scaling_factor: int = 1000  # 0.1 %
    delay_cycles: int = 0
    max_points: int = 20
    valid: bool = True


#: Column order of `CrosstalkComp.corrections` (new model, 000 §4.6).
CROSSTALK_COLUMNS = (
    "accelerate_dir_pos",
    "accelerate_dir_neg",
    "decelerate_dir_pos",
    "decelerate_dir_neg",
)


@dataclass
class CrosstalkComp(Sealed):
    """`kw.crosstalk.*` in either dialect (000 §4.6 new; 001 §4.5 / 003 §3.5 old).

    New model: `mode` 1/2/3, reference `acceleration` (> 0) / `deceleration` (< 0) in
    mm/s², test points `ax_1`, `ax_2` with four corrections each (columns in
    `CROSSTALK_COLUMNS` order). Old model: `acc_table` / `corr_table` over the signed
    master acceleration.
    """

    dialect: str  # "new" | "old"
    master_dyn_ax_nr: int
    mode: int = 1
    master_pos1_ax_nr: int = 0
    master_pos2_ax_nr: int = 0
    n_cycles: int = 0
    manual_activation: bool = False
    max_points: int = 15
    acceleration: float = 0.0
    deceleration: float = 0.0
    velocity_dependent: bool = False
    ax_1: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ax_2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    corrections: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    acc_table: np.ndarray = field(default_factory=lambda: np.zeros(0))  # old model
    corr_table: np.ndarray = field(default_factory=lambda: np.zeros(0))  # old model
    valid: bool = True


@dataclass
class CompList(Sealed):
    """One compensation value list [COMP] (`achskw*.lis`)."""

    path: str
    achs_nr: int
    log_achs_name: str = ""
    cross: CrossComp | None = None
    plane: PlaneComp | None = None
    lsec: LsecComp | None = None
    frict: FrictComp | None = None
    crosstalk: CrosstalkComp | None = None


@dataclass
class AxisConfig(Sealed):
    """Everything known about one logical axis after loading and validation."""

    params: AxisParams
    comp: CompList | None = None

    @property
    def log_nr(self) -> int:
        return self.params.log_nr


@dataclass
class MachineConfig(Sealed):
    """A whole machine: the start-up list and every axis it names, validated."""

    startup_path: Path
    axes: dict[int, AxisConfig]  # logical axis number -> config, ascending order
    diagnostics: list[Diagnostic] = field(default_factory=list)
    #: The machine behind the controller (`twin.toml` beside the start-up list), if any.
    twin: TwinConfig | None = None
    #: Volumetric compensations (004, `vol_comp[i]` of the start-up list): a tuple of
    #: `geo_server.volcomp.config.VolComp` (typed loosely: model sits below volcomp)
    volumetric: tuple[Any, ...] = ()
    #: Folders besides the start-up list's from which files named in a VOLC list or over
    #: the network may be read (`geo-server run --allow-dir`; docs/security.md).
    allow_dirs: tuple[Path, ...] = ()

    @property
    def file_roots(self) -> tuple[Path, ...]:
        """The folders a file named over the network or in a VOLC list must lie in: the
        machine's folder (the start-up list's) and the `--allow-dir` folders."""
        return (self.startup_path.parent, *self.allow_dirs)

    @property
    def list_files(self) -> list[str]:
        """The axis parameter and compensation value lists, sorted (without the
        start-up list)."""
        files = {a.params.path for a in self.axes.values()}
        files |= {a.comp.path for a in self.axes.values() if a.comp is not None}
        return sorted(f for f in files if f)

    @property
    def deactivated(self) -> list[Diagnostic]:
        """The diagnostics that switched a compensation off."""
        return [d for d in self.diagnostics if d.deactivated is not None]


def with_axis_params(cfg: MachineConfig, params: Mapping[int, AxisParams]) -> MachineConfig:
    """`cfg` with the parameters of the axes in `params` replaced: a new configuration,
    not sealed, that shares every other part with `cfg` (`save` seals it)."""
    axes = {nr: replace(ax, params=params.get(nr, ax.params)) for nr, ax in cfg.axes.items()}
    return replace(cfg, axes=axes)
