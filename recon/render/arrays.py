"""numpy buffers handed to drjit: one place that aligns them (kernel reuse)."""

from __future__ import annotations

import numpy as np

__all__ = ["aligned"]


def aligned(a, dtype) -> np.ndarray:
    """A flat copy of ``a`` whose buffer starts on a 64-byte boundary.

    drjit maps numpy memory into its arrays without copying and compiles separate kernels
    for aligned and unaligned inputs; numpy's buffers are aligned to 16 bytes only, so the
    same call could compile a new kernel variant whenever an allocation landed elsewhere.
    Every numpy array the renderer hands to drjit goes through here (torch's CPU buffers are
    64-byte aligned already).
    """
    a = np.ascontiguousarray(a, dtype=dtype).reshape(-1)
    buf = np.empty(a.size + 64 // a.itemsize, dtype=dtype)
    start = (-buf.ctypes.data % 64) // a.itemsize
    out = buf[start:start + a.size]
    out[...] = a
    return out
