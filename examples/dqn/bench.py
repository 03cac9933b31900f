"""Speed of the trainer's parts against the paper's way of doing the same,
measured in the same run (docs/benchmarks.md, run F). Not a test: prints a
Markdown table. Each measurement is bounded in time.

    OMP_NUM_THREADS=1 ../../.venv/bin/python bench.py [--seconds 2]
"""

from __future__ import annotations

import argparse
import collections
import os
import random
import sys
import time

import numpy as np
import torch
from torch.nn import functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from mll_dqn.agent import DQNAgent  # noqa: E402
from mll_dqn.collect import Timers, VectorCollector  # noqa: E402
from mll_dqn.config import PAPER_ENV_CONFIG, preset  # noqa: E402
from mll_dqn.heap import keep_freed_memory  # noqa: E402
from mll_dqn.replay import ReplayBuffer  # noqa: E402


def per_call_us(call, seconds: float) -> float:
    """Median over 5 rounds of the mean time of `call` in microseconds."""
    call()
    rounds = []
    for _ in range(5):
        count, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds / 5:
            call()
            count += 1
        rounds.append((time.perf_counter() - start) / count * 1e6)
    return float(np.median(rounds))


def paper_learn(agent: DQNAgent, batch, optimizer) -> None:
    """The paper script's learn(): per-tensor Adam, per-parameter soft
    update loop."""
    obs, actions, rewards, next_obs, dones = batch
    q_next = agent.target(next_obs).detach().max(1)[0].unsqueeze(1)
    targets = rewards + 0.99 * q_next * (1 - dones)
    q = agent.online(obs).gather(1, actions)
    loss = F.mse_loss(q, targets)
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    for t, o in zip(agent.target.parameters(), agent.online.parameters()):
        t.data.copy_(1e-3 * o.data + (1.0 - 1e-3) * t.data)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--address", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    keep_freed_memory()  # as `train` does
    rng = np.random.default_rng(0)
    rows = []

    # Learning step, batch 128.
    config = preset("paper")
    agent = DQNAgent(config)
    buffer = ReplayBuffer(config.buffer_size, 12)
    n = config.buffer_size
    buffer.add(rng.normal(size=(n, 12)).astype(np.float32),
               rng.integers(0, 4, n), rng.normal(size=n).astype(np.float32),
               rng.normal(size=(n, 12)).astype(np.float32),
               np.full(n, 0.99, np.float32))
    batch = buffer.sample(128, rng)
    ours = per_call_us(lambda: agent.learn(batch), args.seconds)
    paper_agent = DQNAgent(config)
    paper_optimizer = torch.optim.Adam(paper_agent.online.parameters(), lr=5e-4)
    tensors = (torch.from_numpy(batch[0]),
               torch.from_numpy(batch[1]).unsqueeze(1),
               torch.from_numpy(batch[2]).unsqueeze(1),
               torch.from_numpy(batch[3]),
               torch.zeros(128, 1))
    theirs = per_call_us(lambda: paper_learn(paper_agent, tensors,
                                             paper_optimizer), args.seconds)
    rows.append(("learning step, batch 128", ours, theirs))
    for size in (256, 512):
        big = buffer.sample(size, rng)
        rows.append((f"learning step, batch {size}",
                     per_call_us(lambda: agent.learn(big), args.seconds), None))
    # The learner on two torch threads (the `torch_threads` option) against
    # one, batch 512: worth it only if the second core is otherwise idle.
    one_thread = rows[-1][1]
    torch.set_num_threads(2)
    rows.append(("learning step, batch 512, 2 threads (vs 1 thread)",
                 per_call_us(lambda: agent.learn(big), args.seconds),
                 one_thread))
    torch.set_num_threads(1)

    # Replay sampling, 128 of 1e5.
    memory = collections.deque(maxlen=n)
    for i in range(n):
        memory.append((buffer.obs[i], int(buffer.actions[i]),
                       float(buffer.rewards[i]), buffer.next_obs[i], False))

    def paper_sample():
        chosen = random.sample(memory, k=128)
        torch.from_numpy(np.vstack([e[0] for e in chosen])).float()
        torch.from_numpy(np.vstack([e[1] for e in chosen])).long()
        torch.from_numpy(np.vstack([e[2] for e in chosen])).float()
        torch.from_numpy(np.vstack([e[3] for e in chosen])).float()
        torch.from_numpy(np.vstack([e[4] for e in chosen]).astype(np.uint8))

    rows.append(("replay sample, 128 of 1e5",
                 per_call_us(lambda: buffer.sample(128, rng), args.seconds),
                 per_call_us(paper_sample, args.seconds)))

    # Action selection for 3 landers: one batched pass vs one per lander.
    obs3 = rng.normal(size=(3, 12)).astype(np.float32)

    def paper_act():
        for o in obs3:
            with torch.no_grad():
                values = agent.online(torch.from_numpy(o).float().unsqueeze(0))
            if random.random() > 0.1:
                np.argmax(values.numpy())

    rows.append(("action selection, 3 landers",
                 per_call_us(lambda: agent.act(obs3, 0.1, rng), args.seconds),
                 per_call_us(paper_act, args.seconds)))

    # Environment steps through gRPC: vector_env (N per call) vs parallel_env.
    import multi_lunar_lander as mll
    env = mll.parallel_env(address=args.address, **PAPER_ENV_CONFIG)
    env.reset(seed=0)

    def parallel_step():
        if not env.agents:
            env.reset()
        env.step({a: int(rng.integers(4)) for a in env.agents})

    parallel_us = per_call_us(parallel_step, args.seconds)
    env.close()
    for num_envs in (8, 16, 32):
        venv = mll.vector_env(num_envs, address=args.address,
                              **PAPER_ENV_CONFIG)
        venv.reset(seed=0)
        actions = rng.integers(0, 4, (num_envs, 3))
        us = per_call_us(lambda: venv.step(actions), args.seconds) / num_envs
        venv.close()
        rows.append((f"env step via vector_env({num_envs}), per env step", us,
                     parallel_us))

    # One step of the target10 loop: a StepBatch of 16 environments and the 3
    # gradient steps (batch 512) its 48 transitions earn, the gradient steps
    # run during the call (overlap) against after it.
    target = preset("target10")
    learner = DQNAgent(target)
    collector = VectorCollector(learner, target, args.address, rng, Timers(),
                                seed=0)
    owed = target.num_envs * 3 // target.update_every

    def learn_owed():
        for _ in range(owed):
            learner.learn(buffer.sample(target.batch_size, rng))

    def sequential():
        collector.step(0.1)
        learn_owed()

    sequential_us = per_call_us(sequential, args.seconds)
    rows.append(("target10 loop step: StepBatch(16) + 3 learning steps of "
                 "512, overlapped (vs sequential)",
                 per_call_us(lambda: collector.step(0.1, learn_owed),
                             args.seconds), sequential_us))
    collector.close()

    print(f"load average at end: {os.getloadavg()}")
    print("| what | ours (us) | paper's way (us) | ratio |")
    print("|---|---|---|---|")
    for name, us, peer in rows:
        ratio = f"{us / peer:.2f}" if peer else ""
        peer_text = f"{peer:.0f}" if peer else ""
        print(f"| {name} | {us:.0f} | {peer_text} | {ratio} |")


if __name__ == "__main__":
    main()
