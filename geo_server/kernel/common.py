"""Static interpretation of a `MachineConfig` for the kernel (its column layout, which
compensation is selected at start-up, which sin² length belongs to which column).

The test oracle (tests/support/reference.py) states these rules once more from the
manuals, so that it stays independent of the kernel (issue 33).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from geo_server.model import AxisConfig, AxisParams, CompKind, CrossComp, CrosstalkComp, PlaneComp

#: Column index c of every per-compensation array `[n, 7]`.
COMP_ORDER: tuple[CompKind, ...] = (
    CompKind.BACKLASH,
    CompKind.TEMP,
    CompKind.CROSS,
    CompKind.PLANE,
    CompKind.LEAD,
    CompKind.FRICT,
    CompKind.CROSSTALK,
)
BC, TEMP, CROSS, PLANE, LEAD, FRICT, CROSSTALK = range(7)
#: Every compensation (`COMP OFF_ALL`, 000 §5.1 p.94).
ALL_KINDS = CompKind(sum(COMP_ORDER))
COLUMN: dict[CompKind, int] = {kind: i for i, kind in enumerate(COMP_ORDER)}


def hold_columns(kinds: CompKind) -> list[int]:
    """Columns whose offset `COMP … NO_MOVE` holds back until the axis' next motion
    (000 §5.1 p.94): every position compensation. Friction is a current, not a position
    offset, so it has nothing to hold and switches at once."""
    return [COLUMN[k] for k in COMP_ORDER if kinds & k and k is not CompKind.FRICT]


def initial_direction(anwahl_losekomp: int) -> float:
    """Start-up direction state (000 §2.3.2, P-AXIS-00021; docs/design.md §3.6).

    1 = last motion positive, 2 = last motion negative; 0 (backlash off) → positive.
    """
    return -1.0 if anwahl_losekomp == 2 else 1.0


def reload_changes(
    old: AxisConfig, new: AxisConfig, tempc_attrs: Sequence[str]
) -> tuple[list[tuple[int, bool]], list[tuple[int, float]]]:
    """What a reload re-initialises for one axis (docs/design.md §12 "reload"): only
    what the new lists changed, so a COMP OFF or a live TEMPC write survives a reload
    that does not touch it. Returns (selection column, selected) pairs and (TEMPC row of
    `tempc_attrs` — `temperature.Bindings.attrs` — new value) pairs."""
    so, sn = initial_selection(old), initial_selection(new)
    selection = [(c, sn[c]) for c in range(len(sn)) if so[c] != sn[c]]
    po, pn = old.params, new.params
    tempc = [
        (row, float(getattr(pn, attr)))
        for row, attr in enumerate(tempc_attrs)
        if getattr(po, attr) != getattr(pn, attr)
    ]
    return selection, tempc


def initial_selection(ax: AxisConfig) -> list[bool]:
    """What `*::activated` reports at start-up, per column (docs/design.md §6.8).

    A compensation is selected by its axis parameter; compensations with
    `manual_activation` start deselected and need `COMP ON` (000 §5.1, p.94).
    TEMP: `lr_param.temp_comp` and not `temp_comp_manual_activation` (000 §3.2, p.17).
    BACKLASH: `lr_param.anwahl_losekomp` ≠ 0 (000 §2.3.2). FRICT has no manual mode.
    """
    p, comp = ax.params, ax.comp
    cross = comp.cross if comp else None
    plane = comp.plane if comp else None
    lsec = comp.lsec if comp else None
    xtalk = comp.crosstalk if comp else None
    return [
        p.anwahl_losekomp != 0,
        p.temp_comp and not p.temp_comp_manual_activation,
        p.crosscomp and not (cross is not None and cross.manual_activation),
        p.crosscomp2 and not (plane is not None and plane.manual_activation),
        p.ssfk and not (lsec is not None and lsec.manual_activation),
        p.frict_comp,
        p.crosstalk and not (xtalk is not None and xtalk.manual_activation),
    ]


def filter_cycles(ax: AxisConfig) -> list[int]:
    """sin² length N of the step events of each column (docs/design.md §3.4, §3.5;
    N ≤ 1 is a jump → 1).

    BC and LSEC use `lr_param.n_backlash_cyc` (000 §2.3.2 P-AXIS-00243, which also names
    the bilateral LSEC reversal; the manual gives LSEC no own filter length, so its
    activation/deactivation uses it too). TEMP `temp_comp_n_cycles` (P-AXIS-00275),
    CROSS/PLANE/CROSSTALK their list's `n_cycles`. FRICT is not sin²-filtered (1).
    """
    p, comp = ax.params, ax.comp

    def n_of(part: CrossComp | PlaneComp | CrosstalkComp | None) -> int:
        return part.n_cycles if part is not None else 0

    ns = [
        p.n_backlash_cyc,
        p.temp_comp_n_cycles,
        n_of(comp.cross) if comp else 0,
        n_of(comp.plane) if comp else 0,
        p.n_backlash_cyc,
        1,
        n_of(comp.crosstalk) if comp else 0,
    ]
    return [max(1, int(n)) for n in ns]


def listed_kinds(p: AxisParams) -> CompKind:
    """The compensations the axis parameter list enables (000 §5.3 p.97: "enabled in the
    axis parameter list")."""
    return mask_of(
        kind
        for kind, on in (
            (CompKind.BACKLASH, p.anwahl_losekomp != 0),
            (CompKind.LEAD, p.ssfk),
            (CompKind.TEMP, p.temp_comp),
            (CompKind.CROSS, p.crosscomp),
            (CompKind.PLANE, p.crosscomp2),
            (CompKind.FRICT, p.frict_comp),
            (CompKind.CROSSTALK, p.crosstalk),
        )
        if on
    )


def mask_of(kinds: Iterable[CompKind]) -> CompKind:
    out = CompKind(0)
    for k in kinds:
        out |= k
    return out
