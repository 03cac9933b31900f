"""vector_env's transport= option: its steps travel over the native library's gRPC C++ stream or
through shared memory, with the same bits as each other and as parallel envs stepped alone, and the
same errors; the option is checked and survives pickling; "grpc" is gone, and without the library
vector_env says how to get it."""

import gc
import json
import multiprocessing
import os
import pickle
import shutil

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
import subprocess
import sys

from multi_lunar_lander import _native
from multi_lunar_lander._stubs import pb

from mll_test_helpers import check_against_parallel_envs, delete_env, rollout, same_bits

TOKEN = "native-stream-token"


@pytest.fixture(scope="module")
def two_servers():
    with mll.ServerProcess(threads=1) as first, mll.ServerProcess(threads=2) as second:
        yield first.address, second.address


@pytest.fixture(scope="module")
def auth_server(tmp_path_factory):
    token_file = tmp_path_factory.mktemp("token") / "token"
    token_file.write_text(TOKEN + "\n")
    with mll.ServerProcess(threads=1, extra_args=(f"--auth_token_file={token_file}",)) as process:
        yield process.address


@pytest.mark.parametrize("n_landers", [1, 3])
@pytest.mark.parametrize("servers", ["one", "two"])
def test_native_and_shared_memory_give_the_bits_of_parallel_envs_across_auto_resets(
        address, two_servers, continuous, n_landers, servers):
    # max_cycles 20 over 60 steps auto-resets every env at least twice.
    where = address if servers == "one" else list(two_servers)
    options = dict(address=where, n_landers=n_landers, continuous=continuous, max_cycles=20)
    with mll.vector_env(5, transport="native", **options) as native, \
            mll.vector_env(5, transport="shared_memory", **options) as shared:
        assert (native.transport, shared.transport) == ("native", "shared_memory")
        ours, reference = rollout(shared, 9, 60), rollout(native, 9, 60)
        assert check_against_parallel_envs(native, 9, 60) >= 10
    assert len(ours) == len(reference)
    for got, expected in zip(ours, reference):
        assert same_bits(got, expected) and got.dtype == expected.dtype


def test_auto_uses_the_native_library_and_shared_memory_with_a_local_server(address):
    with mll.vector_env(2, address=address, n_landers=1) as vector:
        assert vector.transport == "shared_memory"


def test_step_async_overlaps_two_native_vector_envs(address):
    options = dict(address=address, n_landers=2, max_cycles=30)
    with mll.vector_env(3, transport="native", **options) as first, \
            mll.vector_env(3, transport="native", **options) as second, \
            mll.vector_env(3, transport="shared_memory", **options) as reference:
        for vector in (first, second, reference):
            vector.reset(seed=4)
        rng = np.random.default_rng(2)
        for _ in range(40):
            actions = rng.integers(0, 4, size=(3, 2), dtype=np.int32)
            first.step_async(actions)
            second.step_async(actions)  # Both in flight at once.
            expected = reference.step(actions)
            for result in (first.step_wait(), second.step_wait()):
                for got, want in zip(result[:-1], expected[:-1]):
                    assert same_bits(got, want)


@pytest.mark.parametrize("transport", ["native", "shared_memory"])
def test_an_env_deleted_behind_the_vector_envs_back_is_not_found_with_its_index(address, raw_stub, transport):
    with mll.vector_env(3, address=address, n_landers=1, transport=transport) as vector:
        vector.reset(seed=0)
        delete_env(raw_stub, vector.names[1])
        with pytest.raises(mll.MLLError) as caught:
            vector.step(np.zeros((3, 1), np.int32))
        assert caught.value.code == grpc.StatusCode.NOT_FOUND
        assert caught.value.message.startswith(f"env 1 ({vector.names[1]}): ")
        assert vector.names[1] in caught.value.message.split(": ", 1)[1]  # The server's own words.
        # The stream stays usable: the other envs step on.
        raw_stub.ResetEnv(pb.ResetEnvRequest(name=vector.names[0]))
        with pytest.raises(mll.MLLError):
            vector.step(np.zeros((3, 1), np.int32))


