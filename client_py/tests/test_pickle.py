"""Every environment pickles as its arguments (options, address, TLS/token settings), never a
live channel or stream: copies made in this process or unpickled in another one create their
own environment on the same server (address=None: the unpickling process's embedded server).
SuperSuit's PettingZoo -> Stable-Baselines3 recipe, which clones the env with cloudpickle and,
with num_cpus > 0, sends it to forked worker processes, runs on it."""

import gc
import json
import pickle
import subprocess
import sys

import cloudpickle
import grpc
import numpy as np
import pytest
import supersuit as ss

import multi_lunar_lander as mll

from mll_test_helpers import listed_names, raises_code

# Run in a fresh interpreter: unpickles the env in argv[1], resets it with seed 7, steps it once
# with zero actions and prints what it saw.
_CHILD = """
import json, pickle, sys
import numpy as np
with open(sys.argv[1], "rb") as file:
    env = pickle.load(file)
kind = sys.argv[2]
if kind == "vector":
    observations, _ = env.reset(seed=7)
    observations = observations.tolist()
elif kind == "parallel":
    observations, _ = env.reset(seed=7)
    observations = {agent: o.tolist() for agent, o in observations.items()}
else:
    env.reset(seed=7)
    observations = env.observe(env.agent_selection).tolist()
print(json.dumps({"address": env.address, "name": env.name if kind != "vector" else env.names[0],
                  "observations": observations}))
env.close()
"""


def _constructors(address):
    return {
        "aec": lambda: mll.env(address=address, n_landers=2, gravity=-9.0),
        "parallel": lambda: mll.parallel_env(address=address, n_landers=2, gravity=-9.0),
        "vector": lambda: mll.vector_env(2, address=address, n_landers=2, gravity=-9.0),
    }


def _observations(env, kind):
    if kind == "vector":
        return env.reset(seed=7)[0].tolist()
    if kind == "parallel":
        return {agent: o.tolist() for agent, o in env.reset(seed=7)[0].items()}
    env.reset(seed=7)
    return env.observe(env.agent_selection).tolist()


def _in_child(tmp_path, env, kind):
    path = tmp_path / f"{kind}.pickle"
    path.write_bytes(pickle.dumps(env))
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, str(path), kind], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("kind", ["aec", "parallel", "vector"])
def test_a_copy_in_this_process_is_a_new_env_with_the_same_options(address, kind):
    env = _constructors(address)[kind]()
    for copy in (pickle.loads(pickle.dumps(env)), cloudpickle.loads(cloudpickle.dumps(env))):
        try:
            assert copy.address == env.address
            assert copy.config == env.config and copy.config["gravity"] == pytest.approx(-9.0)
            names = (copy.names, env.names) if kind == "vector" else ([copy.name], [env.name])
            assert not set(names[0]) & set(names[1])
            assert _observations(copy, kind) == _observations(env, kind)
        finally:
            copy.close()
    env.close()


@pytest.mark.parametrize("kind", ["aec", "parallel", "vector"])
def test_a_copy_in_another_process_reaches_the_same_server(tmp_path, address, kind):
    env = _constructors(address)[kind]()
    seen = _in_child(tmp_path, env, kind)
    assert seen["address"] == address
    assert seen["observations"] == _observations(env, kind)
    env.close()


@pytest.mark.parametrize("kind", ["aec", "parallel", "vector"])
def test_an_embedded_env_copied_to_another_process_starts_its_own_server(tmp_path, kind):
    env = _constructors(None)[kind]()
    seen = _in_child(tmp_path, env, kind)
    assert seen["address"] != env.address.split(",")[0]  # The child's own embedded server.
    assert seen["observations"] == _observations(env, kind)
    env.close()


def test_the_pickle_holds_no_connection_and_keeps_the_token(tmp_path, server):
    token_file = tmp_path / "tokens"
    token_file.write_text("pickled-token-7\n")
    with mll.ServerProcess(threads=1, extra_args=(f"--auth_token_file={token_file}",)) as process:
        env = mll.parallel_env(address=process.address, token="pickled-token-7", n_landers=1)
        data = pickle.dumps(env)
        assert b"Channel" not in data and b"_thread" not in data
        seen = _in_child(tmp_path, env, "parallel")  # $MLL_TOKEN plays no part: the token is in the pickle.
        assert seen["address"] == process.address
        env.close()
        # Without the token the same server refuses, so the child did use the pickled one.
        raises_code(grpc.StatusCode.UNAUTHENTICATED, mll.parallel_env, address=process.address, token="")


@pytest.fixture(scope="module")
def own_server():
    """A server of this module's own, so its environment count is exact."""
    with mll.ServerProcess(threads=2) as process:
        yield process.address


