"""A trained Q-network as a small file that numpy alone can fly.

The `.qnet` format (all little-endian), read also by mll_cli's trained pilot
(client_cpp/tools/trained_pilot.cc):

    bytes 0-3   magic "MLLQ"
    uint32      format version (2; version 1 files, which lack the next
                field, are read as inputs 0)
    uint32      inputs: how the network sees the observation's two
                neighbors [8:12]; 0 as they are (offsets), 1 by closeness
                (each neighbor's direction times exp(-distance / 2 world
                units), mll_dqn.agent.neighbor_closeness)
    uint32      L, the number of linear layers
    uint32[L+1] layer sizes, input first (12, 256, 64, 4 for the paper's net)
    then for each layer l: float32 weight[size[l+1]][size[l]] (row-major,
    output-major as torch.nn.Linear stores it), float32 bias[size[l+1]]

The network is ReLU between layers and linear at the output; the pilot flies
argmax Q. This module needs numpy only (no torch), so examples/play.py can
fly the shipped network anywhere the client runs.
"""

from __future__ import annotations

import dataclasses
import os
from typing import List, Sequence, Tuple

import numpy as np

from multi_lunar_lander.neighbors import (  # noqa: F401  (mll_dqn's names)
    NEIGHBOR_REACH, NEIGHBOR_SCALE, neighbor_closeness)

from mll_dqn.config import NEIGHBOR_INPUTS

MAGIC = b"MLLQ"
VERSION = 2
# Larger than any network worth shipping; bounds what a corrupt header asks.
MAX_LAYER_SIZE = 1 << 16
MAX_LAYERS = 16

# The network trained by `python -m mll_dqn train` (default preset) and
# shipped with the examples (docs/dqn.md: the trained pilot).
SHIPPED = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(
    __file__))), "trained.qnet")

Layers = List[Tuple[np.ndarray, np.ndarray]]


@dataclasses.dataclass
class QNet:
    """A .qnet file's network: its layers and how it sees the neighbors."""
    layers: Layers
    neighbor_input: str = "offset"


def save(path: str, layers: Sequence[Tuple[np.ndarray, np.ndarray]],
         neighbor_input: str = "offset") -> None:
    """Writes (weight [out, in], bias [out]) pairs, input layer first, of a
    network that sees the neighbors as `neighbor_input` says."""
    if neighbor_input not in NEIGHBOR_INPUTS:
        raise ValueError(f"neighbor_input = {neighbor_input!r}; allowed: "
                         f"{' or '.join(NEIGHBOR_INPUTS)}")
    sizes = [layers[0][0].shape[1]] + [w.shape[0] for w, _ in layers]
    for (w, b), n_in, n_out in zip(layers, sizes[:-1], sizes[1:]):
        if w.shape != (n_out, n_in) or b.shape != (n_out,):
            raise ValueError(f"layer shapes {w.shape}, {b.shape} do not chain "
                             f"from {n_in} inputs to {n_out} outputs")
    with open(path + ".tmp", "wb") as f:
        f.write(MAGIC)
        np.array([VERSION, NEIGHBOR_INPUTS.index(neighbor_input),
                  len(layers), *sizes], "<u4").tofile(f)
        for w, b in layers:
            np.asarray(w, "<f4").tofile(f)
            np.asarray(b, "<f4").tofile(f)
    os.replace(path + ".tmp", path)


def load(path: str) -> QNet:
    """Reads a .qnet file; ValueError names what is wrong with it."""
    data = open(path, "rb").read()
    if data[:4] != MAGIC:
        raise ValueError(f"{path}: not a .qnet file (magic {data[:4]!r}, "
                         f"expected {MAGIC!r})")
    version = int(np.frombuffer(data, "<u4", count=1, offset=4)[0])
    if version not in (1, VERSION):
        raise ValueError(f"{path}: version {version} is not supported; "
                         f"allowed: 1 or {VERSION}")
    offset = 8
    neighbor_input = 0
    if version >= 2:
        neighbor_input = int(np.frombuffer(data, "<u4", count=1, offset=8)[0])
        offset = 12
        if neighbor_input >= len(NEIGHBOR_INPUTS):
            raise ValueError(
                f"{path}: inputs {neighbor_input}; allowed: "
                + " or ".join(f"{code} ({name})"
                              for code, name in enumerate(NEIGHBOR_INPUTS)))
    n_layers = int(np.frombuffer(data, "<u4", count=1, offset=offset)[0])
    offset += 4
    if not 1 <= n_layers <= MAX_LAYERS:
        raise ValueError(f"{path}: {n_layers} layers; allowed: 1..{MAX_LAYERS}")
    sizes = [int(s) for s in
             np.frombuffer(data, "<u4", count=n_layers + 1, offset=offset)]
    if not all(1 <= s <= MAX_LAYER_SIZE for s in sizes):
        raise ValueError(f"{path}: layer sizes {sizes}; allowed: "
                         f"1..{MAX_LAYER_SIZE}")
    if NEIGHBOR_INPUTS[neighbor_input] != "offset" and sizes[0] != 12:
        raise ValueError(f"{path}: {sizes[0]} inputs; a network that sees "
                         "neighbors by closeness has 12")
    offset += 4 * (n_layers + 1)
    expected = offset + 4 * sum(o * i + o for i, o in zip(sizes, sizes[1:]))
    if len(data) != expected:
        raise ValueError(f"{path}: {len(data)} bytes; layer sizes {sizes} "
                         f"need {expected}")
    layers = []
    for n_in, n_out in zip(sizes[:-1], sizes[1:]):
        w = np.frombuffer(data, "<f4", n_out * n_in, offset)
        offset += 4 * n_out * n_in
        b = np.frombuffer(data, "<f4", n_out, offset)
        offset += 4 * n_out
        layers.append((w.reshape(n_out, n_in).astype(np.float32),
                       b.astype(np.float32)))
    return QNet(layers, NEIGHBOR_INPUTS[neighbor_input])


def q_values(net: QNet, obs: np.ndarray) -> np.ndarray:
    """Q-values [B, actions] of observations [B, inputs], in float32."""
    x = np.asarray(obs, np.float32)
    if net.neighbor_input == "closeness":
        x = neighbor_closeness(x)
    for index, (w, b) in enumerate(net.layers):
        x = x @ w.T + b
        if index + 1 < len(net.layers):
            x = np.maximum(x, 0.0)
    return x


class TrainedPilot:
    """Greedy actions of a .qnet network: pilot(obs [B, 12]) -> actions [B]."""

    def __init__(self, path: str = SHIPPED):
        self.net = load(path)
        self.layers = self.net.layers
        self.n_inputs = self.layers[0][0].shape[1]

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32).reshape(-1, self.n_inputs)
        return q_values(self.net, obs).argmax(axis=1)
