"""HMI diagnostics readout: every compensation of every axis, live over Zenoh (docs/design.md §10).

Per axis: command position, output position (what the drive gets, `dig_cmd_pos` of
000 p.19) and the total offset of all position compensations (docs/design.md §3); per
compensation: selected flag (`*::activated`, `ssfk activated`), effective flag
(`TEMPC::f_is_active`, `CROSSC::f_is_active`, `LSEC::active`: selected **and** all
preconditions such as homing met, 000 p.22), the actual (filtered) value, its change in
this cycle (delta) and the unfiltered value where the manual has an object for it
(`BC::sum backlash` 000 p.12, `CROSSTALK::end_offset` 000 p.91); the TEMPC parameters
(000 p.22–23); and the server's cycle status and latest warnings/errors.

Traffic (docs/design.md §7): one wildcard `get` per area fills the table at start —
`cnc/<m>/axis/**`, `cnc/<m>/sim/**`, `cnc/<m>/status`, `cnc/<m>/errors`, each with a
timeout — and subscriptions to the same four key expressions keep it current (the server
publishes on change, at most every 50 ms, and the status every second). There is no
polling. Subscriptions are declared before the gets, and a get reply never overwrites a
value a publication already delivered.

Usage:

    python -m geo_clients.hmi                                  # live view, cnc/local on :7447
    python -m geo_clients.hmi --connect tcp/10.0.0.5:7447 --machine mill --axis 1 --axis 3
    python -m geo_clients.hmi --once --format json             # one snapshot for scripts
    python -m geo_clients.hmi --once --format csv > snapshot.csv

The live view uses `rich` when it is installed (`--plain` forces plain text).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

from geo_server.dictionary import Dictionary, ObjectDef, load_dictionary
from geo_server.units import LINEAR, show
from geo_server.web.views import AXIS_FIELDS, COMPENSATIONS, CompView

COLUMNS = ("selected", "effective", "actual", "delta", "unfiltered")
CSV_FIELDS = (
    "axis",
    "compensation",
    *COLUMNS,
    "parameters",
    "homed",
    "command_position",
    "output_position",
    "total_offset",
)


class KeyParser:
    """Map the named keys of docs/design.md §7 back to (object, axis); pure, no session."""

    def __init__(self, machine: str, dictionary: Dictionary | None = None) -> None:
        self.machine = machine
        self.prefix = f"cnc/{machine}/"
        d = dictionary or load_dictionary()
        self.geo = {(o.key_group, o.key_field): o for o in d.objects if o.group == "geo"}
        self.sim_axis = {
            o.key_field: o for o in d.objects if o.group == "sim" and o.scope == "axis"
        }
        self.sim_machine = {
            o.key_field: o for o in d.objects if o.group == "sim" and o.scope == "machine"
        }

    def parse(self, key: str) -> tuple[str, ObjectDef | None, int]:
        """(kind, object, axis): kind `named`, `status`, `errors` or `other`."""
        if not key.startswith(self.prefix):
            return "other", None, 0
        parts = key[len(self.prefix) :].split("/")
        if parts == ["status"]:
            return "status", None, 0
        if parts == ["errors"]:
            return "errors", None, 0
        try:
            if len(parts) == 4 and parts[0] == "axis":
                return "named", self.geo.get((parts[2], parts[3])), int(parts[1])
            if len(parts) == 4 and parts[:2] == ["sim", "axis"]:
                return "named", self.sim_axis.get(parts[3]), int(parts[2])
            if len(parts) == 3 and parts[:2] == ["sim", "machine"]:
                return "named", self.sim_machine.get(parts[2]), 0
        except ValueError:
            pass
        return "other", None, 0


class HmiModel:
    """What the readout shows; fed with (key, payload) from gets and publications."""

    def __init__(self, machine: str = "local", max_errors: int = 100) -> None:
        self.machine = machine
        self.keys = KeyParser(machine)
        self.values: dict[tuple[str, int], Any] = {}
        self.status: dict[str, Any] = {}
        self.errors: deque[dict[str, Any]] = deque(maxlen=max_errors)
        self.axes: set[int] = set()
        self.version = 0
        self.updated = 0.0
        self._published: set[str] = set()
        self._cond = threading.Condition()

    def apply(self, key: str, payload: bytes, published: bool = True) -> None:
        """Take one value; a get reply (`published=False`) never overwrites a publication."""
        kind, obj, axis = self.keys.parse(key)
        if kind == "other" or (kind == "named" and obj is None):
            return
        try:
            value = json.loads(payload)
        except ValueError:
            return
        with self._cond:
            if kind == "status":
                if published or "status" not in self._published:
                    self.status = dict(value)
                    self.axes.update(int(a) for a in value.get("axes", []))
            elif kind == "errors":
                items = value if isinstance(value, list) else [value]
                if not published:
                    self.errors.clear()
                self.errors.extend(e for e in items if isinstance(e, dict))
            else:
                if not published and key in self._published:
                    return
                assert obj is not None
                self.values[(obj.name, axis)] = value
                if obj.scope == "axis":
                    self.axes.add(axis)
            if published:
                self._published.add("status" if kind == "status" else key)
            self.version += 1
            self.updated = time.monotonic()
            self._cond.notify_all()

    def value(self, name: str, axis: int) -> Any:
        return self.values.get((name, axis))

    def wait_for(self, predicate: Callable[[HmiModel], bool], timeout: float = 5.0) -> bool:
        """Block until `predicate(model)` holds (True) or `timeout` passes (False)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate(self):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    # ------------------------------------------------------------------ views

    def axis_list(self, only: Iterable[int] | None = None) -> list[int]:
        axes = sorted(self.axes)
        return [a for a in axes if a in set(only)] if only else axes

    def snapshot(self, only: Iterable[int] | None = None) -> dict[str, Any]:
        """Everything as JSON-ready data (the `--once --format json` output)."""
        with self._cond:
            axes = []
            for a in self.axis_list(only):
                entry: dict[str, Any] = {"axis": a}
                for fld, name in AXIS_FIELDS:
                    entry[fld] = self.values.get((name, a))
                comps: dict[str, Any] = {}
                for cv in COMPENSATIONS:
                    c = {col: self._col(cv, col, a) for col in COLUMNS}
                    c["parameters"] = {k: self.values.get((n, a)) for k, n in cv.parameters}
                    comps[cv.key] = c
                entry["compensations"] = comps
                axes.append(entry)
            return {
                "machine": self.machine,
                "status": dict(self.status),
                "axes": axes,
                "errors": list(self.errors),
            }

    def _col(self, cv: CompView, col: str, axis: int) -> Any:
        name = getattr(cv, col)
        return None if name is None else self.values.get((name, axis))

    def rows(self, only: Iterable[int] | None = None) -> list[dict[str, Any]]:
        """One row per (axis, compensation) (the `--format csv` output)."""
        out = []
        for entry in self.snapshot(only)["axes"]:
            for key, c in entry["compensations"].items():
                row = {"axis": entry["axis"], "compensation": key}
                row.update({col: c[col] for col in COLUMNS})
                row["parameters"] = ";".join(f"{k}={v}" for k, v in c["parameters"].items())
                for fld in ("homed", "command_position", "output_position", "total_offset"):
                    row[fld] = entry[fld]
                out.append(row)
        return out


