"""The one table mapping every list validation check to its error ID (docs/design.md §4).

The manuals list error IDs per compensation (000 §2–§4, 002) but give a meaning only for
110392 (backlash configuration error), 110591/110592 (friction) and 110638–110641
(`max_points` changed). Every other assignment below is the emulator's choice, made from
the IDs that the manual lists for that compensation. Temperature compensation has no
manual error ID: its checks use the emulator ID `EMU_TEMP_ERROR` (990271, after
P-AXIS-00271), which no manual defines. List-level warnings (unknown entries, defective
values) have ID 0, like the `Diagnostic` default.

`docs/list_checks.md` is generated from this table by `checks_markdown()`:
`python -c "from geo_server.listfile import checks_markdown as m; print(m(), end='')"`.
"""

from __future__ import annotations

from dataclasses import dataclass

from geo_server.model import COMP_NAMES, CompKind

#: Emulator-chosen error ID of temperature-compensation configuration errors.
EMU_TEMP_ERROR = 990271
#: Emulator-chosen error ID of volumetric-compensation errors (004 names no error ID;
#: after P-AXIS-00525, the volumetric limit).
EMU_VOLC_ERROR = 990525


@dataclass(frozen=True)
class Check:
    """One validation check: what it finds, which ID it reports, whether it deactivates."""

    key: str
    comp: CompKind | None
    error_id: int
    meaning: str
    listed_in: str
    deactivates: bool = True
    severity: str = "warning"
    #: the entry's value is replaced by its default (`geo-server check` exits 1)
    replaces: bool = False


_BL, _TE, _CR, _PL = CompKind.BACKLASH, CompKind.TEMP, CompKind.CROSS, CompKind.PLANE
_LE, _FR, _CT = CompKind.LEAD, CompKind.FRICT, CompKind.CROSSTALK
_M000_BL = "000 §2.4 p.13 (stated meaning)"
_M000_CR = "000 §4.2 p.37; 001"
_M000_PL = "000 §4.3.3 p.51; 001"
_M000_LE = "000 §4.4.3 p.63; 001"
_M000_FR = "000 §4.5.1.2 p.71 (stated meaning)"
_M000_CT = "000 §4.6.4 p.92–93"
_EMU = "none (emulator ID)"
_M004 = "004 (no ID; emulator ID)"
_LIST = "002/003 §1.3 (warning, no ID)"

