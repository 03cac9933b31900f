"""Sessions attached to shared memory (attach_shared_memory; vector_env transport=
"shared_memory", which "auto" tries): step errors, the server's refusals and limits, and the
stream's rules once attached. The same bits as parallel envs and as the gRPC C++ stream, and a
server that dies while a client waits: test_native_transport.py, for both transports."""

import os
import pickle
import queue
import shutil
import subprocess
import time

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb, pb_grpc

from mll_test_helpers import same_bits


REGION_BYTES = 4096 + 2 * (64 << 20)


def test_errors_of_steps_are_the_streams_and_the_session_goes_on(address, raw_stub):
    with mll.vector_env(3, address=address, n_landers=1, transport="shared_memory") as vector:
        vector.reset(seed=1)
        raw_stub.DeleteEnv(pb.DeleteEnvRequest(name=vector.names[1]))
        with pytest.raises(mll.MLLError) as caught:
            vector.step(np.zeros((3, 1), np.int32))
        assert caught.value.code == grpc.StatusCode.NOT_FOUND
        assert caught.value.message.startswith(f"env 1 ({vector.names[1]}): ")
        assert vector.transport == "shared_memory"  # Still attached: an operation's error.
        with pytest.raises(mll.MLLError):
            vector.step(np.zeros((3, 1), np.int32))


def test_a_server_without_shared_memory_sessions_refuses_and_auto_uses_the_stream():
    with mll.ServerProcess(threads=1, extra_args=("--shared_memory_sessions=0",)) as server:
        with mll.vector_env(2, address=server.address, n_landers=1) as vector:
            assert vector.transport == "native"
            vector.reset(seed=1)
            assert vector.step(np.zeros((2, 1), np.int32))[0].shape == (2, 1, 12)
        with pytest.raises(mll.MLLError) as caught:  # At construction, not at the first step.
            mll.vector_env(2, address=server.address, n_landers=1, transport="shared_memory")
        assert caught.value.code == grpc.StatusCode.FAILED_PRECONDITION
        assert "--shared_memory_sessions=0" in caught.value.message


def test_the_session_limit_leaves_later_sessions_on_their_streams():
    with mll.ServerProcess(threads=1, extra_args=("--shared_memory_sessions=1",)) as server:
        with mll.vector_env(1, address=server.address, n_landers=1) as first, \
                mll.vector_env(1, address=server.address, n_landers=1) as second:
            assert (first.transport, second.transport) == ("shared_memory", "native")
        # The first session's slot is free again once it ended.
        deadline = time.monotonic() + 10
        while True:
            with mll.vector_env(1, address=server.address, n_landers=1) as third:
                transport = third.transport
            if transport == "shared_memory" or time.monotonic() > deadline:
                break
        assert transport == "shared_memory"


def test_shared_memory_survives_pickling(address):
    with mll.vector_env(2, address=address, n_landers=1, transport="shared_memory") as vector:
        copy = pickle.loads(pickle.dumps(vector))
        assert copy.transport == "shared_memory"
        copy.close()


def test_the_attach_answer_names_a_sealed_region_and_the_stream_then_refuses_requests(address):
    """What the server hands out, seen from a plain grpcio Session: a /proc/<pid>/fd path of
    the announced size that cannot be shrunk, and FAILED_PRECONDITION for a request sent on the
    stream once attached (the requests belong in the region)."""
    requests = queue.SimpleQueue()  # Open until None: the session (and its region) lives on.
    requests.put(pb.SessionRequest(sequence=1, attach_shared_memory=pb.AttachSharedMemoryRequest()))
    with grpc.insecure_channel(address) as channel:
        responses = pb_grpc.MultiLunarLanderStub(channel).Session(iter(requests.get, None))
        attached = next(responses)
        region = attached.attach_shared_memory
        assert not attached.HasField("error") and region.size == REGION_BYTES
        assert region.path.startswith("/proc/") and "/fd/" in region.path
        descriptor = os.open(region.path, os.O_RDWR)
        try:
            assert os.fstat(descriptor).st_size == REGION_BYTES
            with pytest.raises(OSError):  # Sealed: a client cannot shrink it under the server.
                os.ftruncate(descriptor, 4096)
            header = os.pread(descriptor, 24, 0)
            assert header[:4] == b"MLL1" and int.from_bytes(header[16:24], "little") == region.nonce
        finally:
            os.close(descriptor)
        requests.put(pb.SessionRequest(sequence=2, get_env=pb.GetEnvRequest(name="envs/0")))
        refused = next(responses)
        assert refused.sequence == 2 and refused.error.code == grpc.StatusCode.FAILED_PRECONDITION.value[0]
        assert "attached to shared memory" in refused.error.message
        requests.put(None)
        responses.cancel()



@pytest.fixture(scope="module")
def server_in_another_pid_namespace(tmp_path_factory):
    """A real mll_server in a PID namespace of its own, as in another container: the
    /proc/<pid>/fd path of its region names another process's file here."""
    if shutil.which("unshare") is None or subprocess.run(
        ["unshare", "--pid", "--fork", "--mount-proc", "true"], capture_output=True
    ).returncode:
        pytest.skip("unshare --pid --mount-proc is not permitted here (needs root or user namespaces)")
    wrapper = tmp_path_factory.mktemp("namespace") / "mll_server_in_namespace"
    # --parent_pid is dropped: the test's pid means nothing inside the namespace (unshare's
    # --kill-child ends the server with the wrapper instead).
    wrapper.write_text(
        "#!/bin/bash\n"
        'args=(); for arg in "$@"; do [[ $arg == --parent_pid=* ]] || args+=("$arg"); done\n'
        "exec unshare --pid --fork --mount-proc --kill-child=SIGTERM "
        f'{mll.find_server_binary()} "${{args[@]}}"\n'
    )
    wrapper.chmod(0o755)
    with mll.ServerProcess(binary=str(wrapper), threads=1) as server:
        yield server.address


def test_a_region_that_cannot_be_mapped_here_leaves_auto_on_a_new_stream(address, server_in_another_pid_namespace):
    elsewhere = server_in_another_pid_namespace
    with mll.vector_env(3, address=address, n_landers=2, transport="shared_memory") as reference, \
            mll.vector_env(3, address=elsewhere, n_landers=2) as vector:
        for env in (vector, reference):
            env.reset(seed=8)
        actions = np.ones((3, 2), np.int32)
        for _ in range(5):
            assert same_bits(vector.step(actions)[0], reference.step(actions)[0])
        assert vector.transport == "native"
    with pytest.raises(mll.MLLError) as caught:
        mll.vector_env(1, address=elsewhere, n_landers=1, transport="shared_memory")
    assert caught.value.code == grpc.StatusCode.FAILED_PRECONDITION
    assert "is not this session's region here" in caught.value.message
