"""The shared Q-network's learning step and the config's validation."""

import dataclasses
import math

import numpy as np
import pytest
import torch

import multi_lunar_lander
from mll_dqn.agent import (DQNAgent, QNetwork, RepeatedExploration,
                           neighbor_closeness)
from mll_dqn.config import TrainConfig, preset
from mll_dqn.train import epsilon_after, lr_after


def _batch(rng, size=64):
    return (rng.normal(size=(size, 12)).astype(np.float32),
            rng.integers(0, 4, size), rng.normal(size=size).astype(np.float32),
            rng.normal(size=(size, 12)).astype(np.float32),
            np.where(rng.random(size) < 0.1, 0.0, 0.99).astype(np.float32))


def test_network_shape_is_the_papers():
    agent = DQNAgent(preset("paper"))
    shapes = [tuple(p.shape) for p in agent.online.parameters()]
    assert shapes == [(256, 12), (256,), (64, 256), (64,), (4, 64), (4,)]


@pytest.mark.parametrize("double_dqn,loss", [(False, "mse"), (True, "huber")])
def test_learning_fits_a_fixed_batch(double_dqn, loss):
    torch.set_num_threads(1)
    config = dataclasses.replace(preset("paper"), double_dqn=double_dqn,
                                 loss=loss, lr=1e-3)
    agent = DQNAgent(config)
    batch = _batch(np.random.default_rng(0))
    first = agent.learn(batch)
    for _ in range(300):
        last = agent.learn(batch)
    assert last < 0.2 * first
    assert agent.updates == 301


def test_importance_weights_scale_each_transitions_loss():
    config = dataclasses.replace(preset("paper"), loss="huber")
    batch = _batch(np.random.default_rng(2), size=8)
    agent = DQNAgent(config)
    before = [p.clone() for p in agent.online.parameters()]
    loss, td_errors = agent.learn_weighted(batch, np.zeros(8, np.float32))
    # Weight 0 everywhere: no gradient, the online network is unchanged; the
    # TD errors are still reported (the new priorities).
    assert loss == 0.0 and td_errors.shape == (8,) and (td_errors > 0).all()
    for old, new in zip(before, agent.online.parameters()):
        assert torch.equal(old, new)
    # Weight 1 everywhere is the unweighted loss (the same networks).
    twin = DQNAgent(config)
    twin.online.load_state_dict(agent.online.state_dict())
    twin.target.load_state_dict(agent.target.state_dict())
    unweighted = DQNAgent(config)
    unweighted.online.load_state_dict(agent.online.state_dict())
    unweighted.target.load_state_dict(agent.target.state_dict())
    assert twin.learn_weighted(batch, np.ones(8, np.float32))[0] == pytest.approx(
            unweighted.learn(batch), rel=1e-6)


def _autograd_step(config, online, target, batch, weights, optimizer):
    """The learning step as autograd, torch's Adam and clip_grad_norm_ make
    it: the reference for the agent's hand-written gradient."""
    obs, actions, rewards, next_obs, discounts = (
        torch.from_numpy(array) for array in batch)
    with torch.no_grad():
        next_q = target(next_obs)
        if config.double_dqn:
            best = online(next_obs).argmax(dim=1, keepdim=True)
            next_value = next_q.gather(1, best).squeeze(1)
        else:
            next_value = next_q.max(dim=1)[0]
        targets = rewards + discounts * next_value
    q = online(obs).gather(1, actions.unsqueeze(1)).squeeze(1)
    loss_of = (torch.nn.functional.smooth_l1_loss if config.loss == "huber"
               else torch.nn.functional.mse_loss)
    each = loss_of(q, targets, reduction="none")
    loss = (each if weights is None else torch.from_numpy(weights) * each).mean()
    optimizer.zero_grad()
    loss.backward()
    if config.grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(online.parameters(), config.grad_clip)
    optimizer.step()
    with torch.no_grad():
        for t, o in zip(target.parameters(), online.parameters()):
            t.mul_(1 - config.tau).add_(o, alpha=config.tau)
    return float(loss)


def _agent_and_autograd_twin(config):
    """An agent, and copies of its networks with torch's Adam over the copy
    of the online one, for _autograd_step."""
    agent = DQNAgent(config)
    online, target = (QNetwork(config.hidden, neighbor_input=config.neighbor_input)
                      for _ in range(2))
    online.load_state_dict(agent.online.state_dict())
    target.load_state_dict(agent.target.state_dict())
    return agent, online, target, torch.optim.Adam(online.parameters(), lr=config.lr)


