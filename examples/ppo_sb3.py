"""Stable-Baselines3 PPO on `mll.sb3_vec_env`: every lander is one SB3 environment and all of
them share one policy (parameter sharing), stepped with one batched call per server. Its defaults
are the recipe that lands on the paper's environment (--paper; on the default environment its
landers mostly hover: docs/training.md "PPO recipes"); --supersuit builds the same
environments the way PettingZoo's SB3 tutorial does (SuperSuit's black_death_v3,
pettingzoo_env_to_vec_env_v1 and concat_vec_envs_v1 over `mll.parallel_env`; SuperSuit's SB3
wrapper drops SB3's environment seeds, so there only the policy is seeded).

    python examples/ppo_sb3.py --seed 1 --save ppo_sb3.zip --episodes-csv ppo_sb3_episodes.csv
    python examples/ppo_sb3.py --paper --seed 1 --save ppo_sb3_paper.zip
    python examples/ppo_sb3.py --evaluate ppo_sb3.zip --eval-episodes 100

Rewards are clipped to +-100 (--clip-rewards) and scaled, and observations normalised, by SB3's
VecNormalize (--neighbor-closeness: the policy sees the neighbours by mll.neighbor_closeness); the
scores come from the landers' own returns, unscaled. After training (or with
--evaluate PATH) the policy flies --eval-episodes episodes greedily and one JSON line gives its
mean score and the share of landers per outcome.

Needs stable-baselines3 (`pip install 'multi_lunar_lander[sb3]'`; this repository's venv has
2.4.1, which runs on Debian's torch 1.13) and, for --supersuit, supersuit.
"""

from __future__ import annotations

import json
import time

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.utils import set_random_seed
from stable_baselines3.common.vec_env import VecEnvWrapper, VecMonitor, VecNormalize

import multi_lunar_lander as mll
import ppo_common
import trainer_common


def parse_args(argv=None):
    parser = ppo_common.add_arguments(trainer_common.parser(__doc__.split("\n\n")[0], "SB3's n_steps"))
    parser.add_argument("--supersuit", action="store_true",
                        help="build the environments with SuperSuit over mll.parallel_env (PettingZoo's SB3 tutorial)")
    # SB3's update takes most of its time with minibatches of 64 (about 4.7 ms per minibatch step
    # on 2 cores): minibatches of 256 make it four times shorter, twice the learning rate makes up
    # for the fewer steps, and 9 million lander steps (3 million environment steps) fit in about
    # 20 minutes (docs/training.md "PPO recipes").
    parser.set_defaults(minibatch_size=256, lr=6e-4, total_steps=9_000_000)
    args = parser.parse_args(argv)
    if args.team_credit and args.supersuit:  # SuperSuit's rows of finished landers look like flying ones.
        parser.error("--team-credit needs sb3_vec_env's idle rows: it cannot be used with --supersuit")
    return args


def make_env(args, options: dict):
    """The landers as an SB3 VecEnv: row k is lander k % n_landers of environment k // n_landers."""
    if not args.supersuit:
        return mll.sb3_vec_env(args.envs, address=args.address, **options)
    import supersuit as ss

    parallel = mll.parallel_env(address=args.address, **options)
    # black_death_v3 keeps a done lander's row (zero observation, reward 0) until its environment
    # ends; VecMonitor reports the episodes SB3's logger and Scores read.
    markov = ss.pettingzoo_env_to_vec_env_v1(ss.black_death_v3(parallel))
    return VecMonitor(ss.concat_vec_envs_v1(markov, args.envs, num_cpus=0, base_class="stable_baselines3"))


class ClipRewards(VecEnvWrapper):
    """Each reward clipped to [-limit, limit] (before VecNormalize scales it); the landers'
    episode returns in the infos stay unclipped."""

    def __init__(self, venv, limit: float):
        super().__init__(venv)
        self.limit = limit

    def reset(self):
        return self.venv.reset()

    def step_wait(self):
        observations, rewards, dones, infos = self.venv.step_wait()
        return observations, np.clip(rewards, -self.limit, self.limit), dones, infos


class NeighborCloseness(VecEnvWrapper):
    """The observations, the final ones in infos["terminal_observation"] included, with the
    neighbours seen by closeness (mll.neighbor_closeness)."""

    def reset(self):
        return mll.neighbor_closeness(self.venv.reset())

    def step_wait(self):
        observations, rewards, dones, infos = self.venv.step_wait()
        for info in infos:
            if "terminal_observation" in info:
                info["terminal_observation"] = mll.neighbor_closeness(info["terminal_observation"])
        return mll.neighbor_closeness(observations), rewards, dones, infos