CHECKS: tuple[Check, ...] = (
    # ---- list level (no compensation deactivated)
    Check("list.unknown", None, 0, "unknown entry: ignored", _LIST, False),
    Check(
        "list.defective",
        None,
        0,
        "value cannot be read as the entry's data type (e.g. `abc` for SGN32), or a "
        "non-compensation entry is outside its range: the default is used",
        _LIST,
        False,
        replaces=True,
    ),
    Check(
        "list.alias",
        None,
        0,
        "a name as misprinted in a manual is accepted: `kopf.log_achs_nr` (002/003 p.29) "
        "for `kopf.achs_nr`, a blank after a dot (`lr_param. n_backlash_cyc`, 000 p.13)",
        _LIST,
        False,
    ),
    Check("list.duplicate", None, 0, "entry given twice: the last one counts", _LIST, False),
    Check(
        "list.length",
        None,
        0,
        "a text longer than its documented maximum: `kopf.log_achs_name` of a compensation "
        "value list has at most 16 characters (P-COMP-00002); the value is kept",
        "002/003 §2.2 (no ID)",
        False,
    ),
    Check(
        "list.ignored",
        None,
        0,
        "entry read but not used (`diagnosis_file` of a VOLC list, gear stages other than "
        "`getriebe[0]`, explicit setpoints of an equidistant LSEC table, `neg` values of "
        "a unilateral table, the other crosstalk dialect's entries)",
        _LIST,
        False,
    ),
    Check(
        "list.axis",
        None,
        0,
        "axis parameter list without logical axis number, or the same axis twice: the "
        "list is skipped (an error: `check` exits 1, a reload is rejected)",
        "none (emulator)",
        False,
        "error",
    ),
    Check(
        "list.axis_mismatch",
        None,
        0,
        "`kopf.achs_nr` of an axis parameter list differs from the number the start-up "
        "list gives it (`achs_mds_log_ax_nr[i]`): the start-up list's number is used",
        "none (emulator)",
        False,
    ),
    # ---- backlash (000 §2)
    Check(
        "backlash.range",
        _BL,
        110392,
        "`lr_param.anwahl_losekomp` not 0…2, `getriebe[0].lose` outside SGN16, or "
        "`lr_param.n_backlash_cyc` outside 0…20",
        _M000_BL,
    ),
    # ---- temperature (000 §3)
    Check(
        "temp.range",
        _TE,
        EMU_TEMP_ERROR,
        "`temp_comp_coefficient` outside −10000…10000, `temp_comp_n_cycles` outside "
        "0…20, or `temp_comp_position_0`/`temp_comp_offset_0` outside SGN32",
        _EMU,
    ),
    # ---- cross (000 §4.2, 002 §3.1)
    Check(
        "cross.missing",
        _CR,
        70242,
        "`lr_param.crosscomp 1` but no `kw.crosscomp` table for the axis",
        _M000_CR,
    ),
    Check("cross.master", _CR, 70244, "`kw.crosscomp.master_ax_nr` missing", _M000_CR),
    Check(
        "cross.axis",
        _CR,
        70245,
        "the master axis is not an axis of the machine or is the slave itself; or the "
        "list's `kopf.achs_nr` names no axis of the machine / disagrees with the start-up list",
        _M000_CR,
    ),
    Check("cross.last_index", _CR, 70246, "`kw.crosscomp.last_index` missing", _M000_CR),
    Check(
        "cross.size",
        _CR,
        70247,
        "`last_index` >= `max_points` (002 §3.1.2: 0 <= last_index < max_points)",
        _M000_CR,
    ),
    Check("cross.index", _CR, 70248, "a `table[i]` index is negative or > last_index", _M000_CR),
    Check("cross.order", _CR, 70249, "setpoints not strictly ascending", _M000_CR),
    Check(
        "cross.range",
        _CR,
        70250,
        "a value outside its documented range (n_cycles 0…20, unit/manual_activation "
        "0/1, setpoint/correction SGN32)",
        _M000_CR,
    ),
    Check(
        "cross.incomplete",
        _CR,
        70432,
        "setpoint or correction of a point 0…last_index missing",
        _M000_CR,
    ),
    # ---- plane (000 §4.3, 002 §3.2)
    Check(
        "plane.missing",
        _PL,
        70182,
        "`lr_param.crosscomp2 1` but no `kw.crosscomp2` table, or a required entry "
        "missing (master1/2_ax_nr, last_index_master1/2, interval or interval1/2)",
        _M000_PL,
    ),
    Check(
        "plane.axis",
        _PL,
        70183,
        "a master axis is not an axis of the machine, or both masters are the same axis "
        "(one of them may be the slave itself, 001 §4.4); or `kopf.achs_nr` names no axis "
        "/ disagrees with the start-up list",
        _M000_PL,
    ),
    Check(
        "plane.size",
        _PL,
        70184,
        "(last_index_master1+1)·(last_index_master2+1) > max_points (002 §3.2.1); without "
        "max_points a last index above 100 (000 p.44); or a `table[j][i]` index beyond the "
        "last indices",
        _M000_PL,
    ),
    Check(
        "plane.range",
        _PL,
        70185,
        "a value outside its documented range (interval <= 0, grid not QUADRATIC/"
        "RECTANGULAR, n_cycles 0…20, corrections SGN32, …)",
        _M000_PL,
    ),
    # ---- LSEC (000 §4.4, 002 §3.3)
    Check(
        "lead.missing",
        _LE,
        110217,
        "`lr_param.ssfk 1` but no `kw.ssfk` table, or `kw_nr_max` missing/0; or "
        "`kopf.achs_nr` names no axis / disagrees with the start-up list",
        _M000_LE,
    ),
    Check(
        "lead.size",
        _LE,
        110218,
        "`kw_nr_max` >= `max_points` (must be smaller, 000 p.57)",
        _M000_LE,
    ),
    Check(
        "lead.bilateral",
        _LE,
        110392,
        "bilateral table (which carries the backlash, 000 §4.4) with a `neg` value missing",
        _M000_LE,
    ),
    Check(
        "lead.index",
        _LE,
        110474,
        "a `table[i]` index outside 0…kw_nr_max−1 (docs/design.md §12)",
        _M000_LE,
    ),
    Check(
        "lead.order",
        _LE,
        110476,
        "explicit setpoints (interval 0) not strictly ascending",
        _M000_LE,
    ),
    Check(
        "lead.setpoint",
        _LE,
        110477,
        "interval 0 (non-equidistant) and a `table[i].setpoint` missing",
        _M000_LE,
    ),
    Check(
        "lead.range",
        _LE,
        110478,
        "a value outside its documented range (interval < 0, kw_nr_max < 0, "
        "pos/neg SGN32, setpoint SGN64, unit/bilateral/modulo 0/1)",
        _M000_LE,
    ),
    Check(
        "lead.modulo",
        _LE,
        110479,
        "`kw.ssfk.modulo 1` but the axis is not a modulo axis, or the first and last "
        "setpoints are not one modulo period (`kenngr.modulo_wert`) apart",
        _M000_LE,
    ),
    Check(
        "lead.axis_type",
        _LE,
        110480,
        "LSEC on a spindle (P-AXIS-00175: axis types T, R only)",
        _M000_LE,
    ),
    Check("lead.pos", _LE, 110590, "a `table[i].pos` value missing", _M000_LE),
    # ---- friction (000 §4.5, 002 §3.4)
    Check(
        "frict.velocity",
        _FR,
        110591,
        "negative or not strictly ascending input velocities `table[i].in`",
        _M000_FR,
    ),
    Check(
        "frict.values",
        _FR,
        110592,
        "unknown mode (only 0 and 3; 0 while `lr_param.frict_comp 1`), no values "
        "(no list, table_entries 0, a `table[i].in`/`.out` missing), table_entries > "
        "max_points, an index >= table_entries, reversal_lookahead/delay_cycles/"
        "scaling_factor out of range, or `kopf.achs_nr` names no axis",
        _M000_FR,
    ),
    Check(
        "frict.position_delay",
        _FR,
        0,
        "`position_delay` outside 0…10: warning only, value kept (the manual's own "
        "example, 000 p.70, uses 30)",
        "none (warning only)",
        False,
    ),
    # ---- crosstalk (000 §4.6 new model; 001 §4.5 / 003 §3.5 old model)
    Check(
        "crosstalk.missing",
        _CT,
        70622,
        "`lr_param.crosstalk 1` but no `kw.crosstalk` entries; or `kopf.achs_nr` names "
        "no axis / disagrees with the start-up list",
        _M000_CT,
    ),
    Check(
        "crosstalk.master",
        _CT,
        70625,
        "`master_dyn_ax_nr` (old: `master_ax_nr`) missing, not an axis, or the slave",
        _M000_CT,
    ),
    Check(
        "crosstalk.mode",
        _CT,
        70626,
        "`mode` not 1…3, or entries of both dialects (`table[i]` and `mode`/`position[i]`)",
        _M000_CT,
    ),
    Check(
        "crosstalk.acceleration",
        _CT,
        70627,
        "`acceleration` (`acceleration_pos`) missing or <= 0",
        _M000_CT,
    ),
    Check(
        "crosstalk.deceleration",
        _CT,
        70629,
        "`deceleration` (`acceleration_neg`) missing or >= 0",
        _M000_CT,
    ),
    Check(
        "crosstalk.range",
        _CT,
        70631,
        "a value outside its documented range (n_cycles 0…20, booleans, SGN64 positions)",
        _M000_CT,
    ),
    Check(
        "crosstalk.points",
        _CT,
        70632,
        "more than 15 test points (`max_points` > 15 or a `position[i]` index >= 15), or an "
        "index >= `max_points` when `max_points` > 0",
        _M000_CT,
    ),
    Check(
        "crosstalk.adapt1",
        _CT,
        70657,
        "mode 2/3: `master_pos1_ax_nr` missing or not an axis of the machine (the "
        "compensated axis itself is allowed)",
        "000 §4.6.4 p.92–93 (new model only)",
    ),
    Check(
        "crosstalk.adapt2",
        _CT,
        70658,
        "mode 3: `master_pos2_ax_nr` missing, not an axis, or equal to master_pos1_ax_nr",
        "000 §4.6.4 p.92–93 (new model only)",
    ),
    Check(
        "crosstalk.records",
        _CT,
        70659,
        "too few test records (mode 1: position[0]; mode 2: 2; mode 3: 3) or a gap in the "
        "`position[i]` indices",
        "000 §4.6.4 p.92–93 (new model only)",
    ),
    Check(
        "crosstalk.geometry",
        _CT,
        70660,
        "mode 2: `ax_1` not strictly ascending; mode 3: test points repeated or all on one line",
        "000 §4.6.4 p.92–93 (new model only)",
    ),
    Check(
        "crosstalk.old_table",
        _CT,
        70630,
        "old model: `last_index` missing or not 0…4 (more than 5 points), an index > "
        "last_index, an acceleration/correction missing, accelerations not strictly ascending",
        "001 §4.5 (old model only)",
    ),
)

