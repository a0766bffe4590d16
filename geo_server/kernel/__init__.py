"""Compensation kernel: pure computation, no I/O (docs/design.md §1, §3, §6, §11).

`Kernel` is the fast numpy implementation used by the machine; its test oracle, the
per-axis pure-Python statement of the same rules (`ReferenceKernel`), lives with the tests
(tests/support/reference.py). `COMP_ORDER` gives the column of every compensation in the
kernel's `[n, 7]` arrays; the temperature law is `temperature.offset`.
"""

from geo_server.kernel.common import COMP_ORDER
from geo_server.kernel.kernel import Kernel

__all__ = ["COMP_ORDER", "Kernel"]
