"""RLlib PPO on Ray: env runners (Ray actors) each run Multi Lunar Lander parallel envs, spread
over a list of mll_server addresses, all landers sharing one policy.

    python examples/rllib_ppo.py --addresses 10.0.0.5:50051,10.0.0.6:50051 --env-runners 4 --iterations 100

Env runner k (k = 1, 2, ...) puts the j-th env it creates on server
(k * envs_per_runner + j mod envs_per_runner) mod S of --addresses, so the runners' envs are
spread evenly; without --addresses each runner process
starts its own embedded server. --ray-address joins an existing Ray cluster ("auto" from a
node of it); without it a local Ray is started. docs/training.md shows the cluster setup with
servers on Kubernetes.
"""

from __future__ import annotations

import argparse
import itertools
import math

import ray
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
from ray.tune.registry import register_env

import multi_lunar_lander as mll
import trainer_common

ENV_NAME = "multi_lunar_lander"


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--addresses", default="", help="comma-separated mll_server addresses; empty: embedded")
    parser.add_argument("--token", default=None, help="bearer token of the servers (default: $MLL_TOKEN)")
    parser.add_argument("--landers", type=int, default=3)
    parser.add_argument("--max-cycles", type=int, default=500)
    parser.add_argument("--env-runners", type=int, default=2)
    parser.add_argument("--envs-per-runner", type=int, default=1)
    parser.add_argument("--iterations", type=int, default=100)
    parser.add_argument("--batch", type=int, default=4000, help="train batch size (agent steps) per iteration")
    parser.add_argument("--minibatch", type=int, default=500)
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--ray-address", default=None, help="an existing Ray cluster ('auto', 'ray://host:10001')")
    parser.add_argument("--num-cpus", type=int, default=None, help="CPUs of a local Ray (default: all)")
    parser.add_argument("--sample-timeout-s", type=float, default=60.0,
                        help="how long an iteration waits for its env runners' samples (RLlib's default 60)")
    parser.add_argument("--csv", default=None, help="write one row per iteration: agent steps, mean return")
    return parser.parse_args(argv)


# How many envs this process (one env runner) has created: RLlib 2.60's multi-agent env runner
# gives every env of a runner vector_index 0, so the runner counts them itself.
_CREATED = itertools.count()


def make_env(context):
    """RLlib's env creator. `context` is an EnvContext: env_config plus the runner's
    worker_index, which with the runner's own count picks the server."""
    addresses = [a for a in context["addresses"].split(",") if a]
    server_index = None
    if addresses:
        per_runner = context["envs_per_runner"]
        slot = context.worker_index * per_runner + next(_CREATED) % per_runner
        server_index = slot % len(addresses)
    env = mll.parallel_env(
        address=addresses or None,
        server_index=server_index,
        token=context["token"],
        n_landers=context["landers"],
        max_cycles=context["max_cycles"],
    )
    return ParallelPettingZooEnv(env)


def build(args):
    register_env(ENV_NAME, make_env)
    env_config = {
        "addresses": args.addresses,
        "token": args.token,
        "landers": args.landers,
        "max_cycles": args.max_cycles,
        "envs_per_runner": args.envs_per_runner,
    }
    config = (
        PPOConfig()
        .environment(ENV_NAME, env_config=env_config)
        .env_runners(num_env_runners=args.env_runners, num_envs_per_env_runner=args.envs_per_runner,
                     sample_timeout_s=args.sample_timeout_s)
        .multi_agent(policies={"shared"}, policy_mapping_fn=lambda agent_id, episode, **kwargs: "shared")
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs={"shared": RLModuleSpec()}))
        .training(
            lr=args.lr,
            train_batch_size_per_learner=args.batch,
            minibatch_size=args.minibatch,
            num_epochs=args.epochs,
        )
    )
    return config.build_algo()


def main(argv=None):
    args = parse_args(argv)
    ray.init(address=args.ray_address, num_cpus=args.num_cpus, include_dashboard=False)
    rows = []
    try:
        algo = build(args)
        for iteration in range(1, args.iterations + 1):
            result = algo.train()
            runners = result.get("env_runners", {})
            mean = runners.get("episode_return_mean", math.nan)
            steps = runners.get("num_agent_steps_sampled_lifetime", {})
            steps = sum(steps.values()) if isinstance(steps, dict) else steps
            rows.append((iteration, steps, mean))
            print(f"iteration {iteration}: {steps} agent steps, episode return mean {mean:.1f}", flush=True)
        algo.stop()
    finally:
        ray.shutdown()
    trainer_common.write_csv(args.csv, ["iteration", "agent_steps", "episode_return_mean"], rows)
    return rows


if __name__ == "__main__":
    main()
