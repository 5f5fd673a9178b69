"""Denormal numbers flushed to zero during the update: the CPU's slow path avoided, results unchanged.

ReLU units that stop receiving gradient leave Adam's moment estimates decaying geometrically towards zero, through
the float32 denormal range (below 1.2e-38), where x86 CPUs compute each operation in microcode, tens of times
slower. A few percent of such entries make every optimizer step slower (docs/notes/2026-12-02-denormals.md).
Flushed to zero, they take the value they were decaying to, sooner.

The setting (``torch.set_flush_denormal``: the CPU's flush-to-zero and denormals-are-zero flags, float32 and
float64 alike) belongs to the calling thread. torch's worker threads keep their own, so it is applied only where
torch computes in the calling thread: with one torch thread (``torch.set_num_threads(1)``, rl-zoo3's
``--num-threads 1``, the setting the benchmarks use). With more threads the update runs with IEEE arithmetic.
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
    """Within the context, denormals are flushed to zero (where the CPU can, and torch runs in this one thread: see
    the module); the thread's setting of before is restored after, also on an exception. ``enabled=False``, more than
    one torch thread, or a thread that flushes already: nothing changes."""
    if not enabled or th.get_num_threads() != 1 or denormals_flushed() or not th.set_flush_denormal(True):
        yield
        return
    try:
        yield
    finally:
        th.set_flush_denormal(False)
