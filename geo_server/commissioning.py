"""`geo-server measure`: an ISO 230-2 test on the twin, a closed commissioning loop, a
reference measurement for the PLC temperature client — files and figures (docs/twin.md).

The machine runs in this process in stepped mode (exact, deterministic, as fast as the
host computes), loaded from the start-up list like `geo-server run` loads it; nothing
listens on the network. The procedures themselves are in `geo_server.twin.measure`.

Outputs in `--out` (default `measurement/`):

- `deviations.csv` (and `deviations_after.csv`): every reading x_ij (ISO 230-2 §2.5);
- `result.json`: the figures A, E, M, B, R of each test, the plan, the lists written;
- a plain test: `lsec_<AXIS>.lis` (a compensation value list holding the LSEC table
  from the result, ready to load) and `backlash_<AXIS>.lis` (the backlash entries for
  the axis list) — the values to load when measured with `--off LEAD,BACKLASH`;
- `reference_measurement.csv` (`--temperatures`): what `geo-plc-tempcomp` reads;
- with `--plot`: `error_curve.png/.svg` (before/after with `--commission`) and
  `hysteresis.png/.svg`.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from geo_server import access, jit
from geo_server.errors import GeoError
from geo_server.kernel.common import initial_direction
from geo_server.listfile import ListFileError, load_machine
from geo_server.machine.machine import Machine
from geo_server.model import MachineConfig
from geo_server.paths import default_startup_list, is_product_data
from geo_server.service import ObjectService
from geo_server.twin import iso230
from geo_server.twin.iso230 import Evaluation
from geo_server.twin.measure import (
    MeasureError,
    MeasurementPlan,
    StepBench,
    axis_number,
    backlash_lines,
    check_plan,
    commission,
    lsec_list,
    lsec_setpoints,
    reference_measurement,
    run_test,
    write_lists,
)

#: What a commissioning switches off for the "before" test: the two compensations whose
#: values it measures (unilateral LSEC: the table and the backlash; bilateral: the tables
#: hold the reversal, so backlash compensation stays as it is, 000 §4.1).
OFF_UNILATERAL = ("LEAD", "BACKLASH")
OFF_BILATERAL = ("LEAD",)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `geo-server measure`."""
    p.add_argument("startup", nargs="?", help="start-up list (default: the default machine)")
    p.add_argument("--axis", required=True, help="axis name or logical number (e.g. X or 1)")
    t = p.add_argument_group("test (ISO 230-2:2014 §5)")
    g = t.add_mutually_exclusive_group()
    g.add_argument(
        "--targets",
        help="target positions, mm or °, comma-separated (a negative first one: "
        "--targets=-500,0,500)",
    )
    g.add_argument(
        "--range",
        metavar="START:STOP:STEP",
        help="equidistant targets from START to STOP (mm or °; a negative START: "
        "--range=-500:500:100); default: the setpoints of the axis' LSEC table",
    )
    t.add_argument("--runs", type=int, default=5, help="runs (default 5, as the standard asks)")
    t.add_argument(
        "--overrun", type=float, default=5.0, help="approach overrun, mm or ° (default 5)"
    )
    t.add_argument(
        "--dwell", type=float, default=0.2, help="standstill before each reading, s (0.2)"
    )
    t.add_argument(
        "--off",
        default="",
        metavar="KINDS",
        help="compensations off during the test, e.g. LEAD,BACKLASH (NC COMP OFF, 000 §5.1)",
    )
    t.add_argument("--time-scale", type=float, metavar="K", help="as for `run`")
    w = p.add_argument_group("what to make of it")
    w.add_argument(
        "--commission",
        action="store_true",
        help="the closed loop: measure without LSEC (and backlash, unilateral tables), write "
        "the LSEC table and backlash into the axis' lists, reload, measure again",
    )
    w.add_argument(
        "--temperatures",
        metavar="DEG_C",
        help="a reference measurement: the test in a climate chamber at each temperature "
        "(comma-separated °C), written as reference_measurement.csv for geo-plc-tempcomp",
    )
    w.add_argument(
        "--bilateral",
        action="store_true",
        help="lsec_<AXIS>.lis as a bilateral table (default: as the axis' own LSEC table)",
    )
    w.add_argument("--out", default="measurement", help="folder for the files (created)")
    w.add_argument("--plot", action="store_true", help="PNG and SVG figures (needs matplotlib)")
    p.set_defaults(func=main)