def test_the_token_goes_with_native_steps_and_a_wrong_one_is_unauthenticated(auth_server, monkeypatch):
    monkeypatch.delenv(mll.TOKEN_ENV, raising=False)
    with mll.vector_env(2, address=auth_server, n_landers=1, token=TOKEN, transport="native") as vector:
        vector.reset(seed=3)
        observations = vector.step(np.zeros((2, 1), np.int32))[0]
        assert observations.shape == (2, 1, 12) and np.isfinite(observations).all()
    for token in ("wrong-token", ""):
        with pytest.raises(mll.MLLError) as caught:
            mll.vector_env(2, address=auth_server, n_landers=1, token=token, transport="native")
        assert caught.value.code == grpc.StatusCode.UNAUTHENTICATED
        assert "authorization" in caught.value.message and "wrong-token" not in caught.value.message


@pytest.mark.parametrize("transport", ["native", "shared_memory"])
def test_a_stopped_server_is_unavailable_naming_its_address(transport):
    server = mll.ServerProcess(threads=1)
    try:
        vector = mll.vector_env(2, address=server.address, n_landers=1, transport=transport)
        vector.reset(seed=1)
        vector.step(np.zeros((2, 1), np.int32))
        server.stop()
        for _ in range(2):  # The broken stream, then a new one that cannot connect.
            with pytest.raises(mll.MLLError) as caught:
                vector.step(np.zeros((2, 1), np.int32))
            assert caught.value.code == grpc.StatusCode.UNAVAILABLE
            assert server.address in caught.value.message
        vector.close()
    finally:
        server.stop()


@pytest.mark.parametrize("transport", ["native", "shared_memory"])
def test_transport_survives_pickling(address, transport):
    with mll.vector_env(2, address=address, n_landers=1, transport=transport) as vector:
        copy = pickle.loads(pickle.dumps(vector))
        assert copy.transport == transport
        copy.close()
    gym_env = mll.gym_vector_env(2, address=address, n_landers=1, transport=transport)
    copy = pickle.loads(pickle.dumps(gym_env))
    assert copy.vector.transport == transport
    copy.close()
    gym_env.close()


def test_a_bogus_transport_is_invalid_argument(address):
    with pytest.raises(mll.MLLError) as caught:
        mll.vector_env(2, address=address, transport="bogus")
    assert caught.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert caught.value.message == "transport is 'bogus'; allowed: 'auto', 'shared_memory', 'native'"


def test_the_grpc_transport_is_gone_and_the_error_says_what_to_use(address):
    with pytest.raises(mll.MLLError) as caught:
        mll.vector_env(2, address=address, transport="grpc")
    assert caught.value.code == grpc.StatusCode.INVALID_ARGUMENT
    message = caught.value.message
    assert message.startswith("transport is 'grpc'") and "transport='auto'" in message and "parallel_env" in message


_WITHOUT_LIBRARY = """
import json, sys
import multi_lunar_lander as mll
try:
    mll.vector_env(2, address=sys.argv[1])
except mll.MLLError as error:
    print(json.dumps([error.code.name, error.message]))
penv = mll.parallel_env(address=sys.argv[1], n_landers=1)  # Needs no library.
penv.reset(seed=0)
penv.close()
"""


def test_without_the_library_vector_env_says_how_to_get_it_and_parallel_env_works(address, tmp_path):
    missing = tmp_path / "libmll_native_stream.so"
    env = dict(os.environ, **{_native.LIBRARY_ENV: str(missing)})
    for factory in ("vector_env", "gym_vector_env"):
        script = _WITHOUT_LIBRARY.replace("mll.vector_env", f"mll.{factory}")
        result = subprocess.run([sys.executable, "-c", script, address], env=env, capture_output=True, text=True,
                                timeout=120)
        assert result.returncode == 0, result.stderr
        code, message = json.loads(result.stdout)
        assert code == "FAILED_PRECONDITION"
        assert str(missing) in message and _native.LIBRARY_ENV in message and "wheel" in message
        assert "pip install ." in message


