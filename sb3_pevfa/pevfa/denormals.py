"""Float32 denormal numbers flushed to zero during the update: the CPU's slow path avoided, results unchanged.

ReLU units that stop receiving gradient leave Adam's moment estimates decaying geometrically towards zero, through
the denormal range (below 1.2e-38), where x86 CPUs compute each operation in microcode, tens of times slower.
A few percent of such entries make every optimizer step several times slower (docs/benchmarks.md, "Denormal
numbers"). Flushed to zero, they take the value they were decaying to, about 1e-38 sooner.
"""

from collections.abc import Iterator
from contextlib import contextmanager

import torch as th

_SMALLEST_NORMAL = float(th.finfo(th.float32).tiny)


def denormals_flushed() -> bool:
    """Whether this thread flushes float32 denormals to zero (torch has a setter, ``set_flush_denormal``, only)."""
    return th.tensor([_SMALLEST_NORMAL]).div_(2.0).item() == 0.0


@contextmanager
def flush_denormals(enabled: bool = True) -> Iterator[None]:
    """Within the context, this thread flushes float32 denormals to zero (where the CPU can: x86 with SSE3); the
    setting of before is restored after. ``enabled=False``: nothing changes."""
    if not enabled or denormals_flushed() or not th.set_flush_denormal(True):
        yield
        return
    try:
        yield
    finally:
        th.set_flush_denormal(False)
