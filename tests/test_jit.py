"""The compiled cycle is the Python code it is compiled from (geo_server/jit.py).

A law runs interpreted until its machine code is loaded (a server's first cycles), so the
two must give the same numbers: the same IEEE operations in the same order, no fused
multiply-add, no reassociation. The scenario of tests/support/jit_run.py (three machines:
motion with reversals and a dwell, a TEMPC ramp, a reload, the twin's events) runs here
compiled and in a subprocess interpreted (`NUMBA_DISABLE_JIT=1`), and every array the
cycle writes is compared bit for bit.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support import jit_run

from geo_server import jit

SCRIPT = Path(jit_run.__file__)


@pytest.mark.slow
def test_interpreted_laws_give_the_compiled_numbers(tmp_path: Path) -> None:
    assert jit.loaded()  # (conftest)
    compiled = jit_run.run(tmp_path / "compiled")
    out = tmp_path / "interpreted.npz"
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1"}
    subprocess.run([sys.executable, str(SCRIPT), str(out)], env=env, check=True, timeout=300)
    interpreted = np.load(out)
    assert sorted(interpreted.files) == sorted(compiled)
    for key, value in compiled.items():
        assert np.array_equal(interpreted[key], value, equal_nan=True), key
        # -0.0 and 0.0 are equal but not the same bytes on the wire
        assert interpreted[key].tobytes() == value.tobytes(), key


def test_a_law_is_its_plain_function() -> None:
    """What a compiled function is made from is the module's own function object."""
    from geo_server.kernel import tables

    assert isinstance(tables.interp, jit.Law)
    assert tables.interp.py_func.__module__ == "geo_server.kernel.tables"
    tab = np.array([0.0, 10.0, 1.0, 3.0])  # points 0, 10; values 1, 3
    assert tables.interp(tab, 0, 2, 5.0) == tables.interp.py_func(tab, 0, 2, 5.0) == 2.0
