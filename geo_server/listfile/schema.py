"""Every list entry the emulator knows: data type, documented range, parameter ID.

Types and ranges are those of the parameter descriptions: 002/003 §2–§3 (P-COMP) and
000 §2–§5 (P-AXIS). Entries marked "emulator" are not defined by the manuals; they are
documented in `geo_server.listfile.axislist`. Names use `[]` where an index goes
(`kw.ssfk.table[].pos`); the first segment is lower case (002 §1.3, names are matched
after `syntax.normalize_name`).
"""

from __future__ import annotations

import difflib
import functools
import re
from dataclasses import dataclass
from enum import Enum

from geo_server.model import CompKind


class ListKind(Enum):
    """Which list an entry belongs to (002 §1.2, 002 §1.2)."""

    STUP = "start-up list"
    AXIS = "axis parameter list"
    COMP = "compensation value list"
    VOLC = "volumetric compensation list"


#: Value bounds of the integer data types (002 §1.3 tables: UNSnn, SGNnn).
TYPE_BOUNDS: dict[str, tuple[int, int]] = {
    "BOOLEAN": (0, 1),
    "UNS08": (0, 0xFF),
    "UNS16": (0, 0xFFFF),
    "UNS32": (0, 0xFFFF_FFFF),
    "SGN16": (-0x8000, 0x7FFF),
    "SGN32": (-0x8000_0000, 0x7FFF_FFFF),
    "SGN64": (-0x8000_0000_0000_0000, 0x7FFF_FFFF_FFFF_FFFF),
}

#: Types whose value is text: after them only `(` opens a comment (002 §1.4).
STRING_TYPES = frozenset({"STRING"})
#: Symbolic bit mask (`LEAD | CROSS`, 000 §5.3): the value may contain blanks around `|`.
MASK_TYPES = frozenset({"MASK"})


@dataclass(frozen=True)
class Spec:
    """One known entry.

    `lo`/`hi` are the inclusive documented bounds (None: the data type's bounds).
    `canonical` names the entry an alias stands for (e.g. the mode-3 crosstalk example's
    `acceleration_pos` = `acceleration`); `alias_warning` makes the alias warn.
    `max_len` is the documented maximum length of a STRING (a longer one warns, kept).
    """

    name: str
    type: str
    list: ListKind
    pid: str = ""
    comp: CompKind | None = None
    lo: float | None = None
    hi: float | None = None
    canonical: str = ""
    alias_warning: bool = False
    max_len: int | None = None

    @property
    def key(self) -> str:
        """The name values are stored under."""
        return self.canonical or self.name

    def bounds(self) -> tuple[float | None, float | None]:
        """Inclusive (lo, hi): documented range, else the data type's bounds."""
        lo, hi = TYPE_BOUNDS.get(self.type, (None, None))
        return (lo if self.lo is None else self.lo, hi if self.hi is None else self.hi)


_S, _A, _C = ListKind.STUP, ListKind.AXIS, ListKind.COMP
_BL, _TE, _CR, _PL = CompKind.BACKLASH, CompKind.TEMP, CompKind.CROSS, CompKind.PLANE
_LE, _FR, _CT = CompKind.LEAD, CompKind.FRICT, CompKind.CROSSTALK

