"""Stable-Baselines3 PPO on `mll.sb3_vec_env`: every lander is one SB3 environment and all of
them share one policy (parameter sharing), stepped with one batched call per server, no
SuperSuit needed.

    python examples/ppo_sb3.py --envs 16 --landers 3 --total-steps 2000000 --save ppo_mll.zip

Needs stable-baselines3 (`pip install 'multi_lunar_lander[sb3]'`; this repository's venv has
2.4.1, which runs on Debian's torch 1.13).
"""

from __future__ import annotations

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

import multi_lunar_lander as mll
import trainer_common


def parse_args(argv=None):
    parser = trainer_common.parser(__doc__.split("\n\n")[0], "SB3's n_steps")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--save", default=None, help="save the trained model to this .zip")
    return parser.parse_args(argv)


class Curve(BaseCallback):
    """Mean return of the episodes that ended in each rollout (from the env's "episode" infos)."""

    def __init__(self):
        super().__init__()
        self.rows, self._returns, self._episodes = [], [], 0

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            if "episode" in info:
                self._returns.append(info["episode"]["r"])
        return True

    def _on_rollout_end(self) -> None:
        self._episodes += len(self._returns)
        mean = float(np.mean(self._returns)) if self._returns else float("nan")
        self.rows.append((self.num_timesteps, self._episodes, mean))
        self._returns = []


def main(argv=None):
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    env = mll.sb3_vec_env(args.envs, address=args.address, n_landers=args.landers, max_cycles=args.max_cycles)
    model = PPO(
        "MlpPolicy", env, n_steps=args.num_steps, batch_size=args.batch_size, n_epochs=args.epochs,
        learning_rate=args.lr, ent_coef=0.01, seed=args.seed, device="cpu", verbose=1,
    )
    curve = Curve()
    model.learn(total_timesteps=args.total_steps, callback=curve)
    env.close()
    if args.save:
        model.save(args.save)
    trainer_common.write_csv(args.csv, ["lander_steps", "episodes", "mean_return"], curve.rows)
    return curve.rows


if __name__ == "__main__":
    main()
