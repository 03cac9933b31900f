"""Single-file PPO on `mll.vector_env`'s async API (EnvPool's async_reset / recv / send, in the
style of CleanRL's EnvPool async PPO): every lander of every environment is one row of one
shared policy (parameter sharing), and the policy acts on K = --batch-size environments at a
time while the servers step the others.

    python examples/async_ppo.py --envs 64 --batch-size 16 --address host1:50051,host2:50051 \\
        --total-steps 2000000 --save async_ppo.pt
    python examples/async_ppo.py --evaluate async_ppo.pt --eval-episodes 20

The actor loop: each recv() returns the results of K environments (infos["env_id"]); they close
the transitions those environments were sent, the policy acts on their new observations and
send() sends those actions, which the servers step while the next recv() waits for the next K.
The E / K batches are pipelined on each server's stream, so with servers on another machine
the round trips overlap each other and the policy's forward passes. A rollout is --num-steps
(T) steps of every environment, stored per environment (an environment's steps are contiguous
in time whatever order recv returns them in), so GAE runs over each lander's own sequence; the
learner updates between rollouts (ppo_common.update, the same clipped PPO as ppo_cleanrl.py).
--batch-size must divide --envs: the environments then travel in fixed groups of K and a
rollout ends with none in flight. Rows whose `active` is False (a lander already done, or an
environment's auto-reset step) carry no transition and are left out of the loss.

Prints one JSON line per update (environment and lander steps, steps per second, the mean
return of the lander episodes that ended in it, the losses); --save writes the policy
(state_dict and config) and --evaluate PATH reloads one and runs it greedily.
"""

from __future__ import annotations

import json
import time

import numpy as np
import torch
from gymnasium.wrappers.utils import RunningMeanStd

import multi_lunar_lander as mll
import ppo_common
import trainer_common