# ============================================================================ rendering


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.10g}"
    return str(v)


class Units:
    """How the views show values: engineering units (positions in mm or °, offsets in µm,
    velocities in mm/s; `geo_server.units`) unless `raw`, then the CNC's increments."""

    def __init__(self, raw: bool = False) -> None:
        self.raw = raw
        self._d = load_dictionary()

    def __call__(self, name: str | None, value: Any, axis_type: Any = LINEAR) -> str:
        if name is None or value is None or isinstance(value, bool):
            return _fmt(value)
        shown = show(self._d.by_name(name), value, int(axis_type or LINEAR), self.raw)
        return f"{_fmt(shown.value)} {shown.unit}".rstrip() if not self.raw else _fmt(value)


def status_line(model: HmiModel) -> str:
    s = model.status
    if not s:
        return f"cnc/{model.machine}: no status yet"
    return (
        f"cnc/{model.machine}  cycle {s.get('cycle', '?')}  T {s.get('cycle_time_us', '?')} µs  "
        f"{s.get('mode', '?')}  lateness p50 {s.get('lateness_p50_us', 0):.0f} / "
        f"p99 {s.get('lateness_p99_us', 0):.0f} / max {s.get('lateness_max_us', 0):.0f} µs  "
        f"overruns {s.get('overruns', 0)}"
    )


