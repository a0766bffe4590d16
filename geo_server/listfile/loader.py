"""Start-up list [STUP] -> axis parameter lists [AXIS] + compensation value lists [COMP].

Start-up list entries (000 §4.1 p.26, 000 §4.1):

* `zahl_kw`, `achs_kw[i]`, `achs_kw_log_ax_nr[i]` — compensation value lists (manual);
* `zahl_mds`, `achs_mds[i]`, `achs_mds_log_ax_nr[i]` — axis parameter lists (emulator
  extension: the manuals print no start-up entry for them);
* `vol_comp[i].max_records`, `vol_comp[i].file_name` — volumetric compensations (004
  p.12, p.36), loaded by `geo_server.volcomp.config` (docs/volumetric.md).

File names are relative to the start-up list's folder; Windows `..\\listen\\x.lis` works.
The axis number of a list is `achs_*_log_ax_nr[i]`, else the list's `kopf.achs_nr`.
Without any axis parameter list, every compensation list's axis gets default parameters.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path, PureWindowsPath

from geo_server.errors import GeoError
from geo_server.listfile.axislist import axis_number, build_axis_params
from geo_server.listfile.checks import HEADER_CHECK, MAX_POINTS_IDS
from geo_server.listfile.complist import Ctx, build_comp_list, sections_present
from geo_server.listfile.schema import ListKind, list_kinds_of, lookup
from geo_server.listfile.syntax import NotAListFileError, ParsedList, parse_list
from geo_server.listfile.values import Reporter, Values, read_values
from geo_server.model import (
    AxisConfig,
    AxisParams,
    CompKind,
    CompList,
    CrossComp,
    Diagnostic,
    FrictComp,
    LsecComp,
    MachineConfig,
    PlaneComp,
    seal,
)
from geo_server.twin.file import TwinFileError, find_twin


class ListFileError(GeoError):
    """The lists cannot be read at all: a file missing, unreadable or not a list file
    (binary, UTF-16, a FIFO, nothing of its kind in it), or no axes."""

    def __init__(
        self, path: Path | str, line: int, message: str, earlier: Sequence[Diagnostic] = ()
    ) -> None:
        self.path, self.line, self.message = str(path), line, message
        #: what the lists read before this said (a typo in the start-up list that lost
        #: an axis comes before the twin file's complaint that the axis is missing)
        self.earlier = tuple(earlier)
        where = f"{self.path}:{line}" if line else self.path
        super().__init__(f"{where}: {message}")

    def report(self) -> list[str]:
        """The lines to show, the first cause first: the earlier diagnostics, then this."""
        return [*map(str, self.earlier), f"error: {self}"]


def load_machine(startup: Path | str, allow_dirs: Sequence[Path | str] = ()) -> MachineConfig:
    """Read the start-up list and every list it names; validate; never raise on content.

    The volumetric compensation's files are read only from the start-up list's folder
    and `allow_dirs` (`MachineConfig.file_roots`, docs/security.md). Raises
    `ListFileError` only if a list cannot be read, is not a list file, or no axis is
    defined.
    """
    startup = Path(startup)
    extra = tuple(Path(d) for d in allow_dirs)
    diags: list[Diagnostic] = []
    rep = Reporter(diags)
    stup = _read(startup, ListKind.STUP, rep)
    mds = _named_lists(stup, "mds", rep)
    kws = _named_lists(stup, "kw", rep)
    axes = _load_axes(startup.parent, startup, mds, rep)
    comp_values = [
        (nr, _read(_resolve(startup.parent, f, stup.path, ln), ListKind.COMP, rep))
        for nr, f, ln in kws
    ]
    if not axes:
        for nr, values in comp_values:
            nr = nr or int(values.get("kopf.achs_nr", 0))
            if nr and nr not in axes:
                axes[nr] = AxisParams(log_nr=nr)
    if not axes:
        raise ListFileError(startup, 0, "no axes: no axis parameter or compensation lists")
    configs = {nr: AxisConfig(params=axes[nr]) for nr in sorted(axes)}
    for nr, values in comp_values:
        _attach_comp(configs, nr, values, rep)
    _check_selected(configs, rep)
    # The twin's axis names are checked against the machine's, unless a list had to be
    # skipped already (its axis is missing for a reason the diagnostics name).
    skipped = any(d.severity == "error" and d.deactivated is None for d in diags)
    names = [] if skipped else [c.params.name or str(nr) for nr, c in configs.items()]
    try:
        twin = find_twin(startup, names)
    except TwinFileError as exc:
        raise ListFileError(exc.path, exc.line, exc.message, diags) from None
    # (imported here: geo_server.volcomp.config reads its lists with this package)
    from geo_server.volcomp.config import load_volumetric

    volumetric = load_volumetric(stup, startup.parent, axes, rep, (startup.parent, *extra))
    cfg = MachineConfig(
        startup_path=startup,
        axes=configs,
        diagnostics=diags,
        twin=twin,
        volumetric=volumetric,
        allow_dirs=extra,
    )
    seal(cfg)  # read-only from here on, for the machine and every interface
    return cfg


def _read(path: Path, kind: ListKind, rep: Reporter) -> Values:
    """Read one list of `kind`; a file that is no list of that kind is refused whole."""
    try:
        parsed = parse_list(path)
    except FileNotFoundError:
        raise ListFileError(path, 0, f"{kind.value} not found") from None
    except NotAListFileError as exc:
        raise ListFileError(path, exc.line, str(exc)) from None
    except OSError as exc:
        raise ListFileError(path, 0, f"{kind.value} unreadable: {exc}") from None
    if not any(lookup(kind, e.base) for e in parsed.entries):
        raise ListFileError(path, 0, _nothing_known(parsed, kind))
    return read_values(parsed, kind, rep)


def _nothing_known(parsed: ParsedList, kind: ListKind) -> str:
    """Why a list without a single entry of its kind is refused.

    002 §1.3 replaces defective entries by defaults so the controller starts; a list of
    which nothing at all can be read is no defective list but the wrong file (or an
    empty one), and running with every parameter defaulted would hide that. A start-up
    list without entries names no axes, and the message says so.
    """
    what = f"not {_a(kind)}: none of its lines is an entry of one"
    if kind is ListKind.STUP:
        what = f"no axes: {what}"
    if not parsed.entries and not parsed.warnings:
        return f"{what} (the file is empty or all comments)"
    first = min([e.line for e in parsed.entries] + [w.line for w in parsed.warnings])
    others = {k for e in parsed.entries for k in list_kinds_of(e.base) if k != kind}
    if others:
        names = " or ".join(_a(k) for k in sorted(others, key=lambda k: k.value))
        return f"{what}; they are entries of {names} (the first at line {first})"
    return f"{what} (unknown names or malformed lines from line {first} on)"


def _a(kind: ListKind) -> str:
    """The kind of list with its article: "an axis parameter list"."""
    return f"{'an' if kind.value[0] in 'aeiou' else 'a'} {kind.value}"


def _resolve(folder: Path, name: str, stup: str, line: int) -> Path:
    """A list file named in the start-up list, relative to its folder (Windows `\\` too)."""
    if not name:
        raise ListFileError(stup, line, "empty file name")
    p = Path(*PureWindowsPath(name).parts) if "\\" in name else Path(name)
    return p if p.is_absolute() else Path(os.path.normpath(folder / p))


def _named_lists(stup: Values, tag: str, rep: Reporter) -> list[tuple[int, str, int]]:
    """(axis number or 0, file name, start-up line) of `achs_<tag>[i]`, honouring `zahl_<tag>`."""
    files = stup.table(f"achs_{tag}[]")
    count = stup.item(f"zahl_{tag}")
    out = []
    for (i,), item in sorted(files.items()):
        if count is not None and i >= count.value:  # type: ignore[operator]
            rep.at("list.ignored", f"index {i} >= zahl_{tag} {count.value}: ignored", item.entry)
            continue
        nr = int(stup.get(f"achs_{tag}_log_ax_nr[]", 0, (i,)))
        out.append((nr, str(item.value), item.entry.line))
    if count is not None and len(out) < count.value:  # type: ignore[operator]
        rep.at("list.ignored", f"zahl_{tag} {count.value} but {len(out)} lists named", count.entry)
    return out


def _load_axes(
    folder: Path, startup: Path, mds: list[tuple[int, str, int]], rep: Reporter
) -> dict[int, AxisParams]:
    axes: dict[int, AxisParams] = {}
    for nr, name, line in mds:
        path = _resolve(folder, name, str(startup), line)
        values = _read(path, ListKind.AXIS, rep)
        own = axis_number(values)
        own_entry = values.item("kopf.achs_nr")
        nr = nr or own
        if not nr or nr in axes:
            why = "no logical axis number" if not nr else f"axis {nr} defined twice"
            # where the user fixes it: the axis list's own number when it has one (a
            # duplicate), else the start-up list line that names the list
            if own_entry is not None:
                rep.at("list.axis", f"{why}: list skipped", own_entry.entry)
            else:
                rep.report(
                    "list.axis",
                    f"{why} ({name}: no kopf.achs_nr, no achs_mds_log_ax_nr): list skipped",
                    file=str(startup),
                    line=line,
                    entry="achs_mds",
                )
            continue
        if own and own != nr and own_entry is not None:
            rep.at(
                "list.axis_mismatch",
                f"kopf.achs_nr {own} but the start-up list says {nr}; {nr} used",
                own_entry.entry,
            )
        axes[nr] = build_axis_params(values, nr, rep)
    return axes


def _attach_comp(configs: dict[int, AxisConfig], nr: int, values: Values, rep: Reporter) -> None:
    """Validate one compensation list and attach it to its axis (or report its header)."""
    own = int(values.get("kopf.achs_nr", 0))
    nr = nr or own
    problem = ""
    if not nr:
        problem = "kopf.achs_nr missing and no achs_kw_log_ax_nr: list belongs to no axis"
    elif nr not in configs:
        problem = f"axis {nr} is not an axis of the machine"
    elif own and own != nr:
        problem = f"kopf.achs_nr {own} but the start-up list assigns it to axis {nr}"
    elif configs[nr].comp is not None:
        problem = f"a second compensation value list for axis {nr}"
    if problem:
        _report_header(values, nr, problem, rep)
        return
    ctx = Ctx(axis=configs[nr].params, axes={k: c.params for k, c in configs.items()}, rep=rep)
    configs[nr].comp = build_comp_list(values, ctx)


def _report_header(values: Values, nr: int, problem: str, rep: Reporter) -> None:
    item = values.item("kopf.achs_nr")
    line = item.entry.line if item else 0
    for comp in sections_present(values):
        rep.report(
            HEADER_CHECK[comp],
            f"{problem}: list not used",
            file=values.path,
            line=line,
            entry="kopf.achs_nr",
            axis=nr,
        )


#: selection attribute -> (compensation, CompList attribute, check when the table is missing)
_SELECTIONS = {
    "crosscomp": (CompKind.CROSS, "cross", "cross.missing"),
    "crosscomp2": (CompKind.PLANE, "plane", "plane.missing"),
    "ssfk": (CompKind.LEAD, "lsec", "lead.missing"),
    "frict_comp": (CompKind.FRICT, "frict", "frict.values"),
    "crosstalk": (CompKind.CROSSTALK, "crosstalk", "crosstalk.missing"),
}


def _check_selected(configs: dict[int, AxisConfig], rep: Reporter) -> None:
    """A compensation selected in the axis list needs its table (000 §4.x "Effectiveness")."""
    for nr, cfg in configs.items():
        for attr, (_kind, comp_attr, key) in _SELECTIONS.items():
            if not getattr(cfg.params, attr):
                continue
            if cfg.comp is not None and getattr(cfg.comp, comp_attr) is not None:
                continue
            src = cfg.params.sources.get(f"lr_param.{attr}")
            rep.report(
                key,
                f"lr_param.{attr} 1 but no table in a compensation value list",
                file=src.file if src else cfg.params.path,
                line=src.line if src else 0,
                entry=f"lr_param.{attr}",
                axis=nr,
            )


# --------------------------------------------------------------------------- reload

_Table = CrossComp | PlaneComp | LsecComp | FrictComp
#: per compensation: its table in a compensation list, its entry, its default max_points
_MAX_POINTS: dict[CompKind, tuple[Callable[[CompList], _Table | None], str, int]] = {
    CompKind.LEAD: (lambda c: c.lsec, "kw.ssfk.max_points", 1500),
    CompKind.CROSS: (lambda c: c.cross, "kw.crosscomp.max_points", 1001),
    CompKind.PLANE: (lambda c: c.plane, "kw.crosscomp2.max_points", 10201),
    CompKind.FRICT: (lambda c: c.frict, "frict_comp.max_points", 20),
}


def compare_max_points(old: MachineConfig, new: MachineConfig) -> list[Diagnostic]:
    """Errors for every `max_points` that differs between two loads (002 §3.x.1).

    110638 LSEC, 110639 cross, 110640 plane, 110641 friction. A missing table counts as
    the default value (002: "not specified (or 0) -> default").
    """
    out: list[Diagnostic] = []
    for nr, cfg in new.axes.items():
        before = old.axes.get(nr)
        if before is None:
            continue
        for kind, (table, entry, default) in _MAX_POINTS.items():
            a, b = _max_points(before, table, default), _max_points(cfg, table, default)
            if a != b:
                path = cfg.comp.path if cfg.comp else ""
                msg = f"max_points changed from {a} to {b}; not allowed after start-up"
                out.append(
                    Diagnostic(
                        "error",
                        msg,
                        file=path,
                        entry=entry,
                        error_id=MAX_POINTS_IDS[kind],
                        axis=nr,
                        deactivated=kind,
                    )
                )
    return out


def _max_points(cfg: AxisConfig, table: Callable[[CompList], _Table | None], default: int) -> int:
    comp = table(cfg.comp) if cfg.comp else None
    return comp.max_points if comp is not None else default
