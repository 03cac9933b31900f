"""DQN with parameter sharing on the Multi Lunar Lander server.

Reproduces the paper's experiment (docs/dqn.md): one
Q-network shared by every lander, trained from one replay buffer, with the
paper's algorithm available as preset `paper` and improvements as options.
Run `python -m mll_dqn --help` from examples/dqn.
"""

from mll_dqn.blas import choose_openblas_kernels

# Before any module of the package imports torch (and with it OpenBLAS).
choose_openblas_kernels()