def error_line(e: dict[str, Any]) -> str:
    ident = f"[{e['error_id']}] " if e.get("error_id") else ""
    where = f"{e['file']}:{e['line']} " if e.get("file") else ""
    axis = f"axis {e['axis']} " if e.get("axis") else ""
    return f"cycle {e.get('cycle', '?')} {e.get('severity', '?')} {ident}{axis}{where}" + str(
        e.get("message", "")
    )


def _axis_title(entry: dict[str, Any], u: Units) -> str:
    kind = entry.get("axis_type")
    return (
        f"axis {entry['axis']}  homed {_fmt(entry['homed'])}  "
        f"command {u('SIM::command_position', entry['command_position'], kind)}  "
        f"output {u('SIM::output_position', entry['output_position'], kind)}  "
        f"total offset {u('SIM::total_offset', entry['total_offset'], kind)}  "
        f"v {u('SIM::velocity', entry['velocity'], kind)}"
    )


def _cells(cv: CompView, c: dict[str, Any], kind: Any, u: Units) -> list[str]:
    params = " ".join(f"{k}={u(name, c['parameters'][k], kind)}" for k, name in cv.parameters)
    return [
        _fmt(c["selected"]),
        _fmt(c["effective"]),
        u(cv.actual, c["actual"], kind),
        u(cv.delta, c["delta"], kind),
        u(cv.unfiltered, c["unfiltered"], kind),
        params,
    ]


def render_text(
    model: HmiModel,
    only: Iterable[int] | None = None,
    max_errors: int = 5,
    units: Units | None = None,
) -> str:
    """The whole view as plain text (also what `--plain` shows live)."""
    u = units or Units()
    snap = model.snapshot(only)
    out = [status_line(model), ""]
    head = f"  {'compensation':<12} {'sel':>4} {'eff':>4} {'actual':>12} {'delta':>10} "
    head += f"{'unfiltered':>12}  parameters"
    for entry in snap["axes"]:
        out.append(_axis_title(entry, u))
        out.append(head)
        for cv in COMPENSATIONS:
            sel, eff, actual, delta, unf, params = _cells(
                cv, entry["compensations"][cv.key], entry.get("axis_type"), u
            )
            out.append(
                f"  {cv.key:<12} {sel:>4} {eff:>4} {actual:>12} {delta:>10} {unf:>12}"
                f"  {params}".rstrip()
            )
        out.append("")
    errors = snap["errors"][-max_errors:] if max_errors else []
    out.append(f"errors ({len(snap['errors'])}, latest last):" if errors else "errors: none")
    out.extend("  " + error_line(e) for e in errors)
    return "\n".join(out) + "\n"