@pytest.mark.parametrize("name,changes,weighted", [
    ("paper", {}, False),
    ("default", {}, False),
    ("default", dict(loss="mse", grad_clip=0.05), True),
    ("default", dict(double_dqn=False, grad_clip=0.0), True),
])
def test_hand_written_step_is_autograd_with_torchs_adam(name, changes, weighted):
    """Ten learning steps of the agent (its hand-written gradient, flat Adam,
    clip and target update) leave the networks where autograd, torch.optim.Adam
    and clip_grad_norm_ take copies of them, for each loss, with and without
    Double DQN, importance weights and a clip that bites."""
    torch.set_num_threads(1)
    config = dataclasses.replace(preset(name), **changes)
    agent, online, target, optimizer = _agent_and_autograd_twin(config)
    rng = np.random.default_rng(4)
    for _ in range(10):
        batch = _batch(rng, size=config.batch_size)
        weights = rng.random(config.batch_size).astype(np.float32) if weighted else None
        loss, _ = agent.learn_weighted(batch, weights)
        assert loss == pytest.approx(
            _autograd_step(config, online, target, batch, weights, optimizer),
            rel=1e-5)
    for ours, reference in ((agent.online, online), (agent.target, target)):
        for got, want in zip(ours.parameters(), reference.parameters()):
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_adam_state_of_an_earlier_checkpoint_loads_and_steps_as_torchs():
    """A checkpoint of an earlier version holds torch.optim.Adam's state: it
    loads into the flat Adam, whose next steps match torch's."""
    torch.set_num_threads(1)
    config = preset("default")
    agent, online, target, optimizer = _agent_and_autograd_twin(config)
    rng = np.random.default_rng(5)
    for _ in range(3):
        _autograd_step(config, online, target, _batch(rng, 512), None, optimizer)
    agent.load_state_dict(dict(online=online.state_dict(),
                               target=target.state_dict(),
                               optimizer=optimizer.state_dict(), updates=3))
    assert agent.optimizer.step_count == 3
    for _ in range(3):
        batch = _batch(rng, 512)
        agent.learn(batch)
        _autograd_step(config, online, target, batch, None, optimizer)
    for got, want in zip(agent.online.parameters(), online.parameters()):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_target_network_follows_by_soft_updates():
    config = dataclasses.replace(preset("paper"), tau=0.25)
    agent = DQNAgent(config)
    before = [p.clone() for p in agent.target.parameters()]
    agent.learn(_batch(np.random.default_rng(1)))
    for old, target, online in zip(before, agent.target.parameters(),
                                   agent.online.parameters()):
        torch.testing.assert_close(target, 0.75 * old + 0.25 * online)


def test_double_dqn_target_uses_online_argmax():
    """With a frozen online net, one step's target must be
    r + d * Q_target(s', argmax_a Q_online(s', a))."""
    config = dataclasses.replace(preset("paper"), double_dqn=True, lr=1e-12)
    agent = DQNAgent(config)
    # Make the two networks differ.
    with torch.no_grad():
        for p in agent.target.parameters():
            p.mul_(-1.5)
    obs, actions, rewards, next_obs, discounts = _batch(
        np.random.default_rng(2), 8)
    with torch.no_grad():
        best = agent.online(torch.from_numpy(next_obs)).argmax(1)
        value = agent.target(torch.from_numpy(next_obs))[torch.arange(8), best]
        want = torch.from_numpy(rewards) + torch.from_numpy(discounts) * value
        q = agent.online(torch.from_numpy(obs))[torch.arange(8),
                                                torch.from_numpy(actions)]
        want_loss = torch.nn.functional.mse_loss(q, want)
    loss = agent.learn((obs, actions, rewards, next_obs, discounts))
    assert loss == pytest.approx(float(want_loss), rel=1e-5)


def test_epsilon_greedy_extremes():
    agent = DQNAgent(preset("paper"))
    rng = np.random.default_rng(3)
    obs = rng.normal(size=(500, 12)).astype(np.float32)
    np.testing.assert_array_equal(agent.act(obs, 0.0, rng), agent.greedy(obs))
    random_actions = agent.act(obs, 1.0, rng)
    assert set(np.unique(random_actions)) == {0, 1, 2, 3}


