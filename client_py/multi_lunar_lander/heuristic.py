"""Gymnasium's LunarLander heuristic pilot (docs/environment.md, "Actions") in numpy,
vectorised over any leading dimensions of the observation."""

from __future__ import annotations

import numpy as np


def heuristic(observation, continuous: bool = False):
    """The pilot's action for observation(s) of shape (..., >= 8).

    Returns int64 actions of shape (...) (Discrete(4)), or with continuous=True float32 actions
    of shape (..., 2) ([main, lateral] in [-1, 1]). A single observation gives an int / a (2,)
    array.
    """
    # float64 throughout, as Gymnasium's pilot computes on numpy scalars; it also makes one
    # observation and a batch give bit-identical actions.
    s = np.asarray(observation, dtype=np.float64)
    if s.shape[-1:] and s.shape[-1] < 8:
        raise ValueError(f"observation has shape {s.shape}; the last dimension needs >= 8 values")
    angle_target = np.clip(s[..., 0] * 0.5 + s[..., 2] * 1.0, -0.4, 0.4)
    hover_target = 0.55 * np.abs(s[..., 0])
    angle_todo = (angle_target - s[..., 4]) * 0.5 - s[..., 5] * 1.0
    hover_todo = (hover_target - s[..., 1]) * 0.5 - s[..., 3] * 0.5
    legs = (s[..., 6] != 0) | (s[..., 7] != 0)
    angle_todo = np.where(legs, 0.0, angle_todo)
    hover_todo = np.where(legs, -s[..., 3] * 0.5, hover_todo)
    if continuous:
        action = np.stack([hover_todo * 20 - 1, -angle_todo * 20], axis=-1)
        return np.clip(action, -1, 1).astype(np.float32)
    action = np.select(
        [
            (hover_todo > np.abs(angle_todo)) & (hover_todo > 0.05),
            angle_todo < -0.05,
            angle_todo > 0.05,
        ],
        [2, 3, 1],
        default=0,
    ).astype(np.int64)
    return int(action) if action.ndim == 0 else action