def _env_count(address):
    return len(listed_names(address))


@pytest.mark.parametrize("num_cpus", [0, 2])
def test_supersuit_concat_vec_envs_for_stable_baselines3(own_server, num_cpus):
    """PettingZoo's SB3 tutorial recipe: black_death_v3 keeps finished landers in the batch (it
    steps the env with {} once no agent is left), 4 copies of 3 landers = 12 SB3 envs."""
    base = mll.parallel_env(address=own_server, n_landers=3)
    # Kept referenced: a gymnasium VectorEnv closes its env when garbage-collected (gymnasium 1.2).
    markov = ss.pettingzoo_env_to_vec_env_v1(ss.black_death_v3(base))
    vec = ss.concat_vec_envs_v1(markov, 4, num_cpus=num_cpus, base_class="stable_baselines3")
    try:
        assert vec.num_envs == 12
        assert _env_count(own_server) == 1 + 4  # The original and its 4 copies.
        observations = vec.reset()
        assert observations.shape == (12, 12) and np.isfinite(observations).all()
        rng = np.random.default_rng(0)
        episodes = 0
        for _ in range(400):  # Random landers crash within ~100 steps.
            observations, rewards, dones, infos = vec.step(rng.integers(0, 4, size=12))
            assert observations.shape == (12, 12) and rewards.shape == (12,)
            episodes += int(dones.sum())
            if episodes >= 24:  # Every copy has ended an episode and started the next.
                break
        assert episodes >= 24
    finally:
        vec.close()
        markov.close()
    assert _env_count(own_server) == 0


def test_a_forked_child_leaves_the_parents_embedded_server_alone():
    """A forked worker (multiprocessing's default on Linux, as SuperSuit's num_cpus > 0 uses)
    unpickles an embedded env: it starts its own server and, exiting, does not stop the parent's."""
    import multiprocessing

    env = mll.parallel_env(n_landers=1)
    # Only the server's pid and log path: a reference to the object would keep the child's
    # inherited copy of it alive too.
    pid, log_path = mll.embedded_server().pid, mll.embedded_server()._log_path
    context = multiprocessing.get_context("fork")
    with context.Pool(1) as pool:
        child_address = pool.apply(_reset_and_report, (cloudpickle.dumps(env),))
    assert child_address != env.address
    assert mll.embedded_server().pid == pid and mll.embedded_server().running
    with open(log_path) as log:  # The child removed none of its files.
        assert "listening on" in log.read()
    env.reset(seed=1)  # The parent's env still works.
    env.close()


def _reset_and_report(data):
    env = cloudpickle.loads(data)
    env.reset(seed=1)
    env.step({"lander_0": 0})
    address = env.address
    env.close()
    return address


# The parent's env, inherited by a forked child through memory (an argument would be pickled).
_INHERITED = []


def _use_inherited_then_own(address):
    """In a forked child: the parent's env object, then a new env on the same server."""
    try:
        _INHERITED[0].step({"lander_0": 0})
        refused = None
    except mll.MLLError as error:
        refused = (error.code.name, error.message)
    _INHERITED.clear()  # The child's copy goes: it must not delete the parent's env on the server.
    gc.collect()
    own = mll.parallel_env(address=address, n_landers=1)
    own.reset(seed=2)
    own.step({"lander_0": 1})
    own.close()
    return refused


def test_a_forked_child_refuses_the_parents_connection_and_leaves_its_env_alone(own_server):
    """A forked child inherits the parent's env objects (and a renewal thread's state) but not
    their sockets: using them is refused with FAILED_PRECONDITION naming both processes, dropping
    them deletes nothing, and the child's own envs work. Errors cross the process boundary as
    MLLError (they pickle)."""
    import multiprocessing

    env = mll.parallel_env(address=own_server, n_landers=1)
    env.reset(seed=1)
    _INHERITED[:] = [env]
    context = multiprocessing.get_context("fork")
    with context.Pool(1) as pool:
        code, message = pool.apply(_use_inherited_then_own, (own_server,))
    _INHERITED.clear()
    with context.Pool(1) as pool:
        # An MLLError raised in the worker arrives as itself.
        with pytest.raises(mll.MLLError) as raised:
            pool.apply(_raise_invalid_argument)
    assert code == "FAILED_PRECONDITION" and "forked process must make its own environments" in message
    assert raised.value.code == grpc.StatusCode.INVALID_ARGUMENT and raised.value.message == "n_landers is 0"
    assert env.name in listed_names(own_server)
    env.step({"lander_0": 0})  # The parent's env still works on the parent's connection.
    env.close()


def _raise_invalid_argument():
    raise mll.MLLError(grpc.StatusCode.INVALID_ARGUMENT, "n_landers is 0")