_SPECS: list[Spec] = [
    # ---- start-up list [STUP] (000 §4.1 p.26; 000 §4.1; emulator: *_mds*)
    Spec("zahl_kw", "UNS16", _S),
    Spec("achs_kw[]", "STRING", _S),
    Spec("achs_kw_log_ax_nr[]", "UNS16", _S, lo=1),
    Spec("zahl_mds", "UNS16", _S),
    Spec("achs_mds[]", "STRING", _S),
    Spec("achs_mds_log_ax_nr[]", "UNS16", _S, lo=1),
    Spec("vol_comp[].max_records", "UNS32", _S),
    Spec("vol_comp[].file_name", "STRING", _S),
    # ---- axis parameter list [AXIS]
    Spec("kopf.achs_nr", "UNS16", _A, lo=1),
    Spec("kopf.log_achs_name", "STRING", _A),
    # backlash (000 §2.3)
    Spec("getriebe[].lose", "SGN16", _A, "P-AXIS-00103", _BL),
    Spec("lr_param.anwahl_losekomp", "UNS16", _A, "P-AXIS-00021", _BL, 0, 2),
    Spec("lr_param.n_backlash_cyc", "UNS16", _A, "P-AXIS-00243", _BL, 0, 20),
    # temperature (000 §3.2)
    Spec("lr_param.temp_comp", "BOOLEAN", _A, "P-AXIS-00271", _TE),
    Spec("lr_param.temp_comp_position_0", "SGN32", _A, "P-AXIS-00272", _TE),
    Spec("lr_param.temp_comp_offset_0", "SGN32", _A, "P-AXIS-00273", _TE),
    Spec("lr_param.temp_comp_coefficient", "REAL64", _A, "P-AXIS-00274", _TE, -10000, 10000),
    Spec("lr_param.temp_comp_n_cycles", "UNS16", _A, "P-AXIS-00275", _TE, 0, 20),
    Spec("lr_param.temp_comp_manual_activation", "BOOLEAN", _A, "P-AXIS-00482", _TE),
    # selection of the list-based compensations (000 §4.x.1.2)
    Spec("lr_param.crosscomp", "BOOLEAN", _A, "P-AXIS-00047"),
    Spec("lr_param.crosscomp2", "BOOLEAN", _A, "P-AXIS-00174"),
    Spec("lr_param.ssfk", "BOOLEAN", _A, "P-AXIS-00175"),
    Spec("lr_param.frict_comp", "BOOLEAN", _A, "P-AXIS-00522"),
    Spec("lr_param.crosstalk", "BOOLEAN", _A, "P-AXIS-00789"),
    Spec("lr_param.prog_movement_requires_compensations", "MASK", _A, "P-AXIS-00465"),
    # emulator entries (documented in axislist.py)
    Spec("kenngr.achs_typ", "UNS16", _A, "emulator", lo=1, hi=4),
    Spec("kenngr.modulo_calc", "BOOLEAN", _A, "emulator"),
    Spec("kenngr.modulo_wert", "SGN64", _A, "emulator", lo=1),
    Spec("getriebe[].vb_max", "UNS32", _A, "emulator", lo=1),
    Spec("getriebe[].a_max", "REAL64", _A, "emulator", lo=1e-9, hi=1e9),
    Spec("sim.homed", "BOOLEAN", _A, "emulator"),
    Spec("sim.start_position", "SGN64", _A, "emulator"),
    # volumetric compensation limit (004 p.14)
    Spec("lr_param.vol_comp.s_limit", "UNS32", _A, "P-AXIS-00525"),
    # ---- compensation value list [COMP]: header (002 §2)
    Spec("kopf.achs_nr", "UNS16", _C, "P-COMP-00001", lo=1),
    Spec("kopf.log_achs_nr", "UNS16", _C, "P-COMP-00001", None, 1, None, "kopf.achs_nr", True),
    # "Maximum 16 characters" (002/003 §2.2)
    Spec("kopf.log_achs_name", "STRING", _C, "P-COMP-00002", max_len=16),
    # cross compensation (002 §3.1, 000 §4.2)
    Spec("kw.crosscomp.max_points", "UNS32", _C, "P-COMP-00060", _CR),
    Spec("kw.crosscomp.unit", "BOOLEAN", _C, "P-COMP-00003", _CR),
    Spec("kw.crosscomp.last_index", "SGN32", _C, "P-COMP-00004", _CR, 0),
    Spec("kw.crosscomp.master_ax_nr", "UNS16", _C, "P-COMP-00005", _CR, 1),
    Spec("kw.crosscomp.n_cycles", "UNS16", _C, "P-COMP-00026", _CR, 0, 20),
    Spec("kw.crosscomp.manual_activation", "BOOLEAN", _C, "P-COMP-00029", _CR),
    Spec("kw.crosscomp.table[].setpoint", "SGN32", _C, "P-COMP-00006", _CR),
    Spec("kw.crosscomp.table[].correction", "SGN32", _C, "P-COMP-00007", _CR),
    # plane compensation (002 §3.2, 000 §4.3)
    Spec("kw.crosscomp2.max_points", "UNS32", _C, "P-COMP-00061", _PL),
    Spec("kw.crosscomp2.unit", "BOOLEAN", _C, "P-COMP-00008", _PL),
    Spec("kw.crosscomp2.grid", "STRING", _C, "P-COMP-00031", _PL),
    Spec("kw.crosscomp2.interval", "UNS32", _C, "P-COMP-00009", _PL, 1),
    Spec("kw.crosscomp2.interval1", "UNS32", _C, "P-COMP-00032", _PL, 1),
    Spec("kw.crosscomp2.interval2", "UNS32", _C, "P-COMP-00033", _PL, 1),
    Spec("kw.crosscomp2.last_index_master1", "SGN32", _C, "P-COMP-00010", _PL, 0),
    Spec("kw.crosscomp2.last_index_master2", "SGN32", _C, "P-COMP-00011", _PL, 0),
    Spec("kw.crosscomp2.start_position_master1", "SGN32", _C, "P-COMP-00012", _PL),
    Spec("kw.crosscomp2.start_position_master2", "SGN32", _C, "P-COMP-00013", _PL),
    Spec("kw.crosscomp2.master1_ax_nr", "UNS16", _C, "P-COMP-00014", _PL, 1),
    Spec("kw.crosscomp2.master2_ax_nr", "UNS16", _C, "P-COMP-00015", _PL, 1),
    Spec("kw.crosscomp2.n_cycles", "UNS16", _C, "P-COMP-00027", _PL, 0, 20),
    Spec("kw.crosscomp2.manual_activation", "BOOLEAN", _C, "P-COMP-00030", _PL),
    Spec("kw.crosscomp2.table[][].correction", "SGN32", _C, "P-COMP-00016", _PL),
    Spec(
        "kw.crosscomp2.table[][]",
        "SGN32",
        _C,
        "P-COMP-00016",
        _PL,
        canonical="kw.crosscomp2.table[][].correction",
    ),
    # leadscrew error compensation (002 §3.3, 000 §4.4)
    Spec("kw.ssfk.max_points", "UNS32", _C, "P-COMP-00059", _LE),
    Spec("kw.ssfk.unit", "BOOLEAN", _C, "P-COMP-00017", _LE),
    Spec("kw.ssfk.interval", "SGN32", _C, "P-COMP-00018", _LE, 0),
    Spec("kw.ssfk.kw_startpos", "SGN32", _C, "P-COMP-00019", _LE),
    Spec("kw.ssfk.kw_nr_max", "SGN32", _C, "P-COMP-00020", _LE, 0),
    Spec("kw.ssfk.bilateral", "BOOLEAN", _C, "P-COMP-00021", _LE),
    Spec("kw.ssfk.modulo", "BOOLEAN", _C, "P-COMP-00022", _LE),
    Spec("kw.ssfk.manual_activation", "BOOLEAN", _C, "P-COMP-00028", _LE),
    Spec("kw.ssfk.set_pos_without_comp", "BOOLEAN", _C, "P-COMP-00057", _LE),
    Spec("kw.ssfk.table[].pos", "SGN32", _C, "P-COMP-00023", _LE),
    Spec("kw.ssfk.table[].neg", "SGN32", _C, "P-COMP-00024", _LE),
    Spec("kw.ssfk.table[].setpoint", "SGN64", _C, "P-COMP-00025", _LE),
    # friction compensation (002 §3.4, 000 §4.5)
    Spec("frict_comp.max_points", "UNS32", _C, "P-COMP-00062", _FR),
    Spec("frict_comp.mode", "UNS16", _C, "P-COMP-00041", _FR),
    Spec("frict_comp.table_entries", "UNS16", _C, "P-COMP-00042", _FR),
    Spec("frict_comp.position_delay", "SGN32", _C, "P-COMP-00043", _FR),  # 0..10: warned
    Spec("frict_comp.reversal_lookahead", "UNS16", _C, "P-COMP-00044", _FR, 0, 4),
    Spec("frict_comp.scaling_factor", "SGN16", _C, "P-COMP-00045", _FR),
    Spec("frict_comp.delay_cycles", "SGN16", _C, "P-COMP-00058", _FR, 0, 248),
    Spec("frict_comp.table[].in", "SGN32", _C, "P-COMP-00046", _FR),  # >= 0: 110591
    Spec("frict_comp.table[].out", "SGN32", _C, "P-COMP-00047", _FR),
    # crosstalk compensation, new model (002 §3.5, 000 §4.6)
    Spec("kw.crosstalk.mode", "UNS08", _C, "P-COMP-00082", _CT),  # 1..3: own check
    Spec("kw.crosstalk.master_dyn_ax_nr", "UNS16", _C, "P-COMP-00063", _CT),
    Spec("kw.crosstalk.master_pos1_ax_nr", "UNS16", _C, "P-COMP-00080", _CT),
    Spec("kw.crosstalk.master_pos2_ax_nr", "UNS16", _C, "P-COMP-00081", _CT),
    Spec("kw.crosstalk.n_cycles", "UNS16", _C, "P-COMP-00064", _CT, 0, 20),
    Spec("kw.crosstalk.manual_activation", "BOOLEAN", _C, "P-COMP-00065", _CT),
    Spec("kw.crosstalk.max_points", "UNS32", _C, "P-COMP-00083", _CT),  # <= 15: own check
    Spec("kw.crosstalk.acceleration", "SGN32", _C, "P-COMP-00066", _CT),  # > 0: own check
    Spec("kw.crosstalk.deceleration", "SGN32", _C, "P-COMP-00067", _CT),  # < 0: own check
    Spec("kw.crosstalk.velocity_dependent", "BOOLEAN", _C, "P-COMP-00084", _CT),
    Spec("kw.crosstalk.position[].ax_1", "SGN64", _C, "P-COMP-00085", _CT),
    Spec("kw.crosstalk.position[].ax_2", "SGN64", _C, "P-COMP-00086", _CT),
]

