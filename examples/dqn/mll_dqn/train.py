"""The training loop: collection, replay, learning, logging, checkpoints."""

from __future__ import annotations

import collections
import csv
import dataclasses
import json
import os
import time
from typing import Dict, List, Optional

import numpy as np
import torch
import tqdm

from mll_dqn.agent import DQNAgent
from mll_dqn.blas import loaded_openblas_kernels
from mll_dqn.collect import EpisodeRecord, Timers, make_collector
from mll_dqn.config import OBS_SIZE, TrainConfig
from mll_dqn.heap import keep_freed_memory
from mll_dqn.replay import PrioritizedReplayBuffer, ReplayBuffer

# Window of the running mean score (the paper's: 50 episodes).
SCORE_WINDOW = 50
CHECKPOINT = "checkpoint.pt"
# The network of the best 50-episode mean so far (no replay buffer; loadable
# by evaluate.load_policy like CHECKPOINT), as the paper's script kept best.pth.
BEST = "best.pt"
LOG = "episodes.csv"
SUMMARY = "summary.json"


def use_one_thread(threads: int = 1) -> None:
    """One BLAS/torch thread by default: the fastest for this small network,
    and fair to the server and other users of the machine's 2 cores. One
    inter-op thread too (settable once per process, before any parallel
    work: later calls keep what the first set)."""
    torch.set_num_threads(threads)
    if torch.get_num_interop_threads() != 1:
        try:
            torch.set_num_interop_threads(1)
        except RuntimeError:
            pass


def epsilon_after(config: TrainConfig, episodes: int) -> float:
    """Epsilon after `episodes` finished episodes (decayed once per episode)."""
    return max(config.eps_end, config.eps_start * config.eps_decay ** episodes)


def beta_after(config: TrainConfig, episodes: int) -> float:
    """Prioritized replay's importance exponent after `episodes` finished
    episodes: `prioritized_beta` rising linearly to 1 at the last episode."""
    fraction = min(1.0, episodes / max(1, config.episodes - 1))
    return config.prioritized_beta + (1.0 - config.prioritized_beta) * fraction


def lr_after(config: TrainConfig, episodes: int) -> float:
    """Learning rate after `episodes` finished episodes: `lr` decayed linearly
    to `lr_end` at episode `lr_decay_episodes` (0: the last episode) and held
    there, or `lr` throughout when lr_end is 0."""
    if config.lr_end == 0:
        return config.lr
    decay_episodes = config.lr_decay_episodes or config.episodes - 1
    fraction = min(1.0, episodes / max(1, decay_episodes))
    return config.lr + (config.lr_end - config.lr) * fraction


@dataclasses.dataclass
class Progress:
    """What a checkpoint stores beside the networks and the buffer."""
    episodes: int = 0
    env_steps: int = 0
    transitions: int = 0
    wall_s: float = 0.0
    # CPU seconds of the trainer process (not the server's), less sensitive
    # than wall time to other users of the machine.
    cpu_s: float = 0.0
    scores: List[float] = dataclasses.field(default_factory=list)
    # Best 50-episode mean over full windows, and the episode it ends at.
    best_mean50: Optional[float] = None
    best_episode: int = 0
    # Gradient steps earned by stored transitions but not yet made (with
    # overlap they are made during the next environment call).
    owed_updates: int = 0
    timers: Dict[str, float] = dataclasses.field(default_factory=dict)


def _log_header(n_landers: int) -> List[str]:
    return (["episode", "score", "mean50"]
            + [f"return_{i}" for i in range(n_landers)]
            + [f"outcome_{i}" for i in range(n_landers)]
            + ["epsilon", "steps", "env_steps", "updates", "wall_s"])


