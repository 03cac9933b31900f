"""examples/plot_curves.py: runs sharing a label become one mean curve with a min-max band."""

import pathlib
import sys

import numpy as np

EXAMPLES = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(EXAMPLES))

import plot_curves  # noqa: E402


def test_group_band_is_mean_min_and_max_over_the_shared_range():
    first = (np.array([0.0, 10.0, 20.0]), np.array([0.0, 10.0, 20.0]))
    second = (np.array([5.0, 15.0, 30.0]), np.array([5.0, 5.0, 5.0]))
    grid, mean, low, high = plot_curves.group_band([first, second], points=3)
    np.testing.assert_allclose(grid, [5.0, 12.5, 20.0])  # Where both runs have data.
    np.testing.assert_allclose(low, [5.0, 5.0, 5.0])
    np.testing.assert_allclose(high, [5.0, 12.5, 20.0])
    np.testing.assert_allclose(mean, [5.0, 8.75, 12.5])


def test_writes_one_figure_for_several_labelled_runs(tmp_path):
    rows = "episode,score,mean50,env_steps,wall_s\n" + "".join(
        f"{i},{i},{i * 2},{i * 100},{i * 0.5}\n" for i in range(1, 20)
    )
    paths = []
    for seed in range(3):
        path = tmp_path / f"s{seed}.csv"
        path.write_text(rows)
        paths.append(f"{path}:PPO")
    out = tmp_path / "curves.png"
    plot_curves.main([*paths, f"{paths[0].split(':')[0]}:DQN", "--x", "wall_s", "--out", str(out)])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
