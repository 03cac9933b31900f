"""Greedy evaluation, baselines, and an animated GIF of one episode.

A policy maps a batch of observations [B, 12] to discrete actions [B]:
the trained network (greedy), Gymnasium's heuristic pilot, or uniform random
actions. Evaluation runs whole episodes of one parallel_env from fixed seeds,
so every policy meets the same terrains and pushes.
"""

from __future__ import annotations

import collections
from typing import Callable, Dict, Optional

import numpy as np
import torch

import multi_lunar_lander
from mll_dqn import qnet_file
from mll_dqn.agent import QNetwork
from mll_dqn.collect import NO_OUTCOME, lander_index, outcome_name
from mll_dqn.config import N_ACTIONS, TrainConfig

Policy = Callable[[np.ndarray], np.ndarray]

# Evaluation seeds start here, away from the training run's seeds.
EVAL_SEED = 1_000_000
# Seeds of the episodes that choose which checkpoint to export, apart from
# the evaluation's, so the reported figures are not the ones chosen on.
SELECT_SEED = 2_000_000


def load_network(checkpoint_path: str):
    """(the checkpoint's online QNetwork, its TrainConfig)."""
    saved = torch.load(checkpoint_path)
    config = TrainConfig.from_dict(saved["config"])
    net = QNetwork(config.hidden, neighbor_input=config.neighbor_input)
    net.load_state_dict(saved["agent"]["online"])
    net.eval()
    return net, config


def export_qnet(checkpoint_path: str, out_path: str) -> None:
    """Writes the checkpoint's online network as a .qnet file (qnet_file)."""
    net, config = load_network(checkpoint_path)
    qnet_file.save(out_path, [
        (layer.weight.detach().numpy(), layer.bias.detach().numpy())
        for layer in net.linear_layers()], config.neighbor_input)


def export_best(checkpoints, out_path: str, episodes: int = 30,
                address: Optional[str] = None) -> Dict:
    """Exports the checkpoint whose greedy policy lands most often over
    `episodes` episodes from SELECT_SEED (the first one given if only one, or
    on a tie)."""
    rates = {}
    if len(checkpoints) > 1:
        for path in checkpoints:
            policy, config = load_policy(path)
            rates[path] = evaluate(policy, config.env_config, episodes,
                                   address, SELECT_SEED)["landing_rate"]
    chosen = max(checkpoints, key=lambda path: rates.get(path, 0.0))
    export_qnet(chosen, out_path)
    return dict(out=out_path, checkpoint=chosen, landing_rates=rates)


def load_policy(checkpoint_path: str):
    """(greedy policy of the checkpoint's online network, its TrainConfig)."""
    net, config = load_network(checkpoint_path)

    @torch.no_grad()
    def policy(obs: np.ndarray) -> np.ndarray:
        return net(torch.from_numpy(np.asarray(obs, np.float32))).argmax(
            dim=1).numpy()

    return policy, config


def heuristic_policy(obs: np.ndarray) -> np.ndarray:
    """Gymnasium's heuristic pilot (the client's, vectorised)."""
    return multi_lunar_lander.heuristic(obs)


def random_policy(seed: int = 0) -> Policy:
    rng = np.random.default_rng(seed)
    return lambda obs: rng.integers(0, N_ACTIONS, len(obs))


def run_episode(env, policy: Policy, seed: Optional[int], frames=None):
    """Plays one episode; returns (score, per-lander outcomes, steps)."""
    obs, _ = env.reset(seed=seed)
    n = len(env.possible_agents)
    outcomes = [NO_OUTCOME] * n
    score = 0.0
    steps = 0
    if frames is not None:
        frames.append(env.render())
    while env.agents:
        agents = list(env.agents)
        actions = policy(np.stack([obs[a] for a in agents]))
        obs, rewards, terms, truncs, infos = env.step(
            {a: int(act) for a, act in zip(agents, actions)})
        steps += 1
        score += float(sum(rewards.values()))
        for a in agents:
            if terms[a] or truncs[a]:
                outcomes[lander_index(a)] = outcome_name(infos.get(a, {}))
        if frames is not None and env.agents:
            frames.append(env.render())
    return score, outcomes, steps


def evaluate(policy: Policy, env_config: Dict, episodes: int = 100,
             address: Optional[str] = None, seed: int = EVAL_SEED) -> Dict:
    """Mean score, landing and crash rates over `episodes` episodes.

    Rates are per lander: the fraction of lander-episodes ending in each
    outcome (crash rate counts body/leg damage; out_of_bounds is separate).
    """
    env = multi_lunar_lander.parallel_env(address=address, **env_config)
    scores, steps, counts = [], [], collections.Counter()
    try:
        for episode in range(episodes):
            score, outcomes, length = run_episode(env, policy, seed + episode)
            scores.append(score)
            steps.append(length)
            counts.update(outcomes)
    finally:
        env.close()
    landers = episodes * env_config.get("n_landers", 3)
    return dict(
        episodes=episodes,
        mean_score=float(np.mean(scores)),
        std_score=float(np.std(scores)),
        mean_steps=float(np.mean(steps)),
        landing_rate=counts["landed"] / landers,
        crash_rate=counts["crashed"] / landers,
        out_of_bounds_rate=counts["out_of_bounds"] / landers,
        truncated_rate=counts["truncated"] / landers,
        # Ended by another lander's crash (terminate_on_damage).
        aborted_rate=counts["aborted"] / landers,
    )


def save_gif(policy: Policy, env_config: Dict, path: str,
             address: Optional[str] = None, seed: int = EVAL_SEED,
             frame_skip: int = 2) -> Dict:
    """Renders one episode to an animated GIF (every `frame_skip`-th frame)."""
    from PIL import Image  # Only this command needs Pillow.

    config = dict(env_config, render_mode="rgb_array")
    env = multi_lunar_lander.parallel_env(address=address, **config)
    frames = []
    try:
        score, outcomes, steps = run_episode(env, policy, seed, frames)
    finally:
        env.close()
    images = [Image.fromarray(np.asarray(f, np.uint8))
              for f in frames[::frame_skip]]
    # GIF delays are in ms; the simulation runs at 50 frames per second.
    images[0].save(path, save_all=True, append_images=images[1:],
                   duration=int(1000 * frame_skip / 50), loop=0,
                   optimize=True)
    return dict(path=path, score=score, outcomes=outcomes, steps=steps,
                frames=len(images))
