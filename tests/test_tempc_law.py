"""The temperature compensation law exists once (issue 33; docs/design.md §13.3): the
kernel's target, the PLC client's expected value and the measurement tool's active line
all come from `geo_server.kernel.temperature`; and a machine binds the TEMPC objects of
the dictionary it was given, not those of the default one."""

from __future__ import annotations

import dataclasses

import numpy as np
from geo_clients import plc_tempcomp

from geo_server.dictionary import Dictionary, load_dictionary
from geo_server.kernel import step, temperature
from geo_server.kernel.common import TEMP
from geo_server.listfile.loader import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import default_startup_list


def _homed_machine(dictionary: Dictionary | None = None) -> Machine:
    m = Machine(load_machine(default_startup_list()), dictionary=dictionary, homed=True)
    m.step(60)  # the temperature compensation ramps in over its sin² cycles
    return m


def test_kernel_target_is_the_law() -> None:
    m = _homed_machine()
    m.apply_write("TEMPC::coefficient", m.axes[0], 37.5)
    m.apply_write("TEMPC::offset_0", m.axes[0], -120)
    m.apply_write("SIM::target_position", m.axes[0], 123456.0)
    m.step(3000)
    coef, off0, pos0 = (float(r[0]) for r in m.kernel.tempc_params)
    s = float(m.motion.pos[0])
    assert m.kernel.effective[0, TEMP]
    expected = temperature.offset(off0, coef, pos0, s)
    assert m.kernel.target[0, TEMP] == expected  # bit for bit
    params = plc_tempcomp.Parameters(20.0, int(pos0), int(off0), coef)
    assert plc_tempcomp.compensation(params, s) == expected


def test_compiled_law_is_the_scalar_law() -> None:
    """The kernel's cycle runs `temperature.offset` compiled (geo_server.jit): the same
    IEEE operations in the same order (no fused multiply-add, no reassociation), so the
    same numbers as the plain Python the PLC client and the measurement tool call."""
    rng = np.random.default_rng(3)
    args = [rng.uniform(-1e5, 1e5, 200) for _ in range(4)]
    args[1][:50] = rng.uniform(-1e4, 1e4, 50).round(1)  # coefficients as lists give them
    for v in zip(*args, strict=True):
        assert step._offset(*v) == temperature.offset(*v)


def _renamed_dictionary() -> Dictionary:
    """The default objects with the TEMPC parameters renamed and in reverse order."""
    objs = load_dictionary().objects
    rename = {
        "TEMPC::coefficient": "TEMPC::pitch",
        "TEMPC::offset_0": "TEMPC::start_offset",
        "TEMPC::position_0": "TEMPC::start_position",
    }
    renamed = [dataclasses.replace(o, name=rename[o.name]) for o in objs if o.name in rename]
    others = [o for o in objs if o.name not in rename]
    return Dictionary(others + renamed[::-1])


def test_an_injected_dictionary_binds_its_own_tempc_objects() -> None:
    m = _homed_machine(_renamed_dictionary())
    assert m.tempc.names == ("TEMPC::pitch", "TEMPC::start_offset", "TEMPC::start_position")
    axis = m.axes[1]
    m.apply_write("TEMPC::pitch", axis, 12.0)
    m.apply_write("TEMPC::start_offset", axis, 250)
    m.step(1)
    snap, d = m.snapshot, m.dictionary
    assert snap.value(d.by_name("TEMPC::pitch"), axis) == 12.0
    assert snap.value(d.by_name("TEMPC::start_offset"), axis) == 250
    coef, off0, _ = (float(r[1]) for r in m.kernel.tempc_params)
    assert (coef, off0) == (12.0, 250.0)