def test_guided_exploration_takes_the_heuristic_pilots_share_of_exploring_actions():
    rng = np.random.default_rng(5)
    obs = rng.normal(size=(2000, 12)).astype(np.float32)
    pilot = multi_lunar_lander.heuristic(obs)
    agent = DQNAgent(dataclasses.replace(preset("paper"), explore_guide=1.0))
    np.testing.assert_array_equal(agent.act(obs, 1.0, rng), pilot)
    np.testing.assert_array_equal(agent.act(obs, 0.0, rng), agent.greedy(obs))
    # Half guided: uniform actions agree with the pilot's a quarter of the
    # time, so 1/2 + 1/2 * 1/4 of all actions are the pilot's.
    agent = DQNAgent(dataclasses.replace(preset("paper"), explore_guide=0.5))
    assert 0.59 < (agent.act(obs, 1.0, rng) == pilot).mean() < 0.66
    with pytest.raises(ValueError, match="explore_guide = 0.5 with explore_zeta = 2.0"):
        dataclasses.replace(preset("paper"), explore_guide=0.5,
                            explore_zeta=2.0).validate()


def test_repeated_exploration_keeps_an_exploring_action_for_its_run():
    agent = DQNAgent(preset("paper"))
    rng = np.random.default_rng(4)
    streams = np.arange(6)
    obs = rng.normal(size=(6, 12)).astype(np.float32)
    # epsilon 0: greedy, as plain epsilon-greedy.
    exploration = RepeatedExploration(6, zeta=2.0, max_steps=50)
    np.testing.assert_array_equal(
        exploration.act(agent, obs, streams, 0.0, rng), agent.greedy(obs))
    # epsilon 1: every stream is always exploring, and a new action is drawn
    # only when a run ends. Runs of min(zeta(2), 5) steps last 1.94 steps on
    # average, so the action changes on 0.75 / 1.94 = 39% of the steps
    # (one-step runs, max_steps=1: on 75%, as plain epsilon-greedy).
    for max_steps, low, high in ((5, 0.33, 0.45), (1, 0.70, 0.80)):
        exploration = RepeatedExploration(6, zeta=2.0, max_steps=max_steps)
        history = np.stack([exploration.act(agent, obs, streams, 1.0, rng)
                            for _ in range(1000)])
        assert low < (history[1:] != history[:-1]).mean() < high
    # A stream whose episode ended starts afresh: greedy at epsilon 0.
    exploration = RepeatedExploration(6, zeta=2.0, max_steps=50)
    exploration.act(agent, obs, streams, 1.0, rng)
    exploration.stop(streams[:3])
    actions = exploration.act(agent, obs, streams, 0.0, rng)
    np.testing.assert_array_equal(actions[:3], agent.greedy(obs[:3]))


def test_epsilon_schedule_is_the_papers():
    config = preset("paper")
    assert epsilon_after(config, 0) == 1.0
    assert epsilon_after(config, 100) == pytest.approx(0.995 ** 100)
    assert epsilon_after(config, 1000) == 0.01


def test_learning_rate_decays_linearly_to_lr_end():
    config = dataclasses.replace(preset("paper"), lr=1e-3, lr_end=1e-4,
                                 episodes=101)
    assert lr_after(config, 0) == pytest.approx(1e-3)
    assert lr_after(config, 50) == pytest.approx(5.5e-4)
    assert lr_after(config, 100) == pytest.approx(1e-4)
    assert lr_after(config, 500) == pytest.approx(1e-4)
    # lr_end 0: the paper's constant rate.
    paper = preset("paper")
    assert lr_after(paper, 0) == lr_after(paper, 999) == paper.lr
    agent = DQNAgent(config)
    agent.set_lr(lr_after(config, 50))
    assert agent.optimizer.lr == pytest.approx(5.5e-4)


def test_learning_rate_reaches_lr_end_at_lr_decay_episodes_then_holds():
    config = dataclasses.replace(preset("paper"), lr=1e-3, lr_end=1e-4,
                                 lr_decay_episodes=10, episodes=1000)
    assert lr_after(config, 0) == pytest.approx(1e-3)
    assert lr_after(config, 5) == pytest.approx(5.5e-4)
    assert lr_after(config, 10) == lr_after(config, 999) == pytest.approx(1e-4)


