"""keep_freed_memory: freed blocks of a gradient step's size are reused
without page faults."""

import pathlib
import subprocess
import sys

import pytest

# 200 times touches three fresh 512 KB blocks (512 x 256 float32 activations)
# and frees them, and prints the page faults it took. By default glibc hands
# the freed top of its heap back to the kernel each time (more than its trim
# threshold is free); with the thresholds raised the blocks are reused.
_FAULTS = """
import resource, sys
import numpy as np
from mll_dqn.heap import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
np.ones((512, 256), np.float32)
before = faults()
for _ in range(200):
    blocks = [np.ones((512, 256), np.float32) for _ in range(3)]
    del blocks
print(faults() - before)
"""


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", _FAULTS, mode], check=True,
                         cwd=pathlib.Path(__file__).parents[1],  # examples/dqn
                         capture_output=True, text=True)
    return int(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_freed_activation_sized_blocks_are_reused_without_page_faults():
    kept = _faults("keep")
    default = _faults("default")
    # A fresh 512 KB block is 128 pages; a reused one touches no new page.
    assert kept < 3 * 128
    assert default > 200 * 128
