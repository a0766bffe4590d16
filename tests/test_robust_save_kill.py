"""`save` killed with SIGKILL at random moments (docs/design.md §4: a crash at any moment
leaves either the old or the new file).

A child process (`tests/robust/save_child.py`) loads a private copy of the default lists
and saves new `TEMPC::coefficient` / `TEMPC::offset_0` values of axis 1 in a loop,
alternating two value sets A and B that are new in every round; the parent kills it with
SIGKILL after a random delay (fixed seed) — `KILLS` times, in every other round counted
from the child's first completed save (under load a worker can be slow to start its
first save, and every kill would otherwise land before it). After each kill the axis list
must be byte-identical to one of the complete versions it can legally be in: the one
before the round, the A version or the B version. The parent computes these byte strings
itself (token replacement on the original bytes, not the project's writer).

Temporary files: the writer creates them with `tempfile.mkstemp(prefix=".<list>.",
suffix=".tmp")` in the list's folder. A kill between creating and renaming one leaves it
behind; it is a hidden file ending in `.tmp` that no start-up list names (lists are only
ever opened by the names the start-up list gives), so it cannot be mistaken for a list.
The test checks that every stray file has exactly that form and that the machine still
loads the surviving list.
"""

from __future__ import annotations

import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from geo_server.listfile import load_machine

KILLS = 30
MAX_DELAY_S = 0.04  # kill 0…40 ms after the worker is ready (its saves take ~1 ms each)
CHILD = Path(__file__).parent / "robust" / "save_child.py"


def with_values(original: bytes, coefficient: str, offset_0: str) -> bytes:
    """The axis list with the two value tokens replaced (comments and layout kept)."""
    out = original
    for name, value in (
        (b"lr_param.temp_comp_coefficient", coefficient),
        (b"lr_param.temp_comp_offset_0", offset_0),
    ):
        pattern = re.compile(rb"^(" + re.escape(name) + rb"[ \t]+)(\S+)", re.MULTILINE)
        out, n = pattern.subn(lambda m, v=value: m.group(1) + v.encode(), out)
        assert n == 1, name
    return out


@pytest.mark.slow
def test_save_killed_at_random_points(lists_copy: Path):
    folder = lists_copy.parent
    axis_list = folder / "achsmd1.lis"
    original = axis_list.read_bytes()
    files_before = {p.name for p in folder.iterdir()}
    rng = random.Random(0x5A7E)
    child = subprocess.Popen(
        [sys.executable, str(CHILD), str(lists_copy)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=folder,
    )
    outcomes = {"before": 0, "A": 0, "B": 0}
    after_a_save = []  # the outcomes of the rounds killed after the worker's first save
    previous = original
    try:
        assert child.stdin is not None and child.stdout is not None
        assert child.stdout.readline().strip() == "zygote"
        for r in range(KILLS):
            # new, distinct values every round (REAL64 saved in shortest repr form)
            a = (4000 + 2 * r + 0.5, 1000 + 2 * r)
            b = (4000 + 2 * r + 1.5, 1000 + 2 * r + 1)
            child.stdin.write(f"go {a[0]!r} {a[1]} {b[0]!r} {b[1]}\n")
            child.stdin.flush()
            line = child.stdout.readline().split()
            assert line[0] == "ready", line
            pid = int(line[1])
            if r % 2:  # every other round from after its first save, however slow it is
                assert child.stdout.readline().split() == ["saved"]
            time.sleep(rng.uniform(0, MAX_DELAY_S))
            os.kill(pid, signal.SIGKILL)  # (a zombie until the zygote reaps it: no reuse)
            dead = child.stdout.readline().split()
            if dead == ["saved"]:  # (a first save before the kill, not waited for)
                dead = child.stdout.readline().split()
            assert dead == ["dead", "9"], dead  # killed, not finished or failed

            now = axis_list.read_bytes()
            legal = {
                "before": previous,
                "A": with_values(original, repr(a[0]), str(a[1])),
                "B": with_values(original, repr(b[0]), str(b[1])),
            }
            matches = [k for k, v in legal.items() if v == now]
            assert matches, f"round {r}: the list is no complete version:\n{now.decode()}"
            outcomes[matches[0]] += 1
            if r % 2:
                after_a_save.append(matches[0])
            previous = now
        child.stdin.close()
        assert child.wait(10) == 0
    finally:
        if child.poll() is None:
            child.kill()
            child.wait(5)
        if child.stdout is not None:
            child.stdout.close()

    # a round killed after a completed save has that save's file (or the next one's),
    # never the one before it: the save replaced the list (on a loaded machine the
    # other rounds may all end before their first save)
    assert set(after_a_save) <= {"A", "B"}, (after_a_save, outcomes)
    # stray temporary files: only the writer's hidden `.achsmd1.lis.*.tmp`, never a list
    stray = sorted(p.name for p in folder.iterdir() if p.name not in files_before)
    assert all(re.fullmatch(r"\.achsmd1\.lis\.[^/]+\.tmp", n) for n in stray), stray
    # the surviving list loads and holds the values of the last complete save
    cfg = load_machine(lists_copy)
    assert not [d for d in cfg.diagnostics if d.severity == "error"]
    text = previous.decode("utf-8", "replace")
    coef = re.search(r"^lr_param\.temp_comp_coefficient[ \t]+(\S+)", text, re.MULTILINE)
    assert coef is not None and cfg.axes[1].params.temp_comp_coefficient == float(coef.group(1))
    print(f"outcomes {outcomes}, stray temporary files {len(stray)}")