#: The four correction columns of the new crosstalk model with their P-COMP IDs (002
#: §3.5.13-16) and the alternative names the mode-3 example of 000 p.92 prints. Those
#: name the signs of the acceleration and the velocity: `acc_neg_vel_neg` is a negative
#: acceleration while moving in the negative direction, i.e. accelerating in the
#: negative direction (a·v > 0), and `acc_pos_vel_neg` is decelerating there.
CROSSTALK_CORRECTIONS: dict[str, tuple[str, str]] = {
    "correction_accelerate_dir_pos": ("P-COMP-00087", "acc_pos_vel_pos_correction"),
    "correction_accelerate_dir_neg": ("P-COMP-00088", "acc_neg_vel_neg_correction"),
    "correction_decelerate_dir_pos": ("P-COMP-00089", "acc_neg_vel_pos_correction"),
    "correction_decelerate_dir_neg": ("P-COMP-00090", "acc_pos_vel_neg_correction"),
}
for _col, (_pid, _alt) in CROSSTALK_CORRECTIONS.items():
    _full = f"kw.crosstalk.position[].{_col}"
    _SPECS.append(Spec(_full, "SGN64", _C, _pid, _CT))
    _SPECS.append(Spec(f"kw.crosstalk.position[].{_alt}", "SGN64", _C, _pid, _CT, canonical=_full))
