"""Configuration of the volumetric compensations: start-up entries, VOLC lists, files.

004 §3.1 (p.11-14): the start-up list names up to 5 compensations (`vol_comp[i].
max_records`, `vol_comp[i].file_name`, IDs 0-4); each one's VOLC list assigns the axes
(`X 1` …), gives the `chain` and `workpiece_axes`, up to 10 correction files
(`file[j]`, `file_format[j]`) and the options of §3.3-3.6 and p.23. Loading never raises
on content: what is wrong becomes a diagnostic with file and line (`volc.*` checks,
docs/list_checks.md) and that compensation is not available, the machine still starts —
the discipline of the GEO lists (docs/design.md §4).

Files are read only inside the machine's folders (`MachineConfig.file_roots`: the
start-up list's folder and `geo-server run --allow-dir`), whoever names them — the
start-up list, a VOLC list's `file[j]`, the network (0x27C, `#VOLCOMP [ID.. UPDATE]`);
a name resolving elsewhere is refused with `safefile.REFUSED` at the line naming it. A
VOLC list named over the network that cannot be read as one (missing, a folder, a FIFO,
not a VOLC list …) is refused with the same text: the answer says nothing about the
file system (docs/security.md). Files are read through `safefile.read_regular`, bounded
by `safefile.FileLimits`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PureWindowsPath

import numpy as np

from geo_server.listfile.schema import ListKind, lookup
from geo_server.listfile.syntax import NotAListFileError, parse_list
from geo_server.listfile.values import Reporter, Values, read_values
from geo_server.model import AxisParams, MachineConfig
from geo_server.safefile import LIMITS, REFUSED, is_inside
from geo_server.volcomp.model import VolModel, build_model
from geo_server.volcomp.names import AXES, COMPONENT_ERRORS, LINEAR, POSITION_ERRORS
from geo_server.volcomp.paramfile import FORMATS, Block, ParamFileError, read_param_file
from geo_server.volcomp.tables import ParamTable, TableError, build_tables

#: IDs 0-4 (004 p.11: "Up to 5 compensations can be configured for each controller").
MAX_COMPENSATIONS = 5
#: file[0] … file[9] (004 p.12: "Up to 10 parameter files").
MAX_FILES = 10
INTERPOLATIONS = ("GRID", "SCATTER", "AUTO", "PATH", "PATH_XY")


@dataclass(frozen=True)
class VolcConfig:
    """One VOLC list, checked (004 §3)."""

    path: str
    axes: dict[str, int]  # letter -> logical axis number
    chain: str
    workpiece_axes: int = 0
    files: tuple[tuple[str, str, int], ...] = ()  # (file as written, format, line)
    file_slots: tuple[int, ...] = ()  # the j of each of `files` (file[j])
    negate: str = ""
    set_to_zero: str = ""
    alternative_model: bool = False
    filter_steps: int = 0
    manual_activation: bool = False
    interpolation: str = "GRID"
    enable_splicing: bool = False
    associate_to_channel: bool = False


@dataclass(frozen=True)
class VolComp:
    """One configured compensation: what the start-up list says and what became of it.
    `model` is None when it is not available (`problem` says why)."""

    id: int
    max_records: int = 0
    file_name: str = ""  # the VOLC list as written
    path: str = ""  # the VOLC list found
    config: VolcConfig | None = None
    model: VolModel | None = None
    records: int = 0
    problem: str = ""
    param_files: tuple[str, ...] = field(default_factory=tuple)

    @property
    def available(self) -> bool:
        return self.model is not None


def resolve(folder: Path, name: str) -> Path:
    """A file named in a list: relative to the naming list's folder (`..\\x.lis` works);
    an absolute Windows path (`C:\\volcomp\\vol_comp_0.lis`, 004 p.36) that does not
    exist here is looked up by its file name in that folder (docs/volumetric.md §4)."""
    win = PureWindowsPath(name)
    if win.drive or name.startswith("\\"):
        return folder / win.name
    p = Path(*win.parts) if "\\" in name else Path(name)
    return p if p.is_absolute() else Path(os.path.normpath(folder / p))


class _Problem(Exception):
    """Why a compensation is not available; reported once with file and line."""

    def __init__(self, check: str, message: str, file: str = "", line: int = 0) -> None:
        super().__init__(message)
        self.check, self.message, self.file, self.line = check, message, file, line


def _letters(text: str, allowed: str, what: str, values: Values, rep: Reporter) -> str:
    """`negate XY` / `set_to_zero Z` (004 p.16): letters in any order; unknown ones warn."""
    item = values.item(what)
    out = ""
    for ch in text.upper():
        if ch in allowed and ch not in out:
            out += ch
        elif not ch.isspace() and item is not None:
            rep.at("list.defective", f"{ch!r} is not a linear axis letter: ignored", item.entry)
    return out


def _config(values: Values, rep: Reporter, written: Mapping[int, str]) -> VolcConfig:
    """The VOLC list's entries, checked; `_Problem` when it cannot be used. `written`:
    file names an NC program gave `V.G.VOLCOMP[i].FILE[j]` (004 p.18), in place of the
    list's `file[j]` (or beside it, with the list's `file_format[j]`)."""
    axes = {a: int(v) for a in AXES if (v := values.get(a.lower())) is not None}
    order = sorted(axes, key=lambda a: values.item(a.lower()).entry.line)  # type: ignore[union-attr]
    chain_item = values.item("chain")
    # no `chain` (004 p.23 has none): the assigned axes in the order of their lines
    chain = str(chain_item.value).strip().upper() if chain_item else "".join(order)
    line = chain_item.entry.line if chain_item else 0
    bad = [c for c in chain if c not in AXES]
    if bad or len(set(chain)) != len(chain):
        why = f"unknown axis letter {bad[0]!r}" if bad else "an axis twice"
        raise _Problem("volc.config", f"chain {chain!r}: {why} (X Y Z A B C, 004 p.11)", "", line)
    if sorted(c for c in chain if c in LINEAR) != list(LINEAR):
        raise _Problem(
            "volc.config",
            f"chain {chain!r}: the chain needs exactly the 3 linear axes X, Y, Z and up to 3 "
            "rotary axes A, B, C (004 p.8, p.11)",
            "",
            line,
        )
    wp = int(values.get("workpiece_axes", 0))
    if wp > len(chain):
        item = values.item("workpiece_axes")
        raise _Problem(
            "volc.config",
            f"workpiece_axes {wp} but the chain {chain} has {len(chain)} axes",
            "",
            item.entry.line if item else 0,
        )
    files, slots = [], []
    listed = {j: item for (j,), item in values.table("file[]").items()}
    for j in sorted(set(listed) | set(written)):
        item = listed.get(j)
        line = item.entry.line if item is not None else 0
        fmt_item = values.item("file_format[]", (j,))
        if j >= MAX_FILES:
            raise _Problem(
                "volc.config",
                f"file[{j}]: at most 10 files (file[0] … file[9], 004 p.12)",
                "",
                line,
            )
        if fmt_item is None:
            raise _Problem(
                "volc.config",
                f"file[{j}] without file_format[{j}] (ISG_CSV or ETALON_EXCHANGE, 004 p.12)"
                + ("" if item is not None else f": given by V.G.VOLCOMP[..].FILE[{j}]"),
                "",
                line,
            )
        fmt = str(fmt_item.value).strip().upper()
        if fmt not in FORMATS:
            raise _Problem(
                "volc.config",
                f"file_format[{j}] {fmt_item.value!r}: not ISG_CSV or ETALON_EXCHANGE (004 p.12)",
                "",
                fmt_item.entry.line,
            )
        name = written[j] if j in written else str(item.value).strip() if item else ""
        files.append((name, fmt, line))
        slots.append(j)
    for (j,), item in values.table("file_format[]").items():
        if values.item("file[]", (j,)) is None and j not in written:
            rep.at("list.ignored", f"file_format[{j}] without file[{j}]: ignored", item.entry)
    interp = str(values.get("interpolation", "GRID")).strip().upper()
    if interp not in INTERPOLATIONS:
        item = values.item("interpolation")
        raise _Problem(
            "volc.config",
            f"interpolation {interp!r}: not one of {', '.join(INTERPOLATIONS)} (004 p.34)",
            "",
            item.entry.line if item else 0,
        )
    if (item := values.item("diagnosis_file")) is not None:
        rep.at(
            "list.ignored",
            "the diagnostic file is not available in TwinCAT (004 p.17): ignored",
            item.entry,
        )
    return VolcConfig(
        path=values.path,
        axes=axes,
        chain=chain,
        workpiece_axes=wp,
        files=tuple(files),
        file_slots=tuple(slots),
        negate=_letters(str(values.get("negate", "")), "XYZ", "negate", values, rep),
        set_to_zero=_letters(str(values.get("set_to_zero", "")), "XYZ", "set_to_zero", values, rep),
        alternative_model=bool(values.get("alternative_model", False)),
        filter_steps=int(values.get("filter_steps", 0)),
        manual_activation=bool(values.get("manual_activation", False)),
        interpolation=interp,
        enable_splicing=bool(values.get("enable_splicing", False)),
        associate_to_channel=bool(values.get("associate_to_channel", False)),
    )


def read_volc_list(
    path: Path,
    rep: Reporter,
    *,
    from_network: bool = False,
    written: Mapping[int, str] | None = None,
) -> VolcConfig:
    """Parse and check one VOLC list (at most `FileLimits.volc_list_bytes`); `_Problem`
    if it cannot be used. `from_network`: the name came over the network, and whatever
    keeps it from being read as a VOLC list is answered with `REFUSED` alone.
    `written`: `file[j]` names given by `V.G.VOLCOMP[i].FILE[j]` (`_config`)."""
    try:
        try:
            parsed = parse_list(path, LIMITS.volc_list_bytes)
        except FileNotFoundError:
            raise _Problem(
                "volc.file", "volumetric compensation list not found", str(path)
            ) from None
        except NotAListFileError as exc:
            raise _Problem("volc.file", str(exc), str(path), exc.line) from None
        except OSError as exc:
            why = exc.strerror or str(exc)
            raise _Problem(
                "volc.file", f"volumetric compensation list unreadable: {why}", str(path)
            ) from None
        if not any(lookup(ListKind.VOLC, e.base) for e in parsed.entries):
            raise _Problem(
                "volc.file",
                "not a volumetric compensation list: none of its lines is an entry of one",
                str(path),
            )
    except _Problem:
        if from_network:
            raise _Problem("volc.file", REFUSED) from None
        raise
    values = read_values(parsed, ListKind.VOLC, rep)
    try:
        return _config(values, rep, written or {})
    except _Problem as exc:
        exc.file = exc.file or str(path)
        raise


def _tables(
    cfg: VolcConfig, folder: Path, roots: Sequence[Path], written: Mapping[int, str]
) -> tuple[dict[str, ParamTable], int, tuple[str, ...]]:
    """The correction files' tables. A file an NC program named (`written`, from the
    network) that cannot be used is answered with `REFUSED` alone: its content, whether
    it exists and where it was looked for are not told (docs/security.md, "Files")."""
    blocks: list[Block] = []
    paths: list[str] = []
    untold: set[str] = set()
    for j, (name, fmt, line) in zip(
        cfg.file_slots or range(len(cfg.files)), cfg.files, strict=True
    ):
        p = resolve(folder, name)
        if not is_inside(p, roots):
            raise _Problem("volc.file", REFUSED, cfg.path, line)
        try:
            if j in written:
                untold.add(str(p))
                try:
                    pf = read_param_file(p, fmt)
                except (OSError, ParamFileError):
                    raise _Problem("volc.file", REFUSED, cfg.path, line) from None
            else:
                pf = read_param_file(p, fmt)
        except FileNotFoundError:
            raise _Problem(
                "volc.file", f"correction file {name} not found (looked for {p})", cfg.path, line
            ) from None
        except ParamFileError as exc:
            raise _Problem("volc.file", exc.message, exc.path, exc.line) from None
        except OSError as exc:
            raise _Problem(
                "volc.file", f"correction file {name} unreadable: {exc}", cfg.path, line
            ) from None
        blocks.extend(pf.blocks)
        paths.append(str(p))
    try:
        tables, records = build_tables(blocks, cfg.enable_splicing, cfg.interpolation)
    except TableError as exc:
        if exc.file in untold:
            raise _Problem("volc.file", REFUSED, cfg.path) from None
        raise _Problem("volc.file", exc.message, exc.file, exc.line) from None
    for t in tables.values():
        for arg in t.arguments:
            if arg not in cfg.chain:
                raise _Problem(
                    "volc.file",
                    f"{t.name} depends on {arg}, which is not in the chain {cfg.chain}",
                    t.file,
                    t.line,
                )
    return _constants(tables), records, tuple(paths)


def _constants(tables: Mapping[str, ParamTable]) -> dict[str, ParamTable]:
    """The ISG parameters as the constants the model takes (P0?, N0?, P?k, V?k, IDk,
    LNk describe the machine, 004 p.30), and the position errors, constants where they
    have one value. A header may name arguments with them (p.32: position errors are
    "typically (but not necessarily) constant"): records that all give one value are
    that constant; a position error whose values differ over its arguments stays a
    table, evaluated at the axes' positions like a component error (docs/volumetric.md
    §3); an ISG parameter whose values differ is refused at the block naming it — the
    model has no place for a varying one, and taking it as 0 would report a
    compensation active that corrects nothing."""
    out = dict(tables)
    for name, t in tables.items():
        if not t.arguments or name in COMPONENT_ERRORS:
            continue
        raw = t.values if t.mode == "GRID" else t.point_values
        values = np.unique(np.asarray(raw, dtype=float).ravel())
        if len(values) != 1 and name in POSITION_ERRORS:
            if name[0] in LINEAR and name[2] in LINEAR:
                raise _Problem(
                    "volc.file",
                    f"{name} is the position shift of the linear axis {name[2]}, which has no "
                    "effect (004 p.28: 'only relevant for rotary axes'); its values over "
                    f"({', '.join(t.arguments)}) differ: give a variation over the travel "
                    f"as a component error (E<direction>{name[2]}, 004 p.29-30)",
                    t.file,
                    t.line,
                )
            continue
        if len(values) != 1:
            raise _Problem(
                "volc.file",
                f"{name} is a constant of the machine model (004 p.30), but its values over "
                f"({', '.join(t.arguments)}) differ ({values[0]:g} … {values[-1]:g}); give a "
                "variation over the travel as a component error (E<direction><axis>) or a "
                "position error (<direction>0<axis>, 004 p.29-32)",
                t.file,
                t.line,
            )
        out[name] = ParamTable(name, (), (), np.array(float(values[0])), file=t.file, line=t.line)
    return out


def _assign(
    cfg: VolcConfig, tables: dict[str, ParamTable], machine: dict[int, AxisParams]
) -> VolcConfig:
    """LNX … LNC in a file overwrite the list's axis numbers (004 p.30); every chain axis
    needs a number that is an axis of the machine."""
    axes = dict(cfg.axes)
    for a in AXES:
        t = tables.get(f"LN{a}")
        if t is not None and not t.arguments:
            axes[a] = int(t.values)
    for a in cfg.chain:
        if a not in axes:
            raise _Problem(
                "volc.config",
                f"chain axis {a} has no axis number (`{a} <logical axis number>`, 004 p.11)",
                cfg.path,
            )
        if axes[a] not in machine:
            raise _Problem(
                "volc.config",
                f"{a} {axes[a]}: axis {axes[a]} is not an axis of the machine",
                cfg.path,
            )
    return VolcConfig(**{**cfg.__dict__, "axes": axes})


def load_compensation(
    ident: int,
    max_records: int | None,
    file_name: str,
    folder: Path,
    machine: dict[int, AxisParams],
    rep: Reporter,
    where: tuple[str, int] = ("", 0),
    *,
    roots: Sequence[Path],
    from_network: bool = False,
    written: Mapping[int, str] | None = None,
) -> VolComp:
    """Load compensation `ident` from its VOLC list; report what is wrong and return it
    unavailable then (never raises on content). Files are read only inside `roots`
    (see the module docstring); `from_network`: `file_name` came over the network;
    `written`: file names given by `V.G.VOLCOMP[ident].FILE[j]` (004 p.18)."""
    path = Path(os.path.abspath(resolve(folder, file_name))) if file_name else Path()
    try:
        if not file_name:
            raise _Problem(
                "volc.config",
                REFUSED if from_network else f"vol_comp[{ident}].file_name missing: no VOLC list",
                *where,
            )
        if not max_records:
            raise _Problem(
                "volc.config",
                f"vol_comp[{ident}].max_records missing or 0 (004 p.12: a bound for the "
                "records must be given)",
                *where,
            )
        if not is_inside(path, roots):
            raise _Problem("volc.file", REFUSED, *where)
        cfg = read_volc_list(path, rep, from_network=from_network, written=written)
        tables, records, paths = _tables(cfg, path.parent, roots, written or {})
        if records > max_records:
            raise _Problem(
                "volc.file",
                f"{records} records in the correction files, more than "
                f"vol_comp[{ident}].max_records {max_records} (004 p.12)",
                cfg.path,
            )
        cfg = _assign(cfg, tables, machine)
        model = build_model(cfg.chain, cfg.workpiece_axes, tables, cfg.alternative_model)
    except _Problem as exc:
        rep.report(
            exc.check,
            f"volumetric compensation {ident}: {exc.message}",
            file=exc.file,
            line=exc.line,
        )
        return VolComp(ident, max_records or 0, file_name, str(path), problem=exc.message)
    return VolComp(ident, max_records, file_name, str(path), cfg, model, records, "", paths)


def reload_compensation(
    cfg: MachineConfig,
    ident: int,
    file_name: str,
    rep: Reporter,
    written: Mapping[int, str] | None = None,
) -> VolComp | None:
    """Compensation `ident` of a loaded machine read again from the VOLC list
    `file_name` (`#VOLCOMP UPDATE`, cnc_interpr_vol_comp_file_w: 004 p.23), with the
    start-up list's `max_records`; None when the start-up list does not configure it.
    Both are requests from the network: only inside `cfg.file_roots`, and a list that
    cannot be read is answered with `REFUSED` alone."""
    comp = next((c for c in cfg.volumetric if c.id == ident), None)
    if comp is None:
        return None
    params = {a: ax.params for a, ax in cfg.axes.items()}
    return load_compensation(
        ident,
        comp.max_records,
        file_name,
        cfg.startup_path.parent,
        params,
        rep,
        roots=cfg.file_roots,
        from_network=True,
        written=written,
    )


def load_volumetric(
    stup: Values,
    folder: Path,
    machine: dict[int, AxisParams],
    rep: Reporter,
    roots: Sequence[Path],
) -> tuple[VolComp, ...]:
    """Every `vol_comp[i]` of the start-up list (004 p.12, p.36-37), IDs 0-4; their
    files only from inside `roots` (`MachineConfig.file_roots`)."""
    maxes = stup.table("vol_comp[].max_records")
    names = stup.table("vol_comp[].file_name")
    out = []
    for (i,) in sorted(set(maxes) | set(names)):
        item = names.get((i,)) or maxes[(i,)]
        if i >= MAX_COMPENSATIONS:
            rep.report(
                "volc.config",
                f"vol_comp[{i}]: IDs are 0-4 (004 p.11: up to 5 compensations)",
                file=item.entry.file,
                line=item.entry.line,
            )
            continue
        m = maxes.get((i,))
        n = names.get((i,))
        if n is None:  # a bound without a list (004 p.12 prints the bound alone)
            rep.at(
                "list.ignored",
                f"vol_comp[{i}].file_name missing: no volumetric compensation {i} configured",
                item.entry,
            )
            continue
        out.append(
            load_compensation(
                i,
                int(m.value) if m else None,
                str(n.value).strip() if n else "",
                folder,
                machine,
                rep,
                (item.entry.file, item.entry.line),
                roots=roots,
            )
        )
    return tuple(out)


__all__ = [
    "VolComp",
    "VolcConfig",
    "load_compensation",
    "load_volumetric",
    "read_volc_list",
    "reload_compensation",
    "resolve",
]