CHECKS += (
    # ---- volumetric compensation (004, docs/volumetric.md)
    Check(
        "volc.config",
        None,
        EMU_VOLC_ERROR,
        "VOLC list unusable: no `chain` or one with unknown or repeated letters, not "
        "exactly the linear axes X Y Z, a chain axis without its axis number or one that "
        "is no axis of the machine, `workpiece_axes` beyond the chain, a `file[j]` "
        "without `file_format[j]` or an unknown format, an unknown interpolation mode: "
        "that compensation is not available",
        _M004,
        False,
        "error",
    ),
    Check(
        "volc.file",
        None,
        EMU_VOLC_ERROR,
        "a VOLC list or correction file missing, unreadable or malformed, records not on a "
        "grid, a parameter unknown or over the wrong arguments, more records than "
        "`vol_comp[i].max_records` (004 p.12): that compensation is not available",
        _M004,
        False,
        "error",
    ),
    Check(
        "volc.s_limit",
        None,
        EMU_VOLC_ERROR,
        "an axis of an activated compensation without `lr_param.vol_comp.s_limit` "
        "(P-AXIS-00525, 004 p.14: activation refused), or its correction beyond it "
        "(the compensation is switched off, the program stopped)",
        "004 p.14 (stated meaning; emulator ID)",
        False,
        "error",
    ),
)