_SPECS += [
    # mode-3 example names (000 p.92)
    Spec(
        "kw.crosstalk.acceleration_pos",
        "SGN32",
        _C,
        "P-COMP-00066",
        _CT,
        canonical="kw.crosstalk.acceleration",
    ),
    Spec(
        "kw.crosstalk.acceleration_neg",
        "SGN32",
        _C,
        "P-COMP-00067",
        _CT,
        canonical="kw.crosstalk.deceleration",
    ),
    # crosstalk compensation, old model (001 §4.5, 003 §3.5)
    Spec(
        "kw.crosstalk.master_ax_nr",
        "UNS16",
        _C,
        "P-COMP-00063",
        _CT,
        canonical="kw.crosstalk.master_dyn_ax_nr",
    ),
    Spec("kw.crosstalk.last_index", "SGN32", _C, "P-COMP-00065 (old)", _CT),  # 0..4: own
    Spec("kw.crosstalk.table[].acceleration", "SGN32", _C, "P-COMP-00066 (old)", _CT),
    Spec("kw.crosstalk.table[].correction", "SGN32", _C, "P-COMP-00067 (old)", _CT),
]

# ---- volumetric compensation list [VOLC] (004 §3, p.11-17, p.23): the manual names
# P-VOLC-00012 (file[j]), -00017 (manual_activation) and -00018 (filter_steps) only
_V = ListKind.VOLC
_SPECS += [Spec(axis.lower(), "UNS16", _V, lo=1) for axis in "XYZABC"]
_SPECS += [
    Spec("chain", "STRING", _V),
    Spec("workpiece_axes", "UNS16", _V, lo=0, hi=6),
    Spec("file[]", "STRING", _V, "P-VOLC-00012"),
    Spec("file_format[]", "STRING", _V),
    Spec("negate", "STRING", _V),
    Spec("set_to_zero", "STRING", _V),
    Spec("alternative_model", "BOOLEAN", _V),
    Spec("filter_steps", "UNS32", _V, "P-VOLC-00018"),
    Spec("manual_activation", "BOOLEAN", _V, "P-VOLC-00017"),
    Spec("interpolation", "STRING", _V),
    Spec("enable_splicing", "BOOLEAN", _V),
    Spec("associate_to_channel", "BOOLEAN", _V),
    Spec("diagnosis_file", "STRING", _V),
]

SPECS: dict[tuple[ListKind, str], Spec] = {(s.list, s.name): s for s in _SPECS}


