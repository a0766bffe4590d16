"""Compensation kernel: pure computation, no I/O (docs/design.md §1, §3, §6, §11).

`Kernel` is the Python face of the compiled cycle the machine runs (`kernel.step`, each
law compiled by numba through `geo_server.jit`, interpreted until its machine code has
loaded); its test oracle, the per-axis pure-Python statement of the same rules
(`ReferenceKernel`), lives with the tests (tests/support/reference.py). `COMP_ORDER`
gives the column of every compensation in the kernel's `[n, 7]` arrays; the temperature
law is `temperature.offset`.
"""

from geo_server.kernel.common import COMP_ORDER
from geo_server.kernel.kernel import Kernel

__all__ = ["COMP_ORDER", "Kernel"]