class RealTransitionsBuffer(RolloutBuffer):
    """SB3's rollout buffer, with minibatches of real transitions only. sb3_vec_env keeps a
    finished lander's row until its environment resets, and each of those steps (infos[k]["idle"])
    is a zero-reward episode end from the zero observation: on the paper's environment, where a
    crashed lander's environment flies on for up to 2,000 steps, over a third of the rows. They
    keep their place in each row's sequence (each is an episode end, so no advantage crosses
    them) and are left out of the minibatches, as ppo_cleanrl.py leaves them out of its loss. Rows
    whose infos carry no "idle" (the SuperSuit path) all count as real."""

    def __init__(self, *args, team_landers: int = 0, **kwargs):
        """team_landers: the landers per environment when every lander is credited with its
        team's return (ppo_common.team_credit); 0: each with its own rewards, as SB3 does."""
        self.team_landers = team_landers
        super().__init__(*args, **kwargs)

    def reset(self) -> None:
        super().reset()
        shape = (self.buffer_size, self.n_envs)
        self.real = np.ones(shape, dtype=bool)
        # Each step's rewards as the env gave them (SB3 adds gamma * V(final observation) to a cut
        # off episode's last reward before add()), and which rows ended their episode.
        self.step_rewards = np.zeros(shape, dtype=np.float32)
        self.ended = np.zeros(shape, dtype=bool)
        self.cut_off = np.zeros(shape, dtype=bool)

    def mark_step(self, rewards, dones, infos) -> None:
        """The step whose transitions add() stores next."""
        self.real[self.pos] = [not info.get("idle", False) for info in infos]
        if not self.team_landers:  # Only team credit reads the rest.
            return
        self.step_rewards[self.pos] = rewards
        self.ended[self.pos] = dones
        self.cut_off[self.pos] = [info.get("TimeLimit.truncated", False) for info in infos]

    def compute_returns_and_advantage(self, last_values: torch.Tensor, dones: np.ndarray) -> None:
        if not self.team_landers:
            return super().compute_returns_and_advantage(last_values, dones)
        # The value of each row's next observation: the next step's value where the lander flies
        # on, the bootstrap SB3 added to the reward where it was cut off.
        following = np.concatenate([self.values[1:], last_values.cpu().numpy().reshape(1, -1)])
        final = (self.rewards - self.step_rewards) / self.gamma
        next_values = np.where(self.ended, final, following)
        as_tensor = torch.from_numpy
        team_rewards, next_values = ppo_common.team_credit(
            as_tensor(self.step_rewards), as_tensor(self.real), as_tensor(next_values),
            as_tensor(self.real & (~self.ended | self.cut_off)), self.team_landers)
        deltas = team_rewards + self.gamma * next_values - as_tensor(self.values)
        self.advantages = ppo_common.discounted_sums(deltas, as_tensor(self.ended.astype(np.float32)),
                                                     self.gamma * self.gae_lambda).numpy()
        self.returns = self.advantages + self.values

    def get(self, batch_size=None):
        assert self.full
        indices = np.random.permutation(np.flatnonzero(self.real.swapaxes(0, 1).ravel()))
        if not self.generator_ready:  # As RolloutBuffer.get: env-major rows, as the indices.
            for name in ("observations", "actions", "values", "log_probs", "advantages", "returns"):
                self.__dict__[name] = self.swap_and_flatten(self.__dict__[name])
            self.generator_ready = True
        batch_size = batch_size or len(indices)
        for start in range(0, len(indices), batch_size):
            yield self._get_samples(indices[start:start + batch_size])


class MarkSteps(BaseCallback):
    """Tells the RealTransitionsBuffer each step's idle rows, rewards and episode ends."""

    def _on_step(self) -> bool:
        self.model.rollout_buffer.mark_step(self.locals["rewards"], self.locals["dones"], self.locals["infos"])
        return True


