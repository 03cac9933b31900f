"""The paper's figure 2: score per episode and its 50-episode running mean."""

from __future__ import annotations

import csv
from typing import Optional, Sequence

import numpy as np

# The paper's reported 50-episode mean after 1,000 episodes.
PAPER_SCORE = 1400.0


def read_scores(log_path: str) -> np.ndarray:
    with open(log_path, newline="") as f:
        return np.array([float(row["score"]) for row in csv.DictReader(f)])


def running_mean(scores: np.ndarray, window: int = 50) -> np.ndarray:
    cumulative = np.concatenate([[0.0], np.cumsum(scores)])
    index = np.arange(1, len(scores) + 1)
    start = np.maximum(0, index - window)
    return (cumulative[index] - cumulative[start]) / (index - start)


def plot(log_paths: Sequence[str], out_path: str,
         labels: Optional[Sequence[str]] = None, title: str = "") -> None:
    import matplotlib
    matplotlib.use("Agg")  # Files only; no display needed.
    from matplotlib import pyplot as plt

    labels = labels or [None] * len(log_paths)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for path, label in zip(log_paths, labels):
        scores = read_scores(path)
        episodes = np.arange(1, len(scores) + 1)
        line, = ax.plot(episodes, scores, alpha=0.25, linewidth=0.7)
        ax.plot(episodes, running_mean(scores), color=line.get_color(),
                linewidth=2,
                label=(f"{label}: " if label else "") + "50-episode mean")
    ax.axhline(PAPER_SCORE, color="gray", linestyle="--", linewidth=1,
               label=f"paper: {PAPER_SCORE:.0f}")
    ax.set_xlabel("Episode")
    ax.set_ylabel("Score (sum of all landers' rewards)")
    ax.set_title(title or "DQN with parameter sharing, 3 landers")
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_path, dpi=110)
    plt.close(fig)
