"""Run every geo-server benchmark and write `bench/RESULTS.md` (docs/design.md §11).

    python bench/run_all.py [--quick] [--only kernel,twin,scheduler,transports,ads_symbols,
                                              cpu,batch,volcomp,recorder,hmi_load,engine,memory,soak,
                                              fleet_isolation]
                            [--results FILE]

Each part runs as its own subprocess (so one crashing library cannot take the others
down) with a time limit, prints its Markdown tables, and the whole report — date, machine,
versions, then every part — goes to `bench/RESULTS.md`. Full run: about 7 minutes;
`--quick`: about 2. Exit status 1 when a part failed (its section says why).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import BENCH, PYTHON, machine_info

#: part -> (script, extra arguments full, extra arguments quick, time limit s)
PARTS: dict[str, tuple[str, list[str], list[str], float]] = {
    "kernel": (
        "kernel.py",
        ["--cycles", "2000", "--ref-cycles", "200"],
        ["--cycles", "300", "--ref-cycles", "30"],
        600,
    ),
    "twin": ("twin.py", ["--cycles", "20000"], ["--cycles", "4000"], 600),
    "scheduler": ("scheduler.py", [], ["--quick"], 900),
    "transports": ("transports.py", [], ["--quick"], 600),
    "ads_symbols": ("ads_symbols.py", [], ["--quick"], 300),
    "cpu": ("cpu.py", [], ["--quick"], 300),
    "batch": ("batch.py", [], ["--passes", "30"], 300),
    "volcomp": ("volcomp.py", [], ["--cycles", "1000"], 300),
    "recorder": ("recorder.py", [], ["--cycles", "2000"], 300),
    "hmi_load": ("hmi_load.py", [], ["--rounds", "1", "--seconds", "1"], 900),
    "engine": ("engine.py", [], ["--quick"], 2400),
    "memory": ("memory.py", [], ["--quick"], 300),
    "soak": ("soak.py", [], ["--quick"], 600),
    "fleet_isolation": ("fleet_isolation.py", [], ["--quick"], 1200),
}


def run_part(name: str, quick: bool) -> str:
    """Run one part; its Markdown (or a note saying why there is none)."""
    script, full, fast, limit = PARTS[name]
    argv = [PYTHON, str(BENCH / script), *(fast if quick else full)]
    t0 = time.monotonic()
    print(f"== {name}: {' '.join(argv[1:])}", flush=True)
    with tempfile.NamedTemporaryFile("r", suffix=".md", prefix=f"bench-{name}-") as out:
        if name not in ("kernel", "twin"):  # these only print their table
            argv += ["--out", out.name]
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        lines: list[str] = []
        try:
            assert proc.stdout is not None
            for line in proc.stdout:  # echo progress; the part's own output is bounded
                print("   " + line, end="", flush=True)
                lines.append(line)
            proc.wait(limit)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        took = time.monotonic() - t0
        if proc.returncode != 0:
            tail = "".join(lines[-15:])
            return f"### {name}\n\n**failed** (exit {proc.returncode}):\n\n```\n{tail}```\n"
        if name == "kernel":
            text = "".join(line for line in lines if line.startswith("|"))
            return (
                "### Kernel: cost per GEO cycle (`bench/kernel.py`)\n\n"
                "Every axis with backlash, temperature, cross (1001 points), plane "
                "(101×101), LSEC (1500, bilateral), friction (20) and crosstalk mode 3 "
                "(15 points), homed and moving with reversals; `Kernel.step` only (no "
                "motion, no snapshot), µs per cycle in one thread; `ReferenceKernel` is the "
                f"plain-Python oracle. Targets: ≤ 50 µs at 8 axes, ≤ 300 µs at 128. "
                f"({' '.join(argv[2:])}, {took:.0f} s)\n\n" + text
            )
        if name == "twin":
            text = "".join(line for line in lines if line.startswith("|"))
            return (
                "### Twin: its share of the GEO cycle (`bench/twin.py`)\n\n"
                "`Machine.run_cycle` (kernel, motion, twin, snapshot) with the twin and with "
                "its step a no-op, interleaved in blocks; every axis moving. Target: the "
                f"twin adds ≤ 30 % (docs/twin.md §7). ({' '.join(argv[2:])}, {took:.0f} s)\n\n"
                + text
            )
        return Path(out.name).read_text(encoding="utf-8")


def header(quick: bool) -> str:
    info = machine_info()
    versions = ", ".join(
        f"{k} {info[k]}" for k in ("geo-server", "numpy", "eclipse-zenoh", "pymodbus", "pyads")
    )
    return (
        "# geo-server benchmark results\n\n"
        f"- date: {info['date']}{' (quick run)' if quick else ''}\n"
        f"- machine: `{info['uname']}`\n"
        f"- CPU: {info['cpu']}, {info['cores']} cores\n"
        f"- Python {info['python']}; {versions}\n"
        f"- command: `python bench/run_all.py{' --quick' if quick else ''}`\n\n"
        "All servers and clients on 127.0.0.1, servers in their own processes; µs unless "
        "stated. Percentiles are of all measured samples (p50 = median).\n\n"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short windows (about 2 minutes)")
    ap.add_argument("--only", default=",".join(PARTS), help="comma-separated parts")
    ap.add_argument("--results", default=str(BENCH / "RESULTS.md"), help="report file")
    args = ap.parse_args()
    parts = [p for p in args.only.split(",") if p]
    unknown = set(parts) - set(PARTS)
    if unknown:
        ap.error(f"unknown parts {sorted(unknown)}; choose from {list(PARTS)}")
    t0 = time.monotonic()
    report = header(args.quick)
    failed = []
    for name in parts:
        text = run_part(name, args.quick)
        if "**failed**" in text:
            failed.append(name)
        report += text + "\n"
    report += f"_Total benchmark time {time.monotonic() - t0:.0f} s._\n"
    Path(args.results).write_text(report, encoding="utf-8")
    print("\n" + report)
    print(f"written to {args.results}")
    if failed:
        print(f"failed parts: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
