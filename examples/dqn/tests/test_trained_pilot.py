"""The shipped trained pilot (examples/dqn/trained.qnet) flies 3 landers on a
real server with numpy alone and lands most of them; examples/play.py flies
it into a GIF."""

import importlib.util
import os
import pathlib

import multi_lunar_lander as mll
import pytest
from PIL import Image

from mll_dqn import evaluate
from mll_dqn.config import PAPER_ENV_CONFIG
from mll_dqn.qnet_file import SHIPPED, TrainedPilot

# Seeds of the shipped network's greedy check, and the landing rate it must
# reach over them (docs/dqn.md: the trained pilot; its rate over 100
# evaluation episodes is stated there).
EPISODES = 8
SEED = 3_000_000
MIN_LANDING_RATE = 0.8
PLAY = pathlib.Path(__file__).resolve().parents[2] / "play.py"


@pytest.fixture(scope="module")
def address():
    with mll.ServerProcess(threads=1) as server:
        yield server.address


def test_shipped_network_is_small_and_lands_three_landers(address):
    assert os.path.getsize(SHIPPED) < 200_000
    pilot = TrainedPilot()
    assert [w.shape[1] for w, _ in pilot.layers] == [12, 256, 64]
    result = evaluate.evaluate(pilot, PAPER_ENV_CONFIG, EPISODES, address,
                               SEED)
    assert result["landing_rate"] >= MIN_LANDING_RATE, result


def test_play_flies_the_trained_pilot_into_a_gif(address, tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("play", PLAY)
    play = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(play)
    gif = tmp_path / "trained.gif"
    assert play.main(["--policy", "trained", "--address", address,
                      "--n_landers", "3", "--seed", "4", "--frame_skip", "8",
                      "--gif", str(gif)]) == 0
    printed = capsys.readouterr().out
    assert "episode 0 (seed 4)" in printed and "landed" in printed
    with Image.open(gif) as image:
        assert image.n_frames > 1
    with pytest.raises(SystemExit):
        play.main(["--policy", "trained", "--continuous"])