CHECK_BY_KEY: dict[str, Check] = {c.key: c for c in CHECKS}

#: Generic "value outside its documented range" check per compensation.
RANGE_CHECK: dict[CompKind, str] = {
    _BL: "backlash.range",
    _TE: "temp.range",
    _CR: "cross.range",
    _PL: "plane.range",
    _LE: "lead.range",
    _FR: "frict.values",
    _CT: "crosstalk.range",
}

#: Check reported for every compensation of a list whose axis is unusable.
HEADER_CHECK: dict[CompKind, str] = {
    _CR: "cross.axis",
    _PL: "plane.axis",
    _LE: "lead.missing",
    _FR: "frict.values",
    _CT: "crosstalk.missing",
}

#: Error IDs for a `max_points` change on reload (002 §3.x.1, stated meaning).
MAX_POINTS_IDS: dict[CompKind, int] = {_LE: 110638, _CR: 110639, _PL: 110640, _FR: 110641}


def checks_markdown() -> str:
    """The check table as Markdown (the source of `docs/list_checks.md`)."""
    lines = [
        "# List validation checks and their error IDs",
        "",
        "Generated from `geo_server/listfile/checks.py` by `checks_markdown()`; do not edit.",
        "",
        "A check that deactivates switches the compensation off for that axis only; the",
        "diagnostic names file, line, entry and error ID (docs/design.md §4). IDs with a meaning",
        "stated by the manual keep it; the others are the emulator's assignment from the",
        f"IDs the manual lists for that compensation. Temperature uses {EMU_TEMP_ERROR},",
        "an emulator ID (the manuals list none).",
        "",
        "| Check | Compensation | Error ID | Deactivates | Meaning | ID listed in |",
        "|---|---|---|---|---|---|",
    ]
    for c in CHECKS:
        comp = COMP_NAMES[c.comp] if c.comp is not None else "—"
        ident = str(c.error_id) if c.error_id else "—"
        deact = "yes" if c.deactivates else "no"
        lines.append(f"| `{c.key}` | {comp} | {ident} | {deact} | {c.meaning} | {c.listed_in} |")
    lines += [
        "",
        "Reload only (docs/design.md §4, 002 §3.x.1, stated meaning): a changed `max_points` "
        "rejects",
        "the reload with "
        + ", ".join(f"{v} ({COMP_NAMES[k]})" for k, v in MAX_POINTS_IDS.items())
        + ".",
        "",
    ]
    return "\n".join(lines)