def _floats(text: str, option: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.replace(" ", "").split(",") if x)
    except ValueError:
        raise MeasureError(f"{option} needs numbers separated by commas, got {text!r}") from None


def _targets(args: argparse.Namespace, cfg: MachineConfig, axis: int) -> tuple[float, ...]:
    if args.targets:
        return _floats(args.targets, "--targets")
    if args.range:
        try:
            start, stop, step = (float(x) for x in args.range.split(":"))
        except ValueError:
            raise MeasureError(f"--range needs START:STOP:STEP, got {args.range!r}") from None
        if step <= 0 or stop <= start:
            raise MeasureError("--range: STOP must exceed START and STEP be positive")
        n = int((stop - start) / step + 1e-9)  # the last target at or below STOP
        return tuple(start + i * step for i in range(n + 1))
    return lsec_setpoints(cfg, axis)


def _units(cfg: MachineConfig, axis: int) -> tuple[str, str]:
    """(deviation unit, position unit) of the axis."""
    return ("0.001°", "°") if cfg.axes[axis].params.kind == "R" else ("µm", "mm")


def _print_figures(title: str, ev: Evaluation, unit: str) -> None:
    print(f"\n{title}\n")
    print(ev.table_markdown(unit))


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def main(args: argparse.Namespace) -> int:
    """Run `geo-server measure`; 0 on success, 2 on a usage or list error."""
    try:
        return _measure(args)
    except (MeasureError, ListFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except GeoError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


def _measure(args: argparse.Namespace) -> int:
    from geo_server.twin import plots

    if args.plot and not plots.available():  # said now, not after minutes of measuring
        raise MeasureError(f"--plot: {plots.MISSING}")
    startup = Path(args.startup) if args.startup else default_startup_list()
    if args.commission and (args.targets or args.range):
        raise MeasureError(
            "--commission measures at the setpoints of the axis' LSEC table: "
            "leave out --targets/--range"
        )
    if args.commission and is_product_data(startup):  # read-only, as for `save`
        raise MeasureError(
            "--commission writes into the lists: copy the default machine first "
            "(geo-server init DIR) and name DIR/hochlauf.lis"
        )
    cfg = load_machine(startup)
    axis = axis_number(cfg, args.axis)
    unit, position_unit = _units(cfg, axis)
    plan = MeasurementPlan(
        axis=axis,
        targets=_targets(args, cfg, axis),
        runs=args.runs,
        overrun=args.overrun,
        dwell_s=args.dwell,
        compensation_off=tuple(k.upper() for k in args.off.replace(" ", "").split(",") if k),
    )
    check_plan(plan)  # before anything is loaded or created
    direction = int(initial_direction(cfg.axes[axis].params.anwahl_losekomp))
    jit.load()  # thousands of stepped cycles: compiled from the first one
    machine = Machine(cfg, homed=True, time_scale=args.time_scale)
    svc = ObjectService(machine)
    bench = StepBench(svc)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = cfg.axes[axis].params.name or str(axis)
    label = f"axis {name}: {len(plan.targets)} targets × {plan.runs} runs"
    result: dict[str, Any] = {"axis": axis, "name": name, "startup": str(startup)}
    written: list[str] = []
    started = time.perf_counter()

    if args.temperatures:
        temps = _floats(args.temperatures, "--temperatures")
        print(f"reference measurement, {label}, at {', '.join(f'{t:g}' for t in temps)} °C")
        points = reference_measurement(bench, plan, temps)
        rows = [row for p in points for row in p.rows(axis)]
        comments = [
            f"reference measurement of axis {name} ({axis}) on the twin of {startup}",
            "geo-server measure --temperatures: the test in a climate chamber per temperature;",
            "deviation = what the temperature compensation must add (000 §3.2, Fig. 5)",
        ]
        written.append(
            str(_write(out / "reference_measurement.csv", iso230.reference_csv(rows, comments)))
        )
        result["reference"] = [
            {"chamber_C": p.chamber, "sensor_C": p.temperature, **p.evaluation.as_dict()}
            for p in points
        ]
        for p in points:
            _print_figures(f"at {p.temperature:.2f} °C", p.evaluation, unit)
    elif args.commission:
        comp = cfg.axes[axis].comp
        lsec = comp.lsec if comp is not None else None
        if comp is None or lsec is None:
            raise MeasureError(f"axis {name} has no LSEC table to commission")
        off = OFF_BILATERAL if lsec.bilateral else OFF_UNILATERAL
        plan = replace(plan, targets=lsec_setpoints(cfg, axis), compensation_off=off)
        print(f"commissioning {label}: measuring with {' and '.join(off)} off")
        before = run_test(bench, plan, name)
        c = commission(before, axis, lsec.bilateral, direction)
        written += write_lists(c, cfg.axes[axis].params.path, comp.path)
        reload = svc.commands.reload()
        if not reload.ok:
            raise MeasureError(f"the lists written do not load: {reload.message}")
        print("lists written and reloaded; measuring with every compensation on")
        after = run_test(bench, replace(plan, compensation_off=()), name)
        result.update(before=before.as_dict(), after=after.as_dict())
        result["backlash"] = c.backlash
        _write(out / "deviations.csv", iso230.deviations_csv(before))
        _write(out / "deviations_after.csv", iso230.deviations_csv(after))
        _print_figures("before (LSEC off)", before, unit)
        _print_figures("after (lists written, reloaded)", after, unit)
        print(
            f"\nA {before.accuracy:.2f} → {after.accuracy:.2f} {unit}, "
            f"E {before.systematic:.2f} → {after.systematic:.2f}, "
            f"B {before.reversal:.2f} → {after.reversal:.2f}"
        )
        if args.plot:
            written += _plots(out, name, before, after, unit, position_unit)
    else:
        print(f"positioning test, {label}")
        ev = run_test(bench, plan, name)
        result["test"] = ev.as_dict()
        _write(out / "deviations.csv", iso230.deviations_csv(ev))
        # list files from the result: the values to load when measured with LEAD and
        # BACKLASH off (--off LEAD,BACKLASH); with them on, the residual
        comp = cfg.axes[axis].comp
        bilateral = args.bilateral or bool(comp and comp.lsec and comp.lsec.bilateral)
        c = commission(ev, axis, bilateral, direction)
        written.append(str(_write(out / f"lsec_{name}.lis", lsec_list(c, name))))
        if c.backlash is not None:
            written.append(str(_write(out / f"backlash_{name}.lis", backlash_lines(c, direction))))
        _print_figures(f"axis {name}", ev, unit)
        if args.plot:
            written += _plots(out, name, ev, None, unit, position_unit)
    result["written"] = written
    result["simulated_s"] = float(access.read_name(svc, "TWIN::time", 0))
    result["host_s"] = round(time.perf_counter() - started, 3)
    _write(out / "result.json", json.dumps(result, indent=1, default=float))
    print(f"\n{result['simulated_s']:.0f} s of machine time in {result['host_s']:.1f} s")
    for f in written:
        print(f"wrote {f}")
    print(f"wrote {out / 'result.json'}")
    return 0


def _plots(
    out: Path,
    name: str,
    before: Evaluation,
    after: Evaluation | None,
    unit: str,
    position_unit: str,
) -> list[str]:
    from geo_server.twin import plots

    try:
        files = [*plots.error_curves(
            before, after, out / "error_curve", f"Axis {name}: positioning deviations",
            unit=unit, position_unit=position_unit,
        )]  # fmt: skip
        files += plots.hysteresis(
            before, out / "hysteresis", f"Axis {name}: reversal", unit=unit,
            position_unit=position_unit,
        )  # fmt: skip
    except RuntimeError as exc:  # matplotlib missing
        print(f"warning: no figures: {exc}", file=sys.stderr)
        return []
    return [str(f) for f in files]


__all__ = ["add_arguments", "main"]
