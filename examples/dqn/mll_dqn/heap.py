"""Keep freed memory in the C heap for reuse instead of returning it to the
kernel.

A gradient step of the 12-256-64-4 network at batch 512 allocates and frees
tensors of 512 x 256 floats (512 KB) several times. glibc's malloc serves
blocks that large with a fresh mmap (and frees them with munmap) until its
dynamic threshold has grown, and returns the top of the heap to the kernel
once more than its trim threshold is free; each returned block costs a page
fault per 4 KB page when it is next touched. On the 2-vCPU VM of
docs/dqn.md that was about 300 page faults per gradient step, a fifth of
the step's time. Raising both thresholds keeps the blocks in the heap: the
process keeps the memory of its largest step (a few MB) instead.
"""

from __future__ import annotations

import ctypes
import ctypes.util

# mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
# glibc's upper limit of M_MMAP_THRESHOLD on 64-bit systems: larger blocks
# (the replay buffer's arrays) are still mapped on their own.
MMAP_THRESHOLD_BYTES = 32 << 20
TRIM_THRESHOLD_BYTES = 1 << 30


def keep_freed_memory() -> bool:
    """Sets glibc's mmap and trim thresholds; False where the C library has
    no mallopt (not glibc), which changes nothing else."""
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
                and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
