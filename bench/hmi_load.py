"""Web HMI open + recording 20 objects every cycle: what it costs the cycle and the
transports (issue 21; docs/web.md §6, docs/recorder.md §8).

One `geo-server run --homed --http …` with every axis moving (an NC program in a loop),
per engine. Rounds alternate *baseline* (nobody on the HMI, no recording) and *loaded*
(a WebSocket client receiving the HMI's pushes, as an open page does, and a recording of
20 values every cycle started over Zenoh `cmd/record`), in the same server, so both see
the same host. Per round: round trips of ADS (pyads), Modbus (pymodbus) and Zenoh reads
(closed loop, one request in flight), then the server's status — the punctual engine's
cycle lateness, the exact engine's catch-up time (both over its last 10 000 cycles).
Samples of all rounds of one kind are pooled; the table gives p50/p99 and loaded/baseline.

    python bench/hmi_load.py [--rounds 4] [--seconds 3] [--engines punctual,exact] [--out F]

The browser's own drawing is not counted: it runs where the operator sits.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import (
    HOST,
    ServerProcess,
    address,
    emit,
    free_ports,
    geo_server_argv,
    get_status,
    start_geo,
    table,
    timed_loop,
    wait_port,
)
from recorder import TWENTY
from transports import ads_reader, modbus_reader, zenoh_reader

#: TEMPC::coefficient of axis 1 (from the dictionary)
COEFF = address("TEMPC::coefficient")

PROGRAM = "N10 G90 G01 X100 Y-50 Z30 C90 F3000\nN20 X-100 Y50 Z-30 C0\nN30 $GOTO N10\n"
READERS = {
    "ADS read": lambda p: ads_reader(p["ads"]),
    "Modbus read": lambda p: modbus_reader(p["modbus"]),
    "Zenoh get": lambda p: zenoh_reader(p["zenoh"], COEFF.raw_key),
}


class HmiWatcher:
    """A WebSocket client on the HMI in its own thread: what an open page receives."""

    def __init__(self, port: int) -> None:
        self.url = f"http://{HOST}:{port}/ws"
        self.messages = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)
        self._thread.start()

    async def _run(self) -> None:
        import aiohttp

        async with aiohttp.ClientSession() as s, s.ws_connect(self.url) as ws:
            while not self._stop.is_set():
                try:
                    await asyncio.wait_for(ws.receive(), 0.5)
                    self.messages += 1
                except TimeoutError:
                    continue

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


def record(session: Any, body: dict[str, Any]) -> dict[str, Any]:
    for reply in session.get("cnc/local/cmd/record", payload=json.dumps(body).encode(), timeout=5):
        if reply.ok is None:
            raise RuntimeError(reply.err.payload.to_bytes())
        result: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
        return result
    raise TimeoutError("cmd/record")


def engine_run(engine: str, rounds: int, seconds: float, folder: Path) -> dict[str, Any]:
    zp, mp, ap, hp = free_ports(4)
    ports = {"zenoh": zp, "modbus": mp, "ads": ap}
    program = folder / "loop.nc"
    program.write_text(PROGRAM, encoding="utf-8")
    # recordings asked for over Zenoh go to --record-dir only (docs/security.md)
    extra = ["--http", f"{HOST}:{hp}", "--program", str(program), "--record-dir", str(folder)]
    argv = geo_server_argv(1.0, ports, extra=extra, engine=engine)
    samples: dict[str, dict[str, list[np.ndarray]]] = {
        k: {"baseline": [], "loaded": []} for k in [*READERS, "cycle"]
    }
    pushes = 0
    with ServerProcess(argv, f"hmi-load-{engine}") as srv:
        session = start_geo(srv, ports, min_cycles=500)
        wait_port(hp, 20.0, srv.proc)
        try:
            for r in range(2 * rounds):
                kind = "loaded" if r % 2 else "baseline"
                watcher = None
                if kind == "loaded":
                    watcher = HmiWatcher(hp)
                    out = f"trace-{engine}-{r}.csv"  # (a name in --record-dir)
                    started = record(session, {"start": {"objects": TWENTY, "out": out}})
                    assert started["recording"]["columns"] == 20, started
                time.sleep(1.0)
                for label, factory in READERS.items():
                    read, close = factory(ports)
                    try:
                        rtt, _ = timed_loop(read, 100_000, seconds)
                    finally:
                        close()
                    samples[label][kind].append(rtt)
                time.sleep(max(0.0, 10.5 - 1.0 - 3 * seconds))  # the status window: this round
                st = get_status(session)
                key = "lateness" if engine == "punctual" else "sync"
                samples["cycle"][kind].append(np.array([st[f"{key}_p50_us"], st[f"{key}_p99_us"]]))
                if watcher is not None:
                    stopped = record(session, {"stop": True})["recording"]
                    watcher.close()
                    pushes += watcher.messages
                    print(
                        f"  {engine} round {r + 1}: loaded, {stopped['rows']} rows recorded, "
                        f"{watcher.messages} HMI messages",
                        flush=True,
                    )
                else:
                    print(f"  {engine} round {r + 1}: baseline", flush=True)
        finally:
            session.close()
    return {"samples": samples, "pushes": pushes}


def report(results: dict[str, dict[str, Any]], rounds: int, seconds: float) -> str:
    rows = []
    for engine, res in results.items():
        s = res["samples"]
        for label in READERS:
            base = np.concatenate(s[label]["baseline"])
            load = np.concatenate(s[label]["loaded"])
            b50, l50 = np.median(base), np.median(load)
            b99, l99 = np.percentile(base, 99), np.percentile(load, 99)
            rows.append(
                [
                    engine,
                    f"{label} round trip",
                    f"{b50:.0f} / {b99:.0f}",
                    f"{l50:.0f} / {l99:.0f}",
                    f"{l50 / b50:.2f} / {l99 / b99:.2f}",
                ]
            )
        cb = np.mean(s["cycle"]["baseline"], axis=0)
        cl = np.mean(s["cycle"]["loaded"], axis=0)
        what = "cycle lateness" if engine == "punctual" else "catch-up per request"
        rows.append(
            [
                engine,
                what,
                f"{cb[0]:.0f} / {cb[1]:.0f}",
                f"{cl[0]:.0f} / {cl[1]:.0f}",
                f"{cl[0] / max(cb[0], 1):.2f} / {cl[1] / max(cb[1], 1):.2f}",
            ]
        )
    return (
        f"## Web HMI open + recording 20 values every cycle ({rounds} rounds of each, "
        f"{seconds:g} s per transport, machine moving; µs, p50 / p99)\n\n"
        + table(["engine", "measurement", "baseline", "HMI + recording", "ratio"], rows, "llrrr")
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--engines", default="punctual,exact")
    p.add_argument("--out")
    args = p.parse_args()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for engine in args.engines.split(","):
            results[engine] = engine_run(engine, args.rounds, args.seconds, Path(tmp))
    emit(report(results, args.rounds, args.seconds), args.out)


if __name__ == "__main__":
    main()
