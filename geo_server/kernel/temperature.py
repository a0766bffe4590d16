"""Temperature compensation TEMPC (000 §3; docs/design.md §6.2): its law and its objects.

The law, `offset_0 + coefficient·1e-6·(s − position_0)` (000 §3.1 p.15), is stated here once
(`offset`) and used by the kernel's cycle (compiled, `kernel.step`), by the measurement tool
(`twin/measure.py`) and by the PLC client's expected value (`geo_clients/plc_tempcomp.py`) as
plain Python: the coefficient is scaled first (`slope`), then multiplied by the position
relative to position_0, then offset_0 is added. This module imports no compiler, so a
client that only needs the law does not load one.

The writable TEMPC parameters (000 §3.2.3 objects 0x43–0x45) are bound to the kernel's rows
from the dictionary the machine was given (`bindings`), not from a module-level load of
the default one.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

if TYPE_CHECKING:
    from geo_server.dictionary import Dictionary

#: coefficient [µm/m] → slope [units per unit of position]
SCALE = 1e-6


def slope(coefficient: float) -> float:
    """The line's slope from the coefficient in µm/m (000 p.15)."""
    return coefficient * SCALE


def offset(offset_0: float, coefficient: float, position_0: float, s: float) -> float:
    """Δs at command position `s` (000 §3.1 p.15), unrounded, in the units of offset_0.
    Plain Python that the kernel compiles (`kernel.step`): `slope` written out, as the
    compiled code calls no Python function."""
    return offset_0 + coefficient * SCALE * (s - position_0)


#: The law's parameters, in the order of the kernel's rows (coefficient, offset_0,
#: position_0; 000 §3.2.3 objects 0x43–0x45): the `AxisParams` attributes (axis-list
#: entries P-AXIS-00274, -00273, -00272) they start from.
ATTRS = ("temp_comp_coefficient", "temp_comp_offset_0", "temp_comp_position_0")


class Bindings(NamedTuple):
    """The TEMPC parameter objects of a dictionary, in the law's order (`ATTRS`): object
    names and field names of the object key ("" where the dictionary has no such
    object: the parameter then keeps its axis-list value)."""

    names: tuple[str, ...]
    fields: tuple[str, ...]
    attrs: tuple[str, ...] = ATTRS


def bindings(dictionary: Dictionary) -> Bindings:
    """The TEMPC parameter objects of `dictionary`, found by the axis-list entry they
    stand for (so the kernel's rows do not depend on the dictionary's order or names)."""
    by_attr = {o.param_attr: o for o in dictionary.tempc_parameters()}
    objs = [by_attr.get(a) for a in ATTRS]
    return Bindings(
        tuple(o.name if o else "" for o in objs),
        tuple(o.key_field if o else "" for o in objs),
    )


_DEFAULT: Bindings | None = None


def default_bindings() -> Bindings:
    """`bindings` of the default dictionary, loaded at the first call (a kernel made
    without a dictionary, as in the tests)."""
    global _DEFAULT
    if _DEFAULT is None:
        from geo_server.dictionary import load_dictionary

        _DEFAULT = bindings(load_dictionary())
    return _DEFAULT
