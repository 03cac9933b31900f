"""Single-file PPO in the CleanRL style on `mll.gym_vector_env`: every lander is one
sub-environment of a gymnasium.vector.VectorEnv and all of them share one policy (parameter
sharing). Its defaults are the recipe that lands on the paper's environment (--paper); on the
default environment its landers mostly hover (docs/training.md "PPO recipes").

    python examples/ppo_cleanrl.py --seed 1 --save ppo.pt --episodes-csv ppo_episodes.csv
    python examples/ppo_cleanrl.py --paper --seed 1 --save ppo_paper.pt --episodes-csv ppo_paper_episodes.csv
    python examples/ppo_cleanrl.py --evaluate ppo.pt --eval-episodes 100

--paper uses the environment of the paper's DQN experiment (docs/dqn.md). --episodes-csv writes
one row per environment episode with its score (the sum of its landers' returns) and the running
50-episode mean, like examples/dqn's episodes.csv. After training (or with --evaluate PATH) the
policy flies --eval-episodes episodes greedily and one JSON line gives its mean score and the
share of landers that landed, crashed, flew out or were cut off.

The env uses Gymnasium's NEXT_STEP autoreset; the observation returned on the step an episode
ends is its final observation, so a truncated episode is bootstrapped from it. Rows with
infos["idle"] (a lander waiting for the other landers of its env, or its env's reset step)
carry no transition: their actions were ignored, so they are left out of the loss and their
advantages never reach a real transition (a real episode always ends with done before them).
"""

from __future__ import annotations

import json
import time

import gymnasium
import numpy as np
import torch

import multi_lunar_lander as mll
import ppo_common
import trainer_common


def parse_args(argv=None):
    parser = ppo_common.add_arguments(trainer_common.parser(__doc__.split("\n\n")[0], "CleanRL's num_steps"))
    return parser.parse_args(argv)


def train(args) -> tuple[ppo_common.Agent, ppo_common.ObservationScale | None, list, ppo_common.EnvEpisodes]:
    """Runs PPO; returns the agent, its observation scaling (None without
    --normalize-observations), one (lander steps so far, lander episodes ended so far, mean
    return of the lander episodes ended in the iteration) per iteration, and the environment
    episodes' scores."""
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    base = mll.gym_vector_env(args.envs, address=args.address, **trainer_common.environment_options(args))
    landers = base.n_landers
    scores = ppo_common.EnvEpisodes(args.envs, landers)
    envs = base
    if args.neighbor_closeness:
        envs = gymnasium.wrappers.vector.TransformObservation(envs, mll.neighbor_closeness)
    if args.normalize_observations:
        envs = observation_normalizer = gymnasium.wrappers.vector.NormalizeObservation(envs)
    if args.clip_rewards:  # Before scaling: the paper's +700 / -400 become Gymnasium's +-100.
        envs = gymnasium.wrappers.vector.ClipReward(envs, -args.clip_rewards, args.clip_rewards)
    # Gymnasium's own wrapper scales the rewards the learner sees (landing +700, damage -300 in
    # the paper's setting); the scores come from the env's infos, unscaled.
    envs = gymnasium.wrappers.vector.NormalizeReward(envs, gamma=args.gamma)
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
                ended = infos["_episode_return"]
                returns.extend(infos["episode_return"][ended].tolist())
                env_steps = ((iteration - 1) * steps + step + 1) * args.envs
                scores.add(ended.reshape(-1, landers), infos["episode_return"].reshape(-1, landers), env_steps,
                           time.perf_counter() - started)

        advantages, targets = ppo_common.advantages(  # A truncated episode bootstraps from its final observation.
            agent, next_observations, rewards, values, terminated, done, args.gamma, args.gae_lambda,
            (valid, landers) if args.team_credit else None,
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
        mean50 = f", 50-episode mean score {scores.rows[-1][2]:.1f}" if scores.rows else ""
        print(
            f"iteration {iteration}/{iterations}: {done_steps} lander steps, {episodes} episodes, "
            f"mean return {mean:.1f}{mean50}, {done_steps / (time.perf_counter() - started):.0f} lander steps/s",
            flush=True,
        )
    envs.close()
    scale = None
    if args.normalize_observations:
        rms = observation_normalizer.obs_rms
        scale = ppo_common.ObservationScale(rms.mean, rms.var)
    return agent, scale, curve, scores


def main(argv=None):
    args = parse_args(argv)
    if args.evaluate:
        act, config = ppo_common.load(args.evaluate)
        options = config["options"]
    else:
        agent, scale, curve, scores = train(args)
        options = trainer_common.environment_options(args)
        trainer_common.write_csv(args.csv, ["lander_steps", "episodes", "mean_return"], curve)
        scores.write(args.episodes_csv)
        if args.save:
            ppo_common.save(args.save, agent, options, args, scale)
        act = ppo_common.greedy(agent, scale, args.neighbor_closeness)
    if args.eval_episodes > 0:
        result = ppo_common.evaluate_greedy(act, ppo_common.evaluation_options(args, options),
                                            args.eval_episodes, address=args.address, envs=args.envs, seed=args.seed)
        print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
