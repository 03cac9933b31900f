"""The neighbours of an observation seen by closeness: a view for learned policies.

An observation gives each of a lander's two nearest neighbours as its offset (values 8-9 and
10-11, in half-world units) and an absent neighbour as (0, 0), the same values as a neighbour
about to collide. `neighbor_closeness` replaces each offset by the neighbour's direction times
exp(-distance / NEIGHBOR_REACH): near 1 when the neighbour is near, 0 when it is far or absent,
so the two cases are furthest apart. The DQN's `--neighbor-input closeness` and the PPO
recipes' `--neighbor-closeness` see the neighbours this way (docs/dqn.md, docs/training.md).
"""

from __future__ import annotations

import numpy as np

# World units (m) per observation unit of a neighbour's offset: x in W/2, y in H/2.
NEIGHBOR_SCALE = np.array([10.0, 20.0 / 3.0], np.float32)
# The distance (m) over which closeness falls by a factor e.
NEIGHBOR_REACH = 2.0


def neighbor_closeness(observation) -> np.ndarray:
    """Observations (..., 12) float32 with values 8-11 (the two neighbours' offsets) replaced by
    each neighbour's direction times exp(-distance / NEIGHBOR_REACH) (0 for an absent one), in
    world units; values 0-7 unchanged."""
    observation = np.asarray(observation, np.float32)
    leading = observation.shape[:-1]
    flat = observation.reshape(-1, observation.shape[-1])
    offsets = flat[:, 8:12].reshape(-1, 2, 2) * NEIGHBOR_SCALE
    distance = np.sqrt((offsets * offsets).sum(axis=2, keepdims=True))
    present = distance > 0
    closeness = np.where(
        present,
        np.exp(-distance / np.float32(NEIGHBOR_REACH)) / np.where(present, distance, np.float32(1)),
        np.float32(0),
    )
    seen = np.concatenate((flat[:, :8], (offsets * closeness).reshape(-1, 4)), axis=1)
    return seen.reshape(leading + (seen.shape[-1],))
