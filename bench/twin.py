"""Twin benchmark (docs/twin.md, "Cost"): what the physical twin adds to a GEO cycle.

Two machines, every axis moving back and forth (reversals, arrivals: the scatter and
the thermal model are exercised):

- the default machine (4 axes, lists/ and its twin.toml);
- 32 axes with every compensation at manual table sizes (the kernel benchmark's
  machine) and a twin on every axis: a 101-point pitch curve, cyclic error, lost
  motion, straightness over the next axis (101 points), expansion on one of 8 thermal
  nodes with a sensor each, scatter and friction.

For each: the median and p99 of `Machine.run_cycle` (kernel, motion, twin, snapshot) of
the machine with its twin and of the same machine with a perfect one (no twin file: no
curves, no thermal nodes, no sensors), interleaved in blocks so both see the same host;
the median of the twin's outputs alone (`TwinEngine.evaluate`, what a published cycle
adds; its state advances inside the compiled cycle, docs/design.md §13.3); and the
twin's share (with − without) / without, the figure the SPEC bounds at 30 %.

    python bench/twin.py [--cycles N]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from geo_server import access, jit
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.model import MachineConfig
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService
from geo_server.twin.model import (
    AxisTwin,
    Curve,
    Expansion,
    Sensor,
    Straightness,
    ThermalNode,
    TwinConfig,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.machines import full_machine


def twin_for(n: int) -> TwinConfig:
    """A twin with every kind of error on each of n axes named A1 … An."""
    rng = np.random.default_rng(3)
    positions = tuple(float(p) for p in np.linspace(-500, 500, 101))
    nodes = tuple(ThermalNode(f"n{k}", 1800.0, 20.0, f"A{k + 1}", 10.0, 2.0) for k in range(8))
    sensors = tuple(Sensor(f"n{k}", f"n{k}", f"A{k + 1}", 0.02, 0.01, 0.1) for k in range(8))
    axes = {}
    for i in range(n):
        name = f"A{i + 1}"
        errors = tuple(float(e) for e in np.cumsum(rng.normal(0, 0.5, 101)))
        axes[name] = AxisTwin(
            name,
            linear_slope=-20.0,
            pitch=Curve(positions, errors),
            periodic_amplitude=0.5,
            periodic_period=10.0,
            reversal=5.0,
            straightness=(Straightness(f"A{(i + 1) % n + 1}", Curve(positions, errors)),),
            expansion=Expansion(f"n{i % 8}", 11.5),
            friction_coulomb=2000.0,
            friction_viscous=12.0,
            scatter=0.3,
        )
    return TwinConfig(nodes=nodes, sensors=sensors, axes=axes)


def measure(cfg: MachineConfig, cycles: int, block: int = 200) -> dict[str, float]:
    perfect = dataclasses.replace(cfg, twin=TwinConfig())
    machines = [Machine(c, homed=True) for c in (cfg, perfect)]
    services = [ObjectService(m) for m in machines]
    axes = list(machines[0].axes)
    times: list[list[float]] = [[], []]  # with the twin, with the perfect one
    twin_only: list[float] = []
    flip = 1

    def stroke() -> None:
        nonlocal flip
        flip = -flip
        for svc in services:
            for slot, nr in enumerate(axes):
                span = 200_000 if cfg.axes[nr].params.kind == "T" else 100_000
                access.write_name(svc, "SIM::target_position", nr, flip * span * (1 + slot % 3))

    done = 0
    while done < cycles:
        stroke()  # every block pair: the axes reverse, accelerate, arrive
        for m, target in zip(machines, times, strict=True):
            for _ in range(block):
                t0 = time.perf_counter_ns()
                m.run_cycle()
                target.append((time.perf_counter_ns() - t0) / 1000.0)
        m = machines[0]
        for _ in range(20):
            t0 = time.perf_counter_ns()
            m.twin.evaluate(m._output, m.motion.pos, m.motion.vel)
            twin_only.append((time.perf_counter_ns() - t0) / 1000.0)
        done += 2 * block
    w, wo = np.median(times[0]), np.median(times[1])
    return {
        "with": float(w),
        "with_p99": float(np.percentile(times[0], 99)),
        "without": float(wo),
        "twin": float(np.median(twin_only)),
        "share": float((w - wo) / wo * 100.0),
    }


def main() -> None:
    jit.load()  # the cycle's machine code before anything is timed (geo_server/jit.py)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=20_000)
    args = ap.parse_args()
    default = load_machine(default_startup_list())
    big = full_machine(32)
    big.twin = twin_for(32)
    print("| machine | cycle with twin, median µs | p99 µs | without twin, median µs |", end="")
    print(" twin outputs alone, median µs | twin's share |")
    print("|---|---:|---:|---:|---:|---:|")
    for label, cfg in (("default (4 axes)", default), ("32 axes, full twin", big)):
        r = measure(cfg, args.cycles)
        print(
            f"| {label} | {r['with']:.1f} | {r['with_p99']:.1f} | {r['without']:.1f} | "
            f"{r['twin']:.1f} | {r['share']:+.0f} % |",
            flush=True,
        )


if __name__ == "__main__":
    main()
