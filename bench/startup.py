"""Start-up benchmark (docs/design.md §13.3): from `geo-server run --homed` to its first
answer, and to its cycle's machine code.

For each case a fresh server process (every interface on, the default machine): the
time until a Modbus read of TEMPC::coefficient (FC 3, unit 1, registers 268…271) is
answered, and until its status line no longer says `interpreted` (the compiled cycle
loaded, geo_server/jit.py). Cases: a *warm* cache (the compiled cycle in the cache, as
on every start but the first), *after a reinstall* (a copy of this tree's package with new
modification times, as `pip install` makes, and the same cache: keyed by content, it is
still warm) and a *cold* one (an empty cache folder: the first start after an
installation of another version or an edit of a law compiles). `--against TREE` runs another source
tree (e.g. the code before a change, exported with `git archive`) in the same run,
alternating, for the warm case (a tree without the compiler has no cold case).

    python bench/startup.py [--rounds N] [--against TREE] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
from common import emit, free_ports, table

#: FC 3 of TEMPC::coefficient, axis 1 (docs/modbus-map.md)
REQUEST = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 268, 4)


def _ask(port: int) -> bool:
    with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
        s.sendall(REQUEST)
        return len(s.recv(64)) == 17  # header + FC 3 + byte count + 8 bytes


def start_once(tree: str | None, cache: str | None) -> tuple[float, float | None]:
    """(s to the first answer, s to the compiled cycle or None) of one server start."""
    modbus, ads, zenoh, opcua = free_ports(4)
    env = dict(os.environ)
    if tree:
        env["PYTHONPATH"] = tree
    if cache:
        env["GEO_SERVER_JIT_CACHE"] = cache
    argv = [sys.executable, "-m", "geo_server.cli", "run", "--homed", "--status-period", "0.05",
            "--modbus-port", str(modbus), "--ads-port", str(ads),
            "--zenoh-listen", f"tcp/127.0.0.1:{zenoh}",
            "--opcua-endpoint", f"opc.tcp://127.0.0.1:{opcua}"]  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        argv, env=env, cwd=tree or None, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
        text=True,
    )  # fmt: skip
    compiled: list[float] = []

    def watch() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith("cycle ") and "interpreted" not in line and not compiled:
                compiled.append(time.perf_counter() - t0)

    reader = threading.Thread(target=watch, daemon=True)
    reader.start()
    try:
        while True:
            try:
                if _ask(modbus):
                    break
            except OSError:
                time.sleep(0.002)
            if time.perf_counter() - t0 > 120:
                raise RuntimeError("no answer within 120 s")
        first = time.perf_counter() - t0
        deadline = time.perf_counter() + 90
        while not compiled and time.perf_counter() < deadline and proc.poll() is None:
            time.sleep(0.01)
    finally:
        proc.terminate()
        proc.wait(10)
    return first, (compiled[0] if compiled else None)


def _reinstall(into: str) -> str:
    """This tree's package and data copied into `into` with new modification times (what
    a reinstall changes); returns the tree."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for part in ("geo_server", "objects", "lists"):
        shutil.copytree(os.path.join(here, part), os.path.join(into, part),
                        copy_function=shutil.copy,
                        ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    return into


def _fmt(xs: list[float]) -> str:
    return f"{np.median(xs):.2f} ({min(xs):.2f}–{max(xs):.2f})" if xs else "–"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--against", help="another source tree, run alternating (warm case)")
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    start_once(None, None)  # the warm cache of this tree (compiles on a first run)
    cases: dict[str, tuple[list[float], list[float]]] = {}
    for _ in range(args.rounds):
        plan: list[tuple[str, str | None, str | None]] = [("this tree, warm cache", None, None)]
        if args.against:
            plan.append((f"{args.against}, warm", args.against, None))
        for label, tree, cache in plan:
            first, comp = start_once(tree, cache)
            got = cases.setdefault(label, ([], []))
            got[0].append(first)
            if comp is not None and tree is None:  # (a tree without the compiler: none)
                got[1].append(comp)
    with tempfile.TemporaryDirectory() as copy:
        reinstalled = _reinstall(copy)
        again = cases.setdefault("this tree reinstalled, same cache", ([], []))
        for _ in range(max(1, args.rounds // 3)):
            first, comp = start_once(reinstalled, None)
            again[0].append(first)
            if comp is not None:
                again[1].append(comp)
    cold = cases.setdefault("this tree, cold cache", ([], []))
    for _ in range(max(1, args.rounds // 3)):
        with tempfile.TemporaryDirectory() as empty:
            first, comp = start_once(None, empty)
        cold[0].append(first)
        if comp is not None:
            cold[1].append(comp)
    rows = [[label, _fmt(a), _fmt(b)] for label, (a, b) in cases.items()]
    md = "### Start-up: `geo-server run --homed` to its first answer (s, median (range))\n\n"
    md += table(["case", "first Modbus answer", "compiled cycle loaded"], rows)
    md += (
        "\nEvery interface on (Zenoh, Modbus, ADS, OPC UA). *Compiled cycle loaded*: the first "
        "status line that no longer says `interpreted` (status every 50 ms); a tree without "
        "the compiler has none.\n"
    )
    emit(md, args.out)


if __name__ == "__main__":
    main()
