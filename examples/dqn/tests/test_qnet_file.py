"""The .qnet file: torch's network and numpy's reading of it agree, and a
damaged file is refused with a message naming what is wrong."""

import dataclasses

import numpy as np
import pytest
import torch

from mll_dqn import evaluate, qnet_file
from mll_dqn.agent import DQNAgent
from mll_dqn.config import preset
from mll_dqn.train import _save_best, Progress


def _checkpoint(tmp_path, seed=3, neighbor_input="offset"):
    config = dataclasses.replace(preset("quick"), seed=seed,
                                 neighbor_input=neighbor_input)
    agent = DQNAgent(config)
    path = str(tmp_path / "net.pt")
    _save_best(path, config, agent, Progress())
    return path, agent


@pytest.mark.parametrize("neighbor_input", ["offset", "closeness"])
def test_export_matches_torch_forward(tmp_path, neighbor_input):
    path, agent = _checkpoint(tmp_path, neighbor_input=neighbor_input)
    out = str(tmp_path / "net.qnet")
    evaluate.export_qnet(path, out)
    # 12-256-64-4 in float32 plus a 32-byte header.
    assert (tmp_path / "net.qnet").stat().st_size == 32 + 4 * (
        12 * 256 + 256 + 256 * 64 + 64 + 64 * 4 + 4)
    assert qnet_file.load(out).neighbor_input == neighbor_input
    obs = np.random.default_rng(0).normal(size=(64, 12)).astype(np.float32)
    obs[::4, 8:12] = 0  # Landers without neighbors.
    with torch.no_grad():
        expected = agent.online(torch.from_numpy(obs)).numpy()
    got = qnet_file.q_values(qnet_file.load(out), obs)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)
    pilot = qnet_file.TrainedPilot(out)
    np.testing.assert_array_equal(pilot(obs), expected.argmax(axis=1))


def test_export_best_chooses_the_one_given_alone(tmp_path):
    path, _ = _checkpoint(tmp_path)
    result = evaluate.export_best([path], str(tmp_path / "one.qnet"))
    assert result["checkpoint"] == path and result["landing_rates"] == {}


@pytest.mark.parametrize("damage, message", [
    (lambda d: b"XXXX" + d[4:], "not a .qnet file"),
    (lambda d: d[:4] + (7).to_bytes(4, "little") + d[8:],
     "version 7 is not supported; allowed: 1 or 2"),
    (lambda d: d[:8] + (9).to_bytes(4, "little") + d[12:],
     "inputs 9; allowed: 0 \\(offset\\) or 1 \\(closeness\\)"),
    (lambda d: d[:12] + (99).to_bytes(4, "little") + d[16:], "99 layers"),
    (lambda d: d[:-4], "bytes; layer sizes \\[12, 256, 64, 4\\] need"),
    (lambda d: d[:16] + (0).to_bytes(4, "little") + d[20:],
     "layer sizes \\[0, 256, 64, 4\\]"),
    (lambda d: d[:8] + (1).to_bytes(4, "little") + d[12:16]
     + (13).to_bytes(4, "little") + d[20:],
     "13 inputs; a network that sees neighbors by closeness has 12"),
])
def test_damaged_files_are_refused(tmp_path, damage, message):
    path, _ = _checkpoint(tmp_path)
    good = str(tmp_path / "good.qnet")
    evaluate.export_qnet(path, good)
    bad = tmp_path / "bad.qnet"
    bad.write_bytes(damage(open(good, "rb").read()))
    with pytest.raises(ValueError, match=message):
        qnet_file.load(str(bad))


# Fixed observations and the shipped network's Q-values for them, as numpy
# computes them; tests/client_cpp/trained_pilot_test.cc checks the C++ reader
# against the same numbers.
SHIPPED_OBS = [
    [0.0, 1.4, 0.0, 0.0, 0.0, 0.0, 0, 0, 0, 0, 0, 0],
    [0.3, 0.5, -0.2, -0.4, 0.1, 0.05, 0, 0, 0.2, -0.3, 0.1, 0.0],
    [-0.5, 0.2, 0.3, -0.1, -0.2, -0.1, 1, 0, -0.4, 0.6, 0, 1],
]
SHIPPED_Q = [
    [0.675502, 0.639469, 0.624980, 0.667969],
    [-2.340131, -1.910421, -2.127151, -1.987894],
    [0.409632, 0.406116, 0.444865, 0.358943],
]


def test_shipped_network_q_values():
    net = qnet_file.load(qnet_file.SHIPPED)
    assert net.neighbor_input == "closeness"
    q = qnet_file.q_values(net, np.array(SHIPPED_OBS, np.float32))
    np.testing.assert_allclose(q, SHIPPED_Q, atol=2e-6)