def render_rich(
    model: HmiModel,
    only: Iterable[int] | None = None,
    max_errors: int = 5,
    units: Units | None = None,
) -> Any:
    """The view as a `rich` renderable (needs `rich`)."""
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    u = units or Units()
    snap = model.snapshot(only)
    parts: list[Any] = [Text(status_line(model), style="bold")]
    for entry in snap["axes"]:
        t = Table(title=_axis_title(entry, u), title_justify="left", expand=False)
        for col, just in (
            ("compensation", "left"),
            ("sel", "center"),
            ("eff", "center"),
            ("actual", "right"),
            ("delta", "right"),
            ("unfiltered", "right"),
            ("parameters", "left"),
        ):
            t.add_column(col, justify=just)  # type: ignore[arg-type]
        for cv in COMPENSATIONS:
            c = entry["compensations"][cv.key]
            sel, eff = c["selected"], c["effective"]
            style = "green" if eff or (eff is None and sel) else ("yellow" if sel else "dim")
            t.add_row(cv.key, *_cells(cv, c, entry.get("axis_type"), u), style=style)
        parts.append(t)
    errors = snap["errors"][-max_errors:] if max_errors else []
    parts.append(Text("errors: none" if not errors else f"errors ({len(snap['errors'])}):"))
    parts.extend(Text("  " + error_line(e), style="red") for e in errors)
    return Group(*parts)


def rich_text(model: HmiModel, width: int = 120, **kw: Any) -> str:
    """`render_rich` rendered to plain text (headless tests, logs)."""
    from rich.console import Console

    console = Console(file=io.StringIO(), width=width, record=True, color_system=None)
    console.print(render_rich(model, **kw))
    return console.export_text()


def snapshot_json(model: HmiModel, only: Iterable[int] | None = None) -> str:
    return json.dumps(model.snapshot(only), indent=2, ensure_ascii=False) + "\n"


def snapshot_csv(model: HmiModel, only: Iterable[int] | None = None) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS, lineterminator="\n")
    w.writeheader()
    for row in model.rows(only):
        w.writerow({k: "" if v is None else v for k, v in row.items()})
    return buf.getvalue()


# ============================================================================ Zenoh


