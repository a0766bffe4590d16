"""Compensation kernel: pure computation, no I/O (docs/design.md §1, §3, §6, §11).

`Kernel` is the fast numpy implementation used by the machine; `ReferenceKernel` is the
per-axis pure-Python statement of the same rules, used as the test oracle. Both share
the interface documented on `Kernel`; `COMP_ORDER` gives the column of every
compensation in their `[n, 7]` arrays.
"""

from geo_server.kernel.common import COMP_ORDER
from geo_server.kernel.kernel import Kernel
from geo_server.kernel.reference import ReferenceKernel

__all__ = ["COMP_ORDER", "Kernel", "ReferenceKernel"]
