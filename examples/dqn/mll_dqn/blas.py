"""Pick OpenBLAS's kernels from the CPU's instruction sets.

Debian's OpenBLAS (0.3.21, DYNAMIC_ARCH) chooses its kernels by CPU model
number. A model it does not know, such as this machine's virtualised Xeon
(family 6, model 207), falls back to the "Prescott" kernels (SSE3), which
makes a batch-512 gradient step of the 12-256-64-4 network take 3.9 ms
instead of 1.9 ms (docs/dqn.md). OPENBLAS_CORETYPE overrides the choice; it
is read once, when the library loads, so this runs before torch is imported.
A value the user set is kept.
"""

from __future__ import annotations

import os
from typing import Iterable, Optional

# Kernel families of OpenBLAS and the instruction sets they need, best first.
_KERNELS_BY_FLAGS = (
    ("SkylakeX", {"avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl"}),
    ("Haswell", {"avx2", "fma"}),
)


def kernels_for_flags(flags: Iterable[str]) -> Optional[str]:
    """The best OpenBLAS core type whose instruction sets are all in flags."""
    flags = set(flags)
    for core_type, needed in _KERNELS_BY_FLAGS:
        if needed <= flags:
            return core_type
    return None


def _cpu_flags(cpuinfo_path: str = "/proc/cpuinfo") -> set:
    try:
        with open(cpuinfo_path) as cpuinfo:
            for line in cpuinfo:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def choose_openblas_kernels() -> Optional[str]:
    """Sets OPENBLAS_CORETYPE unless already set; returns the value in force."""
    if "OPENBLAS_CORETYPE" not in os.environ:
        core_type = kernels_for_flags(_cpu_flags())
        if core_type is not None:
            os.environ["OPENBLAS_CORETYPE"] = core_type
    return os.environ.get("OPENBLAS_CORETYPE")


def loaded_openblas_kernels() -> Optional[str]:
    """The kernels the OpenBLAS loaded in this process reports using (after
    torch is imported), or None if no OpenBLAS with that query is loaded."""
    import ctypes

    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split()[-1] for line in maps
                            if "openblas" in line})
    except OSError:
        return None
    for path in paths:
        try:
            corename = ctypes.CDLL(path).openblas_get_corename
        except (OSError, AttributeError):
            continue  # e.g. numpy's bundled OpenBLAS, whose symbols are renamed
        corename.restype = ctypes.c_char_p
        return corename().decode()
    return None
