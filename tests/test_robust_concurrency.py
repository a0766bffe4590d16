"""Concurrent writers on all three transports at once against a running GEO cycle.

Design (so that the result is checkable):

- three writer threads, one per transport, each with its own client of the project's
  library (`geo_server.client.connect`);
- writer k owns `TEMPC::offset_0` of axis k and writes a strictly increasing sequence
  of distinct values to it (waiting for each acknowledgement before the next write);
- all writers also share one object, `TEMPC::coefficient` of axis 4, writing values that
  are distinct across writers (writer w, write i -> w·1000 + i + 0.25), interleaved with
  their own writes;
- a service-side observer (`ObjectService.subscribe_changes`, called on the cycle thread
  after *every* cycle) records each value change with its cycle number;
- every write records when it was sent and when it was acknowledged.

Then: each acknowledged write to an owned object was observed exactly once, in the order
written (an acknowledged write is applied exactly once, in arrival order); on the shared
object no value appears twice, each writer's values appear in its own order, and a write
acknowledged before another was sent is never observed after it; the final value of
every object is the last observed one, and all three transports read back exactly that.
"""

from __future__ import annotations

import threading
import time

import pytest
from robust.harness import TIMEOUT, FullServer, next_netid

from geo_server import access
from geo_server.client import connect

VIAS = ("zenoh", "modbus", "ads")
OWN = "TEMPC::offset_0"
SHARED = "TEMPC::coefficient"
SHARED_AXIS = 4
WRITES = 120  # per writer and object: 3 × 2 × 120 = 720 acknowledged writes


def open_client(srv: FullServer, via: str):
    if via == "zenoh":
        return connect(
            "zenoh", machine=srv.machine_name, connect=[srv.zenoh_endpoint], timeout=TIMEOUT
        )
    if via == "modbus":
        assert srv.modbus is not None
        return connect("modbus", host="127.0.0.1", port=srv.modbus.port, timeout=TIMEOUT)
    assert srv.ads is not None
    return connect("ads", host="127.0.0.1", port=srv.ads.port, netid=next_netid(), timeout=TIMEOUT)


@pytest.mark.slow
def test_concurrent_writers_on_all_transports(loop_thread, lists_copy):
    with FullServer(loop_thread, lists_copy) as srv:
        service = srv.service
        observed: dict[tuple[str, int], list[tuple[int, object]]] = {}
        watched = [(OWN, k) for k in (1, 2, 3)] + [(SHARED, SHARED_AXIS)]

        def on_change(changed: dict) -> None:  # cycle thread, after every cycle
            cycle = service.current(stale_ok=True).cycle
            for key, value in changed.items():
                observed.setdefault(key, []).append((cycle, value))

        initial = {key: access.read_name(service, *key) for key in watched}
        unsubscribe = service.subscribe_changes(watched, on_change)
        # the observer's first call (on the cycle thread) reports the initial values
        deadline = time.monotonic() + TIMEOUT
        while not all(observed.get(key) for key in watched) and time.monotonic() < deadline:
            time.sleep(0.001)
        assert all(observed.get(key) for key in watched)
        for key in watched:
            assert [v for _c, v in observed[key]] == [initial[key]]
            observed[key].clear()
        clients = {via: open_client(srv, via) for via in VIAS}
        # (via, name, axis, value, t_sent, t_acked)
        log: list[tuple[str, str, int, object, float, float]] = []
        errors: list[str] = []
        start = threading.Barrier(len(VIAS))
        cycle0 = srv.cycle

        def writer(w: int, via: str) -> None:
            c = clients[via]
            axis = w + 1
            start.wait()
            try:
                for i in range(WRITES):
                    for name, ax, value in (
                        (OWN, axis, 10_000 * axis + i),  # strictly increasing, distinct
                        (SHARED, SHARED_AXIS, w * 1000 + i + 0.25),
                    ):
                        t0 = time.monotonic()
                        c.write(name, ax, value)
                        log.append((via, name, ax, value, t0, time.monotonic()))
            except Exception as exc:
                errors.append(f"{via}: {type(exc).__name__}: {exc}")

        threads = [
            threading.Thread(target=writer, args=(w, via), name=f"writer-{via}")
            for w, via in enumerate(VIAS)
        ]
        try:
            t_start = time.monotonic()
            for t in threads:
                t.start()
            for t in threads:
                t.join(120)
            elapsed = time.monotonic() - t_start
            assert not any(t.is_alive() for t in threads)
            assert not errors, errors
            assert len(log) == len(VIAS) * 2 * WRITES

            # one more cycle so that the observer has seen the last applied write
            target = srv.cycle + 2
            deadline = time.monotonic() + TIMEOUT
            while srv.cycle < target and time.monotonic() < deadline:
                time.sleep(0.001)
            unsubscribe()

            # -- owned objects: exactly the acknowledged values, once each, in order
            for w, via in enumerate(VIAS):
                key = (OWN, w + 1)
                acked = [v for (vv, n, a, v, _s, _t) in log if vv == via and n == OWN]
                seen = [v for _c, v in observed.get(key, [])]
                assert seen == acked, (via, seen[:5], acked[:5])
                assert acked == sorted(acked) and len(set(acked)) == WRITES
                cycles = [c for c, _v in observed[key]]
                assert cycles == sorted(cycles) and len(set(cycles)) == len(cycles)

            # -- the shared object
            shared_seen = [v for _c, v in observed.get((SHARED, SHARED_AXIS), [])]
            assert len(shared_seen) == len(set(shared_seen)), "a value appeared twice"
            shared_acked = {v: (s, t) for (_via, n, _a, v, s, t) in log if n == SHARED}
            assert set(shared_seen) <= set(shared_acked), "a value nobody wrote"
            position = {v: i for i, v in enumerate(shared_seen)}
            for w in range(len(VIAS)):  # each writer's values in its own order
                mine = [v for v in shared_seen if int(v) // 1000 == w]
                assert mine == sorted(mine), (w, mine[:10])
            # real-time order: acknowledged before the other was sent -> observed before
            by_ack = sorted(shared_acked.items(), key=lambda kv: kv[1][1])
            inversions = 0
            for v_a, (_s_a, t_a) in by_ack:
                if v_a not in position:
                    continue  # overwritten in the same cycle by a later arrival
                for v_b, (s_b, _t_b) in shared_acked.items():
                    if s_b > t_a and v_b in position and position[v_b] < position[v_a]:
                        inversions += 1
            assert inversions == 0
            # most shared writes are visible on their own (not all overwritten)
            assert len(shared_seen) >= WRITES, len(shared_seen)
            # the final value is some writer's LAST shared write (applied after its others)
            last_of_writer = {w * 1000 + WRITES - 1 + 0.25 for w in range(len(VIAS))}
            assert shared_seen[-1] in last_of_writer

            # -- every transport reads back the same last values
            final = {
                (OWN, 1): observed[(OWN, 1)][-1][1],
                (OWN, 2): observed[(OWN, 2)][-1][1],
                (OWN, 3): observed[(OWN, 3)][-1][1],
                (SHARED, SHARED_AXIS): shared_seen[-1],
            }
            for key, value in final.items():
                assert value != initial[key]
                assert access.read_name(service, *key) == value, key
                for via, c in clients.items():
                    assert c.read(*key) == value, (via, key)

            # the cycle kept running at (generously) half its nominal rate or better
            assert srv.cycle - cycle0 >= 0.5 * elapsed / srv.machine.cycle_s
            assert srv.scheduler.cycle_errors == 0
        finally:
            for c in clients.values():
                c.close()