class Hmi:
    """Feed an `HmiModel` from a Zenoh session: one get per area, then subscriptions."""

    def __init__(
        self,
        machine: str = "local",
        connect: list[str] | None = None,
        timeout: float = 2.0,
        session: Any = None,
    ) -> None:
        self.model = HmiModel(machine)
        self.machine = machine
        self.timeout = timeout
        self._own = session is None
        if session is None:
            import zenoh

            from geo_server.client.zenoh_client import client_config

            session = zenoh.open(client_config(connect or ["tcp/127.0.0.1:7447"]))
        self.session = session
        self._subs: list[Any] = []

    @property
    def areas(self) -> list[str]:
        p = f"cnc/{self.machine}"
        return [f"{p}/axis/**", f"{p}/sim/**", f"{p}/status", f"{p}/errors"]

    def subscribe(self) -> None:
        """Declare the four subscriptions (before the gets: nothing is missed)."""
        for ke in self.areas:
            self._subs.append(self.session.declare_subscriber(ke, self._on_sample))

    def _on_sample(self, sample: Any) -> None:
        self.model.apply(str(sample.key_expr), sample.payload.to_bytes(), published=True)

    def fill(self) -> int:
        """One wildcard get per area (each with the timeout); returns the replies taken."""
        n = 0
        for ke in self.areas:
            for reply in self.session.get(ke, timeout=self.timeout):
                if reply.ok is not None:
                    self.model.apply(
                        str(reply.ok.key_expr), reply.ok.payload.to_bytes(), published=False
                    )
                    n += 1
        return n

    def start(self) -> HmiModel:
        self.subscribe()
        self.fill()
        return self.model

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._subs.clear()
        if self._own:
            self.session.close()

    def __enter__(self) -> Hmi:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def run_live(
    hmi: Hmi,
    only: Iterable[int] | None = None,
    refresh: float = 0.2,
    duration: float | None = None,
    plain: bool = False,
    out: Any = None,
    max_errors: int = 5,
    units: Units | None = None,
) -> None:
    """Redraw when the model changed, at most every `refresh` s, until Ctrl-C/`duration`.

    On a terminal the view is redrawn in place (rich, or plain text after a clear-screen
    code); into a pipe or a file each new view is appended after a separator line and no
    terminal control codes are written."""
    out = out or sys.stdout
    only = list(only) if only else None
    terminal = bool(getattr(out, "isatty", lambda: False)())
    try:
        import rich  # noqa: F401

        have_rich = not plain and terminal
    except ImportError:
        have_rich = False
    seen = -1
    # the duration counts from here (importing rich can take a while) and the first view
    # is always drawn, however short the duration
    end = None if duration is None else time.monotonic() + duration
    drawn = False

    def due() -> bool:
        return not drawn or end is None or time.monotonic() < end

    if have_rich:
        from rich.console import Console
        from rich.live import Live

        console = Console(file=out)
        with Live(
            render_rich(hmi.model, only, max_errors, units), console=console, auto_refresh=False
        ) as live:
            while due():
                if hmi.model.version != seen:
                    seen = hmi.model.version
                    live.update(render_rich(hmi.model, only, max_errors, units), refresh=True)
                drawn = True
                time.sleep(refresh)
        return
    while due():
        if hmi.model.version != seen:
            seen = hmi.model.version
            view = render_text(hmi.model, only, max_errors, units)
            out.write(
                ("\x1b[H\x1b[2J" + view) if terminal else f"--- {time.strftime('%H:%M:%S')}\n{view}"
            )
            out.flush()
        drawn = True
        time.sleep(refresh)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="geo-hmi",
        description="HMI diagnostics readout of geo-server over Zenoh: every compensation "
        "of every axis, live, or one snapshot as JSON/CSV.",
    )
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="Zenoh endpoint")
    p.add_argument("--machine", default="local", help="machine name (key prefix cnc/<machine>)")
    p.add_argument("--timeout", type=float, default=2.0, help="seconds per get (default 2)")
    p.add_argument(
        "--axis", action="append", help="show only these axes (number or name; repeatable)"
    )
    p.add_argument("--once", action="store_true", help="print one snapshot and exit")
    p.add_argument("--format", choices=("text", "json", "csv"), default="text")
    p.add_argument("--errors", type=int, default=5, help="latest errors shown (default 5)")
    p.add_argument("--plain", action="store_true", help="plain text live view (no rich)")
    p.add_argument(
        "--raw", action="store_true", help="internal units (increments) instead of mm, µm, °"
    )
    p.add_argument("--refresh", type=float, default=0.2, help="redraw period, s (default 0.2)")
    p.add_argument("--duration", type=float, help="stop the live view after this many seconds")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        hmi = Hmi(args.machine, args.connect, args.timeout)
    except Exception as exc:  # zenoh.ZError and friends
        print(f"error: cannot open a Zenoh session: {exc}", file=sys.stderr)
        return 2
    units = Units(raw=args.raw)
    with hmi:
        hmi.fill()
        try:
            only = axis_numbers(hmi.model, args.axis)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if args.once:
            if not hmi.model.axes:
                print(
                    f"error: no answer from cnc/{args.machine} within {args.timeout} s "
                    "(is the server running with that machine name?)",
                    file=sys.stderr,
                )
                return 1
            if args.format == "json":
                sys.stdout.write(snapshot_json(hmi.model, only))
            elif args.format == "csv":
                sys.stdout.write(snapshot_csv(hmi.model, only))
            else:
                sys.stdout.write(render_text(hmi.model, only, args.errors, units))
            return 0
        hmi.start()
        with contextlib.suppress(KeyboardInterrupt):
            run_live(hmi, only, args.refresh, args.duration, args.plain, None, args.errors, units)
    return 0


def axis_numbers(model: HmiModel, wanted: list[str] | None) -> list[int] | None:
    """`--axis` values (numbers or names, e.g. 1 or X) as axis numbers."""
    if not wanted:
        return None
    names = {str(n).upper(): int(a) for a, n in (model.status.get("axis_names") or {}).items()}
    out = []
    for w in wanted:
        if w.isdigit():
            out.append(int(w))
        elif w.upper() in names:
            out.append(names[w.upper()])
        else:
            raise ValueError(f"no axis named {w!r} (axes: {', '.join(names) or 'unknown'})")
    return out


if __name__ == "__main__":
    raise SystemExit(main())