def test_a_library_without_its_extension_beside_it_is_refused_naming_the_extension(address, tmp_path):
    # The library alone, copied where no _fast_calls extension lies: the two are built and shipped
    # together, and one without the other is refused as a missing library is.
    lonely = tmp_path / _native.LIBRARY_NAME
    shutil.copy(_native.library("vector_env")._name, lonely)
    env = dict(os.environ, **{_native.LIBRARY_ENV: str(lonely)})
    result = subprocess.run([sys.executable, "-c", _WITHOUT_LIBRARY, address], env=env, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    code, message = json.loads(result.stdout)
    assert code == "FAILED_PRECONDITION"
    assert f"{lonely}: cannot load it (no {_native.FAST_CALLS_NAME} extension" in message, message


# The parent's vector env, inherited by a forked child through memory.
_INHERITED = []


def _step_inherited_then_own(address):
    try:
        _INHERITED[0].step(np.zeros((2, 1), np.int32))
        refused = None
    except mll.MLLError as error:
        refused = (error.code.name, error.message)
    _INHERITED.clear()  # The child's copy goes without closing the parent's stream.
    gc.collect()
    own_refused = []
    for transport in ("native", "auto"):
        try:
            mll.vector_env(2, address=address, n_landers=1, transport=transport)
            own_refused.append(None)
        except mll.MLLError as error:
            own_refused.append((error.code.name, error.message))
    penv = mll.parallel_env(address=address, n_landers=1)  # Unary grpcio calls: no native library.
    penv.reset(seed=2)
    shape = penv.step({"lander_0": 0})[0]["lander_0"].shape
    penv.close()
    return refused, own_refused, shape


def test_a_forked_child_refuses_the_parents_vector_env_and_vector_envs_of_its_own(address):
    """gRPC C++ does not survive a fork: after the parent has used the native library, a forked
    child is refused its parent's vector env and vector envs of its own (saying to start workers
    with spawn or forkserver); parallel_env works there."""
    vector = mll.vector_env(2, address=address, n_landers=1, transport="native")
    vector.reset(seed=1)
    vector.step(np.zeros((2, 1), np.int32))
    _INHERITED[:] = [vector]
    with multiprocessing.get_context("fork").Pool(1) as pool:
        refused, own_refused, shape = pool.apply_async(_step_inherited_then_own, (address,)).get(timeout=60)
    _INHERITED.clear()
    assert refused[0] == "FAILED_PRECONDITION" and "forked process must make its own environments" in refused[1]
    for code, message in own_refused:
        assert code == "FAILED_PRECONDITION" and "does not survive a fork" in message and "spawn" in message
    assert shape == (12,)
    assert vector.step(np.zeros((2, 1), np.int32))[0].shape == (2, 1, 12)  # The parent's streams still work.
    vector.close()


@pytest.mark.parametrize("transport", ["native", "shared_memory"])
def test_ctrl_c_interrupts_a_step_that_waits_for_a_stalled_server(transport):
    """KeyboardInterrupt reaches a step whose server does not answer (stopped with SIGSTOP);
    once the server runs again the next step works (the interrupted one's results are dropped)."""
    import _thread
    import os
    import signal
    import threading
    import time

    # A process started in the background by a non-interactive shell inherits SIGINT ignored, and
    # then Python installs no Ctrl-C handler (interrupt_main would do nothing): install it here.
    previous_handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    server = mll.ServerProcess(threads=1)
    try:
        vector = mll.vector_env(2, address=server.address, n_landers=1, transport=transport)
        vector.reset(seed=1)
        vector.step(np.zeros((2, 1), np.int32))
        os.kill(server.pid, signal.SIGSTOP)
        # The signal is delivered asynchronously: wait until the server is stopped (state T).
        deadline = time.monotonic() + 10
        while open(f"/proc/{server.pid}/stat").read().rsplit(")", 1)[1].split()[0] != "T":
            assert time.monotonic() < deadline
            time.sleep(0.01)
        # Ctrl-C every 0.5 s, at most 10 times, until the step is interrupted: CPython may run
        # the handler inside a finalizer that runs meanwhile, which swallows that one interrupt.
        interrupted = threading.Event()

        def press_ctrl_c():
            for _ in range(10):
                if interrupted.wait(0.5):
                    return
                _thread.interrupt_main()
            if not interrupted.wait(0.5):  # Never interrupted: let the step finish, the test fail.
                os.kill(server.pid, signal.SIGCONT)

        presser = threading.Thread(target=press_ctrl_c)
        presser.start()
        started = time.monotonic()
        try:
            with pytest.raises(KeyboardInterrupt):
                vector.step(np.zeros((2, 1), np.int32))
            assert time.monotonic() - started < 5
        finally:
            interrupted.set()
            presser.join()
            os.kill(server.pid, signal.SIGCONT)
        # The interrupted step's result is lost; the env stepped or not, but steps go on.
        assert vector.step(np.zeros((2, 1), np.int32))[0].shape == (2, 1, 12)
        assert vector.transport == transport
        vector.close()
    finally:
        server.stop()
        signal.signal(signal.SIGINT, previous_handler)