def lookup(kind: ListKind, base: str) -> Spec | None:
    """The spec of entry `base` (indices written `[]`) in a list of `kind`, if known."""
    return SPECS.get((kind, base))


#: Names a list of each kind reads without a warning (the manuals' misprints left out).
_NAMES: dict[ListKind, list[str]] = {
    kind: [s.name for s in _SPECS if s.list == kind and not s.alias_warning] for kind in ListKind
}


@functools.lru_cache(maxsize=1024)
def nearest_name(kind: ListKind, base: str) -> str | None:
    """The known entry of a list of `kind` most like the unknown `base` (a misspelling,
    e.g. `lr_param.temp_comp_coefficent`), or None if none is close."""
    near = difflib.get_close_matches(base, _NAMES[kind], n=1, cutoff=0.8)
    return near[0] if near else None


def list_kinds_of(base: str) -> list[ListKind]:
    """The kinds of list that know the entry `base` (for "wrong list" hints)."""
    return [kind for kind in ListKind if (kind, base) in SPECS]


_CLASS_BY_NAME: dict[str, str] = {
    s.name: "string" if s.type in STRING_TYPES else "mask" if s.type in MASK_TYPES else "number"
    for s in _SPECS
}


def value_class(base: str) -> str:
    """How the tokenizer reads the value of `base`: "string", "mask" or "number".

    002 §1.4: after a numeric value a blank starts a comment; after a string only `(`.
    Unknown entries are read like numbers (they are ignored anyway). An entry name has
    the same type in every list kind, so no list kind is needed.
    """
    return _CLASS_BY_NAME.get(base, "number")


_INT = re.compile(r"[+-]?(?:0[xX][0-9a-fA-F]+|\d+)")
_REAL = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_BOOL = {"0": False, "1": True, "false": False, "true": True}
#: Symbols of the P-AXIS-00465 bit mask (000 §5.3 p.98).
MASK_SYMBOLS = {
    k.name: k
    for k in (CompKind.BACKLASH, CompKind.LEAD, CompKind.TEMP, CompKind.CROSS, CompKind.PLANE)
}


#: A converted entry value (`convert`): BOOLEAN, the integer types, REAL64, STRING, MASK.
Value = bool | int | float | str | CompKind


def convert(spec: Spec, text: str) -> Value:
    """Turn value text into a Python value of the spec's type; ValueError if defective.

    BOOLEAN: 0/1 (002 §1.3) and TRUE/FALSE in any case (000 p.91 examples). Integers:
    decimal, or hexadecimal `0x..`. REAL64: decimal with optional exponent. MASK: a number
    or symbols joined by `|` (000 §5.3, `LEAD | CROSS`).
    """
    t = spec.type
    if t == "STRING":
        return text
    if t == "BOOLEAN":
        try:
            return _BOOL[text.lower()]
        except KeyError:
            raise ValueError(f"{text!r} is not a BOOLEAN (0, 1, TRUE, FALSE)") from None
    if t == "REAL64":
        if not _REAL.fullmatch(text):
            raise ValueError(f"{text!r} is not a REAL64 number")
        return float(text)
    if t == "MASK":
        return _convert_mask(text)
    if not _INT.fullmatch(text):
        raise ValueError(f"{text!r} is not an integer ({t})")
    return int(text, 0) if "x" in text.lower() else int(text)


def _convert_mask(text: str) -> CompKind:
    if _INT.fullmatch(text):
        value = int(text, 0) if "x" in text.lower() else int(text)
        known = sum(MASK_SYMBOLS.values(), CompKind(0))
        if value < 0 or value & ~int(known):
            raise ValueError(f"{text!r}: only the bits 0x1..0x10 are defined")
        return CompKind(value)
    mask = CompKind(0)
    for sym in (s.strip().upper() for s in text.split("|")):
        if sym not in MASK_SYMBOLS:
            raise ValueError(
                f"unknown compensation symbol {sym!r} (BACKLASH LEAD TEMP CROSS PLANE)"
            )
        mask |= MASK_SYMBOLS[sym]
    return mask


def out_of_range(spec: Spec, value: object) -> str:
    """A message if a numeric value lies outside the documented range, else ""."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return ""
    lo, hi = spec.bounds()
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        lo_s = "" if lo is None else f"{lo:g} <= "
        hi_s = "" if hi is None else f" <= {hi:g}"
        return f"value {value:g} outside {lo_s}{spec.name.rsplit('.', 1)[-1]}{hi_s} ({spec.type})"
    return ""