class Scores(BaseCallback):
    """The learning curve from the landers' episode ends (infos[k]["episode"]): one row per
    rollout (lander steps, lander episodes so far, mean return of the rollout's lander
    episodes) and the environment episodes' scores (ppo_common.EnvEpisodes)."""

    def __init__(self, envs: int, landers: int):
        super().__init__()
        self.rows, self._returns, self._episodes = [], [], 0
        self.landers = landers
        self.scores = ppo_common.EnvEpisodes(envs, landers)
        self._started = time.perf_counter()

    def _on_step(self) -> bool:
        infos = self.locals["infos"]
        ended = np.array(["episode" in info for info in infos])
        if ended.any():
            returns = np.array([info["episode"]["r"] if "episode" in info else 0.0 for info in infos])
            self._returns.extend(returns[ended].tolist())
            env_steps = self.num_timesteps // self.landers
            self.scores.add(ended.reshape(-1, self.landers), returns.reshape(-1, self.landers), env_steps,
                            time.perf_counter() - self._started)
        return True

    def _on_rollout_end(self) -> None:
        self._episodes += len(self._returns)
        mean = float(np.mean(self._returns)) if self._returns else float("nan")
        self.rows.append((self.num_timesteps, self._episodes, mean))
        mean50 = f", 50-episode mean score {self.scores.rows[-1][2]:.1f}" if self.scores.rows else ""
        print(f"{self.num_timesteps} lander steps, {self._episodes} episodes, mean return {mean:.1f}{mean50}",
              flush=True)
        self._returns = []


def greedy(model: PPO, scale: ppo_common.ObservationScale | None, closeness: bool):
    """The model's deterministic policy on observations [envs, landers, features], seen as in
    training (neighbours by closeness when `closeness`, then scaled by `scale`, as VecNormalize
    did)."""

    def act(observation: np.ndarray) -> np.ndarray:
        flat = observation.reshape(-1, observation.shape[-1])
        if closeness:
            flat = mll.neighbor_closeness(flat)
        if scale is not None:
            flat = scale(flat)
        return model.predict(flat, deterministic=True)[0].reshape(observation.shape[:-1])

    return act


def main(argv=None):
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.evaluate:
        model = PPO.load(args.evaluate, device="cpu")
        options = model.environment_options  # Saved with the model (below).
        statistics, closeness = model.observation_statistics, model.neighbor_closeness
        scale = None if statistics is None else ppo_common.ObservationScale(*statistics)
    else:
        options = trainer_common.environment_options(args)
        env = make_env(args, options)
        closeness = args.neighbor_closeness
        if closeness:
            env = NeighborCloseness(env)
        if args.clip_rewards:
            env = ClipRewards(env, args.clip_rewards)
        env = VecNormalize(env, norm_obs=args.normalize_observations, norm_reward=True, gamma=args.gamma)
        model = PPO(
            "MlpPolicy", env, n_steps=args.num_steps, batch_size=args.minibatch_size, n_epochs=args.epochs,
            learning_rate=args.lr, gamma=args.gamma, gae_lambda=args.gae_lambda, clip_range=args.clip,
            ent_coef=args.ent_coef, vf_coef=args.vf_coef, max_grad_norm=args.max_grad_norm,
            seed=None if args.supersuit else args.seed, device="cpu", verbose=0,
            rollout_buffer_class=RealTransitionsBuffer,
            rollout_buffer_kwargs=dict(team_landers=options["n_landers"] if args.team_credit else 0),
        )
        # Without a logger of its own, each learn() makes an empty SB3-<time> directory in /tmp.
        model.set_logger(Logger(folder=None, output_formats=[]))
        if args.supersuit:  # SuperSuit 3.11's SB3 wrapper cannot take SB3's env.seed(): seed the policy only.
            set_random_seed(args.seed)
        scores = Scores(args.envs, options["n_landers"])
        model.learn(total_timesteps=args.total_steps, callback=CallbackList([MarkSteps(), scores]))
        env.close()
        trainer_common.write_csv(args.csv, ["lander_steps", "episodes", "mean_return"], scores.rows)
        scores.scores.write(args.episodes_csv)
        scale = None
        if args.normalize_observations:
            scale = ppo_common.ObservationScale(env.obs_rms.mean, env.obs_rms.var, clip=env.clip_obs)
        if args.save:
            # What evaluation needs, saved in the .zip beside the policy.
            model.environment_options = options
            # Plain values (mean, var, clip), so that loading the .zip needs no module of ours.
            model.observation_statistics = None if scale is None else (
                scale.mean.tolist(), scale.var.tolist(), scale.clip)
            model.neighbor_closeness = closeness
            # Without this example's rollout buffer: PPO.load gives SB3's own, and needs no module of ours.
            model.save(args.save, include=["environment_options", "observation_statistics", "neighbor_closeness"],
                       exclude=["rollout_buffer_class", "rollout_buffer_kwargs"])
    if args.eval_episodes > 0:
        act = greedy(model, scale, closeness)
        result = ppo_common.evaluate_greedy(act, ppo_common.evaluation_options(args, options),
                                            args.eval_episodes, address=args.address, envs=args.envs, seed=args.seed)
        print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
