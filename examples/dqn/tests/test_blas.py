"""OpenBLAS kernel choice: the package picks kernels from the CPU's flags."""

import os
import pathlib
import subprocess
import sys

from mll_dqn import blas

_AVX512 = {"avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl"}


def test_kernels_follow_the_instruction_sets():
    assert blas.kernels_for_flags(_AVX512 | {"avx2", "fma", "sse3"}) == "SkylakeX"
    assert blas.kernels_for_flags({"avx2", "fma", "avx512f"}) == "Haswell"
    assert blas.kernels_for_flags({"sse3", "avx"}) is None


def _kernels_in_a_fresh_process(extra_env):
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
    env.update(extra_env)
    code = ("import mll_dqn.agent, os; from mll_dqn import blas; "
            "print(os.environ.get('OPENBLAS_CORETYPE'), blas.loaded_openblas_kernels())")
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True,
                         cwd=pathlib.Path(__file__).parents[1],  # examples/dqn
                         capture_output=True, text=True).stdout.split()
    return out


def test_torch_uses_the_kernels_the_package_chose():
    chosen = blas.kernels_for_flags(blas._cpu_flags())
    requested, loaded = _kernels_in_a_fresh_process({})
    assert requested == str(chosen)
    if chosen is not None and loaded != "None":
        assert loaded.lower() == chosen.lower()


def test_a_users_choice_is_kept():
    requested, loaded = _kernels_in_a_fresh_process({"OPENBLAS_CORETYPE": "Haswell"})
    assert requested == "Haswell"
    if loaded != "None":
        assert loaded.lower() == "haswell"
