"""A warm-up of the twin, with and without the PLC temperature client (docs/twin.md).

The default machine's twin warms up as a workshop does in the morning (its ambient
profile: +3 K in two hours) while one axis works — strokes between two positions near
the end of its travel, where the thermal error is largest — and the screw heats from the
motion. Each time the axis arrives at the far position (moving in its reference
direction) the residual error `TWIN::residual` and the sensor `TWIN::sensor_temperature`
are recorded: the thermal drift of the tool position over the warm-up.

With `plc=True` the PLC temperature client (`geo_clients.plc_tempcomp`) runs beside it:
every `period_s` of simulated time it reads each axis' twin sensor over a real transport
(`via`: Zenoh, Modbus or ADS) and writes the TEMPC parameters derived from the reference
measurement of the twin (`data/twin_reference_measurement.csv`, made by
`lists/tools/make_twin_reference.py`). The machine runs stepped (deterministic) with a
time scale, so four hours take a few seconds.

    geo-warmup --hours 4 --via modbus --plot out/     # both runs, figures, CSV

prints the residual at the start and the end and its worst value, with and without the
client, and writes `warmup.csv` and (with `--plot`) `warmup.png/.svg`.
"""

from __future__ import annotations

import argparse
import csv
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path

from geo_clients.plc_tempcomp import TemperatureAdapter, TwinSensors, load_reference
from geo_clients.testing import GeoTestServer
from geo_server.twin.measure import StepBench
from geo_server.units import UNITS_PER_MM, UNITS_PER_UM

#: The twin's reference measurement for the default machine (axes X, Y, Z).
TWIN_REFERENCE = Path(__file__).resolve().parent / "data" / "twin_reference_measurement.csv"


@dataclass
class WarmupRecord:
    """The samples of one warm-up: one per arrival at the far position."""

    axis: int
    position_mm: float
    plc: bool
    times_s: list[float] = field(default_factory=list)
    residual_um: list[float] = field(default_factory=list)
    sensor_C: list[float] = field(default_factory=list)
    ambient_C: list[float] = field(default_factory=list)
    writes: int = 0

    @property
    def worst_um(self) -> float:
        """The largest |residual| over the warm-up."""
        return max(abs(r) for r in self.residual_um)

    @property
    def drift_um(self) -> float:
        """How far the residual moved from its first value, at most."""
        return max(abs(r - self.residual_um[0]) for r in self.residual_um)


def run_warmup(
    *,
    hours: float = 4.0,
    axis: str = "X",
    stroke_mm: tuple[float, float] = (400.0, 500.0),
    plc: bool = False,
    via: str = "modbus",
    period_s: float = 10.0,
    time_scale: float = 250.0,
    reference: Path | str = TWIN_REFERENCE,
    startup: Path | str | None = None,
) -> WarmupRecord:
    """Run one warm-up (module docstring) on a fresh stepped server; `time_scale`
    simulated seconds per cycle second (1 ms cycles: 0.25 s each at 250)."""
    with GeoTestServer(startup, time_scale=time_scale) as srv:
        nr = srv.axis(axis)
        lo, hi = (round(p * UNITS_PER_MM) for p in stroke_mm)
        rec = WarmupRecord(nr, stroke_mm[1], plc)
        adapter = None
        if plc:
            srv.start(via)
            client = srv.client(via)
            adapter = TemperatureAdapter(
                client, load_reference(reference), TwinSensors(client, [nr]), axes=[nr]
            )
        end = hours * 3600.0
        next_tick = 0.0
        target = hi
        bench = StepBench(srv.service)  # its `at` knows modulo axes
        srv.write("SIM::target_position", nr, target)
        # bounded: the simulated hours in cycles, and as much again for slow strokes
        for _ in range(
            2 * round(end / (srv.machine.cycle_s * srv.machine.twin.time_scale)) + 200_000
        ):
            t = float(srv.read("TWIN::time"))
            if adapter is not None and t >= next_tick:
                rec.writes += len(adapter.tick(t).writes)
                next_tick += period_s
            srv.step(1)
            if not bench.at(nr, target):
                continue
            if target == hi:
                rec.times_s.append(t)
                rec.residual_um.append(float(srv.read("TWIN::residual", nr)) / UNITS_PER_UM)
                rec.sensor_C.append(float(srv.read("TWIN::sensor_temperature", nr)))
                rec.ambient_C.append(float(srv.read("TWIN::ambient_temperature")))
                if t >= end:
                    return rec
            target = lo if target == hi else hi
            srv.write("SIM::target_position", nr, target)
        raise RuntimeError(f"axis {axis} did not complete its strokes in time")


def write_csv(path: Path, records: list[WarmupRecord]) -> None:
    """One row per sample: run, time, residual, sensor, ambient."""
    with path.open("w", encoding="utf-8", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["run", "time_s", "residual_um", "sensor_C", "ambient_C"])
        for r in records:
            run = "with PLC client" if r.plc else "without"
            for row in zip(r.times_s, r.residual_um, r.sensor_C, r.ambient_C, strict=True):
                w.writerow([run, *(f"{v:.4f}" for v in row)])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="geo-warmup", description=__doc__.split("\n\n")[0])
    p.add_argument("--hours", type=float, default=4.0, help="simulated hours (default 4)")
    p.add_argument("--axis", default="X", help="axis name (default X)")
    p.add_argument("--via", default="modbus", choices=("service", "zenoh", "modbus", "ads"))
    p.add_argument("--period", type=float, default=10.0, help="PLC period, simulated s")
    p.add_argument("--time-scale", type=float, default=250.0, help="default 250")
    p.add_argument("--out", default="warmup", help="folder for warmup.csv and the figures")
    p.add_argument("--plot", action="store_true", help="warmup.png/.svg (needs matplotlib)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    common = {"hours": args.hours, "axis": args.axis, "via": args.via}
    common |= {"period_s": args.period, "time_scale": args.time_scale}
    without = run_warmup(plc=False, **common)
    with_plc = run_warmup(plc=True, **common)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "warmup.csv", [without, with_plc])
    for r in (without, with_plc):
        what = f"with the PLC client over {args.via}" if r.plc else "without the PLC client"
        print(
            f"{args.axis} at {r.position_mm:g} mm, {what}: residual {r.residual_um[0]:+.2f} → "
            f"{r.residual_um[-1]:+.2f} µm, worst {r.worst_um:.2f} µm; sensor "
            f"{r.sensor_C[0]:.2f} → {r.sensor_C[-1]:.2f} °C"
            + (f"; {r.writes} TEMPC writes" if r.plc else "")
        )
    if args.plot:
        from geo_server.twin import plots

        try:
            files = plots.warmup(
                without.times_s,
                {
                    "without PLC client": without.residual_um,
                    "with PLC client": with_plc.residual_um,
                },
                {"sensor": without.sensor_C, "ambient": without.ambient_C},
                out / "warmup",
                f"Axis {args.axis} at {without.position_mm:g} mm: a {args.hours:g}-hour warm-up",
            )
        except RuntimeError as exc:
            print(f"warning: no figures: {exc}", file=sys.stderr)
            return 0
        for f in files:
            print(f"wrote {f}")
    print(f"wrote {out / 'warmup.csv'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