def train(config: TrainConfig, out_dir: str, address: Optional[str] = None,
          resume: bool = False, progress_bar: bool = True) -> Dict:
    """Trains; returns the summary (also written to out_dir/summary.json)."""
    config.validate()
    use_one_thread(config.torch_threads)
    keep_freed_memory()
    os.makedirs(out_dir, exist_ok=True)
    checkpoint_path = os.path.join(out_dir, CHECKPOINT)
    log_path = os.path.join(out_dir, LOG)
    agent = DQNAgent(config)
    buffer = (PrioritizedReplayBuffer(config.buffer_size, OBS_SIZE,
                                      config.prioritized_alpha)
              if config.prioritized_alpha > 0
              else ReplayBuffer(config.buffer_size, OBS_SIZE))
    progress = Progress()
    rng = np.random.default_rng(config.seed)
    if resume and os.path.exists(checkpoint_path):
        saved = torch.load(checkpoint_path)
        _check_resumable(saved["config"], config, checkpoint_path)
        agent.load_state_dict(saved["agent"])
        buffer.load_state_dict(saved["buffer"])
        progress = Progress(**saved["progress"])
        rng.bit_generator.state = saved["rng"]
        _truncate_log(log_path, progress.episodes)
    elif os.path.exists(log_path):
        os.remove(log_path)
    n_landers = config.env_config.get("n_landers", 3)
    new_log = not os.path.exists(log_path)
    # Line-buffered: each episode is on disk as soon as it ends.
    log_file = open(log_path, "a", newline="", buffering=1)
    log = csv.writer(log_file)
    if new_log:
        log.writerow(_log_header(n_landers))
    timers = Timers()
    timers.seconds.update(progress.timers)
    # A resumed run reseeds with an offset so it does not replay episodes.
    collector = make_collector(agent, config, address, rng, timers,
                               seed=config.seed + progress.episodes)
    window = collections.deque(progress.scores[-SCORE_WINDOW:],
                               maxlen=SCORE_WINDOW)
    learn_start = config.effective_learn_start()
    wall_start = time.perf_counter() - progress.wall_s
    cpu_start = time.process_time() - progress.cpu_s
    run_start = time.perf_counter()
    bar = tqdm.tqdm(total=config.episodes, initial=progress.episodes,
                    disable=not progress_bar, unit="ep", dynamic_ncols=True)
    last_checkpoint = progress.episodes
    steps_before = progress.env_steps
    stopped_early = False

    def learn_owed() -> None:
        """The gradient steps owed by the stored transitions."""
        for _ in range(progress.owed_updates):
            start = time.perf_counter()
            if config.prioritized_alpha > 0:
                batch, index, weights = buffer.sample_prioritized(
                        config.batch_size, rng,
                        beta_after(config, progress.episodes))
                mid = time.perf_counter()
                td_errors = agent.learn_weighted(batch, weights)[1]
                buffer.update_priorities(index, td_errors)
            else:
                batch = buffer.sample(config.batch_size, rng)
                mid = time.perf_counter()
                agent.learn(batch)
            timers.add("sample", mid - start)
            timers.add("learn", time.perf_counter() - mid)
        progress.owed_updates = 0

    try:
        while progress.episodes < config.episodes:
            epsilon = epsilon_after(config, progress.episodes)
            agent.set_lr(lr_after(config, progress.episodes))
            # With overlap, the gradient steps owed by the transitions stored
            # so far run while this step's environment call is in flight.
            transitions, episodes = collector.step(
                epsilon, learn_owed if config.overlap else None)
            if transitions is not None and len(transitions[1]):
                start = time.perf_counter()
                obs, actions, rewards, next_obs, discounts = transitions
                buffer.add(obs, actions, rewards * config.reward_scale,
                           next_obs, discounts)
                timers.add("store", time.perf_counter() - start)
                before = progress.transitions
                progress.transitions += len(transitions[1])
                # One learning trigger per `update_every` transitions, as the
                # paper's t_step counter.
                triggers = (progress.transitions // config.update_every
                            - before // config.update_every)
                if len(buffer) > learn_start:
                    progress.owed_updates += (triggers
                                              * config.updates_per_trigger)
            if not config.overlap:
                learn_owed()
            progress.env_steps = steps_before + collector.env_steps
            for record in episodes:
                if progress.episodes >= config.episodes:
                    break
                progress.episodes += 1
                progress.scores.append(record.score)
                window.append(record.score)
                progress.wall_s = time.perf_counter() - wall_start
                log.writerow(_log_row(
                    progress, record, float(np.mean(window)),
                    epsilon_after(config, progress.episodes - 1),
                    agent.updates))
                bar.update(1)
                if (len(window) == SCORE_WINDOW
                        and (progress.best_mean50 is None
                             or np.mean(window) > progress.best_mean50)):
                    progress.best_mean50 = float(np.mean(window))
                    progress.best_episode = progress.episodes
                    _save_best(os.path.join(out_dir, BEST), config, agent,
                               progress)
                bar.set_postfix(mean50=f"{np.mean(window):.0f}",
                                eps=f"{epsilon:.3f}")
            if progress.episodes - last_checkpoint >= config.checkpoint_every:
                log_file.flush()
                _save(checkpoint_path, config, agent, buffer, progress, rng,
                      timers, wall_start, cpu_start)
                last_checkpoint = progress.episodes
            if (config.time_limit_s
                    and time.perf_counter() - run_start > config.time_limit_s):
                stopped_early = True
                break
        # An overlapped run still owes the last step's gradient steps.
        learn_owed()
    finally:
        bar.close()
        log_file.close()
        collector.close()
    _save(checkpoint_path, config, agent, buffer, progress, rng, timers,
          wall_start, cpu_start)
    summary = _summary(config, progress, agent, timers, stopped_early)
    with open(os.path.join(out_dir, SUMMARY), "w") as f:
        json.dump(summary, f, indent=2)
    return summary


# Fields a resumed run may change: how long it runs and how often it saves.
_RESUME_MAY_CHANGE = ("episodes", "time_limit_s", "checkpoint_every")


def _check_resumable(saved: Dict, config: TrainConfig, path: str) -> None:
    now = config.to_dict()
    # Through the dataclass, so fields added since the save take defaults.
    saved = TrainConfig.from_dict(saved).to_dict()
    changed = sorted(k for k in now if k not in _RESUME_MAY_CHANGE
                     and now[k] != saved[k])
    if changed:
        raise ValueError(
            f"checkpoint {path} was made with other values of {changed}; "
            f"only {list(_RESUME_MAY_CHANGE)} may change on resume")


def _log_row(progress: Progress, record: EpisodeRecord, mean: float,
             epsilon: float, updates: int) -> list:
    return ([progress.episodes, f"{record.score:.3f}", f"{mean:.3f}"]
            + [f"{r:.3f}" for r in record.returns] + record.outcomes
            + [f"{epsilon:.5f}", record.steps, progress.env_steps, updates,
               f"{progress.wall_s:.3f}"])


def _truncate_log(log_path: str, episodes: int) -> None:
    """Drops log rows past the checkpoint's episode count (a resumed run
    repeats them)."""
    if not os.path.exists(log_path):
        return
    with open(log_path, newline="") as f:
        rows = list(csv.reader(f))
    with open(log_path, "w", newline="") as f:
        csv.writer(f).writerows(rows[:episodes + 1])


def _save(path: str, config: TrainConfig, agent: DQNAgent,
          buffer: ReplayBuffer, progress: Progress, rng: np.random.Generator,
          timers: Timers, wall_start: float, cpu_start: float) -> None:
    progress.wall_s = time.perf_counter() - wall_start
    progress.cpu_s = time.process_time() - cpu_start
    progress.timers = dict(timers.seconds)
    state = dict(config=config.to_dict(), agent=agent.state_dict(),
                 buffer=buffer.state_dict(),
                 progress=dataclasses.asdict(progress),
                 rng=rng.bit_generator.state)
    # Write then rename, so an interrupted save never leaves a broken file.
    torch.save(state, path + ".tmp")
    os.replace(path + ".tmp", path)


def _save_best(path: str, config: TrainConfig, agent: DQNAgent,
                progress: Progress) -> None:
    state = dict(config=config.to_dict(),
                 agent=dict(online=agent.online.state_dict()),
                 best_mean50=progress.best_mean50,
                 episode=progress.best_episode)
    torch.save(state, path + ".tmp")
    os.replace(path + ".tmp", path)


def _summary(config: TrainConfig, progress: Progress, agent: DQNAgent,
             timers: Timers, stopped_early: bool) -> Dict:
    scores = np.asarray(progress.scores)
    means = np.array([scores[max(0, i - SCORE_WINDOW + 1):i + 1].mean()
                      for i in range(len(scores))])
    reached = np.flatnonzero(means >= 1400)
    wall = max(progress.wall_s, 1e-9)
    seconds = dict(timers.seconds)
    # The overlapped environment call is timed on its own thread; the parts
    # of the split below are sequential on the trainer's thread.
    env_call = seconds.pop("env_call", None)
    seconds["other"] = max(0.0, wall - sum(seconds.values()))
    return dict(
        config=config.to_dict(),
        episodes=progress.episodes,
        stopped_early=stopped_early,
        final_mean50=float(means[-1]) if len(means) else None,
        mean_last200=float(scores[-200:].mean()) if len(scores) else None,
        best_mean50=progress.best_mean50,
        best_mean50_episode=progress.best_episode,
        first_episode_mean50_ge_1400=(int(reached[0]) + 1
                                      if len(reached) else None),
        wall_s=wall,
        trainer_cpu_s=progress.cpu_s,
        env_steps=progress.env_steps,
        transitions=progress.transitions,
        updates=agent.updates,
        env_steps_per_s=progress.env_steps / wall,
        updates_per_s=agent.updates / wall,
        time_split_s=seconds,
        time_split_fraction={k: v / wall for k, v in seconds.items()},
        env_call_overlapped_s=env_call,
        blas_kernels=loaded_openblas_kernels(),
    )
