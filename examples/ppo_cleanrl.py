"""Single-file PPO in the CleanRL style on `mll.gym_vector_env`: every lander is one
sub-environment of a gymnasium.vector.VectorEnv and all of them share one policy (parameter
sharing).

    python examples/ppo_cleanrl.py --envs 16 --landers 3 --total-steps 2000000 --csv ppo.csv
    python examples/ppo_cleanrl.py --paper --total-steps 2500000 --episodes-csv ppo_paper.csv

--paper uses the environment of the paper's DQN experiment (docs/dqn.md) and writes, with
--episodes-csv, one row per environment episode with its score (the sum of its landers'
returns) and the running 50-episode mean, like examples/dqn's episodes.csv.

The env uses Gymnasium's NEXT_STEP autoreset; the observation returned on the step an episode
ends is its final observation, so a truncated episode is bootstrapped from it. Rows with
infos["idle"] (a lander waiting for the other landers of its env, or its env's reset step)
carry no transition: their actions were ignored, so they are left out of the loss and their
advantages never reach a real transition (a real episode always ends with done before them).
"""

from __future__ import annotations

import time

import gymnasium
import numpy as np
import torch

import multi_lunar_lander as mll
import ppo_common
import trainer_common


def parse_args(argv=None):
    parser = ppo_common.add_arguments(trainer_common.parser(__doc__.split("\n\n")[0], "CleanRL's num_steps"))
    parser.add_argument("--paper", action="store_true", help="the paper's environment options (docs/dqn.md)")
    parser.add_argument("--episodes-csv", default=None, help="write one row per environment episode: its score")
    return parser.parse_args(argv)


# The environment of the paper's DQN experiment (docs/dqn.md).
PAPER_OPTIONS = dict(
    n_landers=3, max_cycles=2000, damage_reward=-300.0, successful_reward=700.0, terminate_reward=-100.0,
    shared_reward=False, terminate_on_damage=False, remove_on_damage=True,
)


class EnvScores:
    """Environment episodes' scores (the sum of their landers' returns), from the per-lander
    episode ends: an env's episode is complete once each of its landers has ended."""

    def __init__(self, envs: int, landers: int):
        self.shape = (envs, landers)
        self.sums = np.zeros(envs)
        self.ended = np.zeros(envs, dtype=int)
        self.scores: list[float] = []

    def add(self, infos) -> None:
        if "_episode_return" not in infos:
            return
        mask = infos["_episode_return"].reshape(self.shape)
        self.sums += np.where(mask, infos["episode_return"].reshape(self.shape), 0.0).sum(axis=1)
        self.ended += mask.sum(axis=1)
        complete = self.ended == self.shape[1]
        self.scores.extend(self.sums[complete].tolist())
        self.sums[complete], self.ended[complete] = 0.0, 0


def train(args) -> tuple[list[tuple[int, int, float]], list[tuple[int, float, float, int, float]]]:
    """Runs PPO; returns (lander steps so far, lander episodes ended so far, mean return of the
    lander episodes ended in the iteration) per iteration, and (env episode, score, 50-episode
    mean, env steps so far, wall seconds) per environment episode."""
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    options = PAPER_OPTIONS if args.paper else dict(n_landers=args.landers, max_cycles=args.max_cycles)
    base = mll.gym_vector_env(args.envs, address=args.address, **options)
    scores, episode_rows = EnvScores(args.envs, base.n_landers), []
    # Gymnasium's own wrapper scales the rewards the learner sees (landing +700, damage -300 in
    # the paper's setting); the scores come from the env's infos, unscaled.
    envs = gymnasium.wrappers.vector.NormalizeReward(base, gamma=args.gamma)
    n, steps = envs.num_envs, args.num_steps
    agent = ppo_common.Agent(envs.single_observation_space.shape[0], envs.single_action_space.n)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.lr, eps=1e-5)

    shape = (steps, n)
    observations = torch.zeros(shape + envs.single_observation_space.shape)
    next_observations = torch.zeros_like(observations)
    actions = torch.zeros(shape, dtype=torch.long)
    logprobs, rewards, values = torch.zeros(shape), torch.zeros(shape), torch.zeros(shape)
    terminated, done, valid = torch.zeros(shape), torch.zeros(shape), torch.zeros(shape, dtype=torch.bool)

    observation = torch.from_numpy(envs.reset(seed=args.seed)[0])
    curve, episodes, started = [], 0, time.perf_counter()
    iterations = max(1, args.total_steps // (steps * n))
    for iteration in range(1, iterations + 1):
        returns = []
        for step in range(steps):
            observations[step] = observation
            with torch.no_grad():
                action, logprob, _, value = agent.act(observation)
            actions[step], logprobs[step], values[step] = action, logprob, value
            observation_np, reward, term, trunc, infos = envs.step(action.numpy())
            observation = torch.from_numpy(observation_np)
            next_observations[step] = observation  # The final observation where an episode ended.
            rewards[step] = torch.from_numpy(reward)
            terminated[step] = torch.from_numpy(term.astype(np.float32))
            done[step] = torch.from_numpy((term | trunc).astype(np.float32))
            valid[step] = torch.from_numpy(~infos["idle"])
            if "_episode_return" in infos:
                returns.extend(infos["episode_return"][infos["_episode_return"]].tolist())
            known = len(scores.scores)
            scores.add(infos)
            env_steps = ((iteration - 1) * steps + step + 1) * args.envs
            for index in range(known, len(scores.scores)):
                mean50 = float(np.mean(scores.scores[max(0, index - 49) : index + 1]))
                row = (index + 1, scores.scores[index], mean50, env_steps, time.perf_counter() - started)
                episode_rows.append(row)

        advantages, targets = ppo_common.advantages(  # A truncated episode bootstraps from its final observation.
            agent, next_observations, rewards, values, terminated, done, args.gamma, args.gae_lambda
        )
        rows = valid.flatten().nonzero().squeeze(-1)  # Real transitions only.
        batch = tuple(
            t.reshape((-1,) + t.shape[2:])[rows] for t in (observations, actions, logprobs, advantages, targets)
        )
        ppo_common.update(agent, optimizer, batch, args)

        episodes += len(returns)
        mean = float(np.mean(returns)) if returns else float("nan")
        done_steps = iteration * steps * n
        curve.append((done_steps, episodes, mean))
        print(
            f"iteration {iteration}/{iterations}: {done_steps} lander steps, {episodes} episodes, "
            f"mean return {mean:.1f}, {done_steps / (time.perf_counter() - started):.0f} lander steps/s",
            flush=True,
        )
    envs.close()
    return curve, episode_rows


def main(argv=None):
    args = parse_args(argv)
    curve, episode_rows = train(args)
    trainer_common.write_csv(args.csv, ["lander_steps", "episodes", "mean_return"], curve)
    trainer_common.write_csv(
        args.episodes_csv,
        ["episode", "score", "mean50", "env_steps", "wall_s"],
        ((e, f"{s:.3f}", f"{m:.3f}", n, f"{w:.3f}") for e, s, m, n, w in episode_rows),
    )


if __name__ == "__main__":
    main()