def parse_args(argv=None):
    parser = ppo_common.add_arguments(
        trainer_common.parser(__doc__.split("\n\n")[0], "T: steps of each environment per rollout")
    )
    parser.add_argument("--batch-size", type=int, default=None,
                        help="environments per recv (K); must divide --envs; default about envs/4")
    args = parser.parse_args(argv)
    if args.batch_size is None:  # The largest divisor of --envs up to envs / 4.
        args.batch_size = max(k for k in range(1, max(1, args.envs // 4) + 1) if args.envs % k == 0)
    if not 1 <= args.batch_size <= args.envs or args.envs % args.batch_size:
        parser.error(f"--batch-size {args.batch_size} must divide --envs {args.envs}")
    return args


class RewardScale:
    """Gymnasium's NormalizeReward, per lander row: rewards divided by the running standard
    deviation of the discounted returns (statistics of the rows that carry a transition)."""

    def __init__(self, shape: tuple[int, int], gamma: float):
        self.returns, self.gamma, self.rms = np.zeros(shape), gamma, RunningMeanStd(shape=())

    def __call__(self, ids, reward, terminated, active):
        self.returns[ids] = self.returns[ids] * self.gamma * (1 - terminated) + reward
        if active.any():
            self.rms.update(self.returns[ids][active])
        return reward / np.sqrt(self.rms.var + 1e-8)


def train(args) -> tuple[ppo_common.Agent, ppo_common.ObservationScale | None]:
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    steps, count, size = args.num_steps, args.envs, args.batch_size
    options = trainer_common.environment_options(args)
    envs = mll.vector_env(count, address=args.address, batch_size=size, **options)
    landers, features = envs.n_landers, envs.single_observation_space.shape[0]
    agent = ppo_common.Agent(features, envs.single_action_space.n)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.lr, eps=1e-5)
    scale = RewardScale((count, landers), args.gamma)
    observations_seen = RunningMeanStd(shape=(features,)) if args.normalize_observations else None

    # The rollout, per environment: [step of that environment, environment, lander].
    shape = (steps, count, landers)
    observations = torch.zeros(shape + (features,))
    next_observations = torch.zeros_like(observations)
    actions = torch.zeros(shape, dtype=torch.long)
    logprobs, rewards, values = torch.zeros(shape), torch.zeros(shape), torch.zeros(shape)
    terminated, done, valid = torch.zeros(shape), torch.zeros(shape), torch.zeros(shape, dtype=torch.bool)
    step = np.zeros(count, dtype=np.int64)  # Each environment's next step in this rollout.
    sent = np.zeros(count, dtype=bool)  # An action of ours is in flight (else: async_reset's result).
    in_flight = np.zeros(count, dtype=bool)
    latest = np.zeros((count, landers, features), np.float32)  # Observations to act on next rollout.

    def act_and_send(ids, observation):
        at = (torch.from_numpy(step[ids]), torch.from_numpy(ids))
        observation = torch.from_numpy(observation)
        with torch.no_grad():
            action, logprob, _, value = agent.act(observation)
        observations[at], actions[at], logprobs[at], values[at] = observation, action, logprob, value
        envs.send(action.numpy(), ids)
        sent[ids] = in_flight[ids] = True

    updates = max(1, args.total_steps // (steps * count * landers))
    transitions, env_steps, started = 0, 0, time.perf_counter()
    scores = ppo_common.EnvEpisodes(count, landers)
    envs.async_reset(seed=args.seed)
    in_flight[:] = True
    curve = []
    for update in range(1, updates + 1):
        step[:] = 0
        if not in_flight.any():  # Every rollout but the first starts from the held observations.
            for ids in np.arange(count).reshape(-1, size):
                act_and_send(ids, latest[ids])
        returns = []
        while in_flight.any():
            observation, reward, term, trunc, active, infos = envs.recv()
            if args.neighbor_closeness:
                observation = mll.neighbor_closeness(observation)
            if observations_seen is not None:  # Gymnasium's NormalizeObservation, per recv.
                observations_seen.update(observation.reshape(-1, features))
                observation = ppo_common.ObservationScale(observations_seen.mean, observations_seen.var)(observation)
            if args.clip_rewards:
                reward = np.clip(reward, -args.clip_rewards, args.clip_rewards)
            ids = infos["env_id"]
            in_flight[ids] = False
            closes = sent[ids]  # These rows end a transition (else they are async_reset's).
            if closes.any():
                rows, at = ids[closes], (torch.from_numpy(step[ids[closes]]), torch.from_numpy(ids[closes]))
                scaled = scale(rows, reward[closes], term[closes], active[closes])
                rewards[at] = torch.from_numpy(scaled.astype(np.float32))
                next_observations[at] = torch.from_numpy(observation[closes])  # Final ones at episode ends.
                terminated[at] = torch.from_numpy(term[closes].astype(np.float32))
                done[at] = torch.from_numpy((term | trunc)[closes].astype(np.float32))
                valid[at] = torch.from_numpy(active[closes])
                step[rows] += 1
                sent[rows] = False
            ended = term | trunc
            returns.extend(infos["episode_return"][ended].tolist())
            env_steps += int(closes.sum())
            scores.add(ended, infos["episode_return"], env_steps, time.perf_counter() - started, envs=ids)
            more = step[ids] < steps
            if more.any():
                act_and_send(ids[more], observation[more])
            latest[ids[~more]] = observation[~more]

        advantages, targets = ppo_common.advantages(
            agent, next_observations, rewards, values, terminated, done, args.gamma, args.gae_lambda,
            (valid, landers) if args.team_credit else None,
        )
        rows = valid.flatten().nonzero().squeeze(-1)  # Real transitions only.
        batch = tuple(
            t.reshape((-1,) + t.shape[3:])[rows] for t in (observations, actions, logprobs, advantages, targets)
        )
        losses = ppo_common.update(agent, optimizer, batch, args)
        transitions += len(rows)
        seconds = time.perf_counter() - started
        mean = float(np.mean(returns)) if returns else None
        line = {
            "update": update, "env_steps": update * steps * count, "lander_steps": update * steps * count * landers,
            "transitions": transitions, "env_steps_per_s": round(update * steps * count / seconds, 1),
            "episodes": len(returns), "mean_return": mean, **losses,
        }
        curve.append((line["lander_steps"], len(returns), "" if mean is None else f"{mean:.3f}"))
        print(json.dumps(line), flush=True)
    envs.close()
    trainer_common.write_csv(args.csv, ["lander_steps", "episodes", "mean_return"], curve)
    scores.write(args.episodes_csv)
    observation_scale = None
    if observations_seen is not None:
        observation_scale = ppo_common.ObservationScale(observations_seen.mean, observations_seen.var)
    if args.save:
        ppo_common.save(args.save, agent, options, args, observation_scale)
    return agent, observation_scale


def main(argv=None):
    args = parse_args(argv)
    if args.evaluate:
        act, config = ppo_common.load(args.evaluate)
        options = config["options"]
    else:
        (agent, observation_scale), options = train(args), trainer_common.environment_options(args)
        act = ppo_common.greedy(agent, observation_scale, args.neighbor_closeness)
    if args.eval_episodes > 0:
        result = ppo_common.evaluate_greedy(act, ppo_common.evaluation_options(args, options),
                                            args.eval_episodes, address=args.address, envs=args.envs, seed=args.seed)
        print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
