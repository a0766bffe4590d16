"""Start and stop `geo-server run` many times: no abort, every exit code documented.

Each start runs the default machine with every interface on its own ports and
`PYTHONFAULTHANDLER=1`, connects a client on every interface it can reach in the time
it has (raw Modbus and ADS requests, a Zenoh get, an OPC UA Hello), and sends Ctrl-C
(SIGINT) or SIGTERM at a random moment — before the interfaces are up, while they start,
while clients talk. Every `--cold-every`th start uses an empty compile cache, so the
signal often lands while the cycle compiles.

    python bench/startstop.py [--starts 200] [--cold-every 20] [--seed 1]

Accepted exit codes: 0 (stopped), 130 (Ctrl-C before it served: `entry.EXIT_INTERRUPTED`),
and -2 or -15 (SIGINT or SIGTERM while Python was still importing, before any handler was
installed: the signal's default action; a shell shows 130 and 143). Anything
else — above all -6 (SIGABRT) — is listed with the start's output. Exit status 0 when
every start ended with an accepted code.
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time

from common import free_ports

ACCEPTED = {0, 130, -signal.SIGINT, -signal.SIGTERM}
#: FC 3 of TEMPC::coefficient, axis 1 (docs/modbus-map.md)
MODBUS = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 268, 4)
#: ADS ReadDeviceInfo to port 551 (an AMS/TCP frame with an empty body)
ADS = struct.pack("<HI", 0, 32) + bytes([127, 0, 0, 1, 1, 1]) + struct.pack("<H", 551)
ADS += bytes([127, 0, 0, 1, 1, 1]) + struct.pack("<HHHIII", 32905, 1, 4, 0, 0, 1)
#: OPC UA Hello (version 0, buffers 65535, no limits, an endpoint URL)
URL = b"opc.tcp://127.0.0.1"
OPCUA = b"HELF" + struct.pack("<IIIIII", 32 + len(URL), 0, 65535, 65535, 0, 0)
OPCUA += struct.pack("<i", len(URL)) + URL


def _poke(port: int, frame: bytes) -> None:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5) as s:
            s.sendall(frame)
            s.recv(256)
    except OSError:
        pass


def one_start(rng: random.Random, cold: bool) -> tuple[int, str, float]:
    modbus, ads, zenoh, opcua = free_ports(4)
    env = {**os.environ, "PYTHONFAULTHANDLER": "1"}
    empty = tempfile.mkdtemp() if cold else None
    if empty:
        env["GEO_SERVER_JIT_CACHE"] = empty
    argv = [sys.executable, "-m", "geo_server.cli", "run", "--homed", "--status-period", "0.2",
            "--modbus-port", str(modbus), "--ads-port", str(ads),
            "--zenoh-listen", f"tcp/127.0.0.1:{zenoh}",
            "--opcua-endpoint", f"opc.tcp://127.0.0.1:{opcua}"]  # fmt: skip
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    when = rng.uniform(0.0, 6.0 if cold else 3.0)
    t0 = time.monotonic()
    while time.monotonic() - t0 < when and proc.poll() is None:
        _poke(modbus, MODBUS)
        _poke(ads, ADS)
        _poke(opcua, OPCUA)
        time.sleep(0.05)
    proc.send_signal(rng.choice([signal.SIGINT, signal.SIGINT, signal.SIGTERM]))
    try:
        out, _ = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        return -999, out.decode(errors="replace"), when
    finally:
        if empty:
            shutil.rmtree(empty, ignore_errors=True)
    return proc.returncode, out.decode(errors="replace"), when


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=200)
    ap.add_argument("--cold-every", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    codes: dict[int, int] = {}
    bad: list[tuple[int, int, float, str]] = []
    t0 = time.monotonic()
    for i in range(args.starts):
        cold = args.cold_every > 0 and i % args.cold_every == args.cold_every - 1
        code, out, when = one_start(rng, cold)
        codes[code] = codes.get(code, 0) + 1
        if code not in ACCEPTED:
            bad.append((i, code, when, out[-3000:]))
            print(f"start {i}: exit {code} after {when:.2f} s{' (cold)' if cold else ''}")
    secs = time.monotonic() - t0
    print(f"{args.starts} starts in {secs / 60:.1f} min; exit codes {dict(sorted(codes.items()))}")
    for i, code, when, out in bad:
        print(f"--- start {i}, exit {code}, signal after {when:.2f} s:\n{out}")
    aborts = codes.get(-signal.SIGABRT, 0)
    print(f"aborts: {aborts}; unaccepted exits: {len(bad)}")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