def test_target_preset_keeps_the_papers_samples_per_transition():
    paper, target = preset("paper"), preset("target")
    assert (target.batch_size / target.update_every
            == paper.batch_size / paper.update_every)
    assert target.lr_end < target.lr and target.mode == "vector"
    assert target.env_config == paper.env_config
    target.validate()


def test_default_preset_is_target10_with_the_changes_docs_list():
    default, target10 = preset("default"), preset("target10")
    changed = {f.name: getattr(default, f.name) for f in dataclasses.fields(default)
               if getattr(default, f.name) != getattr(target10, f.name)}
    assert changed == dict(explore_guide=1.0, buffer_size=1_000_000,
                           eps_decay=0.98, lr_decay_episodes=700,
                           neighbor_input="closeness")
    default.validate()


def test_paper_preset_is_table_iv():
    config = preset("paper")
    assert (config.lr, config.buffer_size, config.batch_size, config.gamma,
            config.tau, config.update_every, config.episodes) == (
                5e-4, 100_000, 128, 0.99, 1e-3, 4, 1000)
    assert config.hidden == (256, 64) and config.mode == "parallel"
    assert not config.double_dqn and config.loss == "mse" and config.n_step == 1
    assert config.env_config["max_cycles"] == 2000
    assert config.env_config["successful_reward"] == 700


@pytest.mark.parametrize("field,value,message", [
    ("n_step", 0, "n_step = 0 is out of range; allowed: >= 1"),
    ("mode", "async", "mode = 'async' is out of range; allowed: parallel or"),
    ("gamma", 1.5, "gamma = 1.5 is out of range; allowed: [0, 1]"),
    ("reward_scale", 0.0, "reward_scale = 0.0 is out of range; allowed: > 0"),
    ("lr_end", 1.0, "lr_end = 1.0 is out of range; allowed: [0, lr]"),
    ("torch_threads", 0, "torch_threads = 0 is out of range; allowed: >= 1"),
    ("explore_zeta", 1.0, "explore_zeta = 1.0 is out of range; allowed: 0 (off) or > 1"),
    ("explore_guide", 1.5, "explore_guide = 1.5 is out of range; allowed: [0, 1]"),
    ("neighbor_input", "raw",
     "neighbor_input = 'raw' is out of range; allowed: offset or closeness"),
])
def test_bad_config_names_field_value_and_range(field, value, message):
    config = dataclasses.replace(TrainConfig(), **{field: value})
    with pytest.raises(ValueError) as error:
        config.validate()
    assert message in str(error.value)


def test_neighbor_closeness_is_largest_near_and_zero_when_absent():
    # Lander 0 has a neighbor 1 world unit to its right and one 6 units below
    # it; lander 1 has none. Offsets are own minus neighbor, in W/2 and H/2.
    obs = torch.zeros(2, 12)
    obs[:, :8] = torch.arange(8.0)
    obs[0, 8:12] = torch.tensor([-1.0 / 10, 0.0, 0.0, 6.0 / (20.0 / 3.0)])
    seen = neighbor_closeness(obs)
    assert torch.equal(seen[:, :8], obs[:, :8])
    expected = [-math.exp(-0.5), 0.0, 0.0, math.exp(-3.0)]
    assert seen[0, 8:].tolist() == pytest.approx(expected, rel=1e-6)
    assert seen[1, 8:].tolist() == [0.0] * 4
    # A neighbor nearly overlapping sees ~1, not the 0 of an absent one.
    obs[1, 8] = 1e-4
    assert neighbor_closeness(obs)[1, 8] == pytest.approx(1.0, abs=1e-3)
    # The network applies it only when configured to.
    paper, default = QNetwork(), QNetwork(neighbor_input="closeness")
    default.load_state_dict(paper.state_dict())
    with torch.no_grad():
        assert torch.equal(default(obs), paper(neighbor_closeness(obs)))
        assert not torch.equal(default(obs), paper(obs))


def test_target10_is_target_with_overlap():
    target, fast = preset("target"), preset("target10")
    assert fast.overlap and not target.overlap
    assert dataclasses.replace(fast, overlap=False) == target
    assert not preset("paper").overlap
