"""Sessions attached to shared memory (attach_shared_memory; vector_env transport=
"shared_memory", which "auto" tries): the same bits and errors as the stream, the server's
refusals and limits, a server that dies while a client waits, and the stream's rules once
attached."""

import os
import pickle
import time

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import _native
from multi_lunar_lander._stubs import pb, pb_grpc

from mll_test_helpers import rollout, same_bits

pytestmark = pytest.mark.skipif(
    not _native.available(),
    reason=f"{_native.LIBRARY_NAME} is not built (looked at {', '.join(map(str, _native.library_paths()))})",
)
REGION_BYTES = 4096 + 2 * (64 << 20)


@pytest.mark.parametrize("n_landers", [1, 3])
def test_shared_memory_and_grpc_give_the_same_bits_across_auto_resets(address, continuous, n_landers):
    # max_cycles 20 over 60 steps auto-resets every env at least twice.
    options = dict(address=address, n_landers=n_landers, continuous=continuous, max_cycles=20)
    with mll.vector_env(5, transport="shared_memory", **options) as shared, \
            mll.vector_env(5, transport="grpc", **options) as grpcio:
        assert (shared.transport, grpcio.transport) == ("shared_memory", "grpc")
        ours, reference = rollout(shared, 9, 60), rollout(grpcio, 9, 60)
    assert len(ours) == len(reference)
    for got, expected in zip(ours, reference):
        assert same_bits(got, expected) and got.dtype == expected.dtype


def test_errors_of_steps_are_the_streams_and_the_session_goes_on(address, raw_stub):
    with mll.vector_env(3, address=address, n_landers=1, transport="shared_memory") as vector:
        vector.reset(seed=1)
        raw_stub.DeleteEnv(pb.DeleteEnvRequest(name=vector._names[1]))
        with pytest.raises(mll.MLLError) as caught:
            vector.step(np.zeros((3, 1), np.int32))
        assert caught.value.code == grpc.StatusCode.NOT_FOUND
        assert caught.value.message.startswith(f"env 1 ({vector._names[1]}): ")
        assert vector.transport == "shared_memory"  # Still attached: an operation's error.
        with pytest.raises(mll.MLLError):
            vector.step(np.zeros((3, 1), np.int32))


def test_a_server_without_shared_memory_sessions_refuses_and_auto_uses_the_stream():
    with mll.ServerProcess(threads=1, extra_args=("--shared_memory_sessions=0",)) as server:
        with mll.vector_env(2, address=server.address, n_landers=1) as vector:
            assert vector.transport == "native"
            vector.reset(seed=1)
            assert vector.step(np.zeros((2, 1), np.int32))[0].shape == (2, 1, 12)
        with pytest.raises(mll.MLLError) as caught:
            mll.vector_env(2, address=server.address, n_landers=1, transport="shared_memory").transport
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
                if third.transport == "shared_memory" or time.monotonic() > deadline:
                    break
        assert third.transport == "shared_memory"


def test_a_server_that_dies_while_attached_is_unavailable_naming_its_address():
    server = mll.ServerProcess(threads=1)
    try:
        vector = mll.vector_env(2, address=server.address, n_landers=1, transport="shared_memory")
        vector.reset(seed=1)
        vector.step(np.zeros((2, 1), np.int32))
        server.stop()
        started = time.monotonic()
        for _ in range(2):  # The ended session, then a new stream that cannot connect.
            with pytest.raises(mll.MLLError) as caught:
                vector.step(np.zeros((2, 1), np.int32))
            assert caught.value.code == grpc.StatusCode.UNAVAILABLE
            assert server.address in caught.value.message
        assert time.monotonic() - started < 30
        vector.close()
    finally:
        server.stop()


def test_a_closed_stream_is_reopened_and_attached_again(address):
    with mll.vector_env(2, address=address, n_landers=2, transport="shared_memory") as vector, \
            mll.vector_env(2, address=address, n_landers=2, transport="grpc") as reference:
        actions = np.zeros((2, 2), np.int32)
        for env in (vector, reference):
            env.reset(seed=5)
            env.step(actions)
        vector._servers[0].stream.close()
        assert same_bits(vector.step(actions)[0], reference.step(actions)[0])
        assert vector.transport == "shared_memory"


def test_shared_memory_survives_pickling(address):
    with mll.vector_env(2, address=address, n_landers=1, transport="shared_memory") as vector:
        copy = pickle.loads(pickle.dumps(vector))
        assert copy.transport == "shared_memory"
        copy.close()


def test_the_attach_answer_names_a_sealed_region_and_the_stream_then_refuses_requests(address):
    """What the server hands out, seen from a plain grpcio Session: a /proc/<pid>/fd path of
    the announced size that cannot be shrunk, and FAILED_PRECONDITION for a request sent on the
    stream once attached (the requests belong in the region)."""
    requests = [pb.SessionRequest(sequence=1, attach_shared_memory=pb.AttachSharedMemoryRequest()),
                pb.SessionRequest(sequence=2, get_env=pb.GetEnvRequest(name="envs/0"))]
    with grpc.insecure_channel(address) as channel:
        responses = pb_grpc.MultiLunarLanderStub(channel).Session(iter(requests))
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
        refused = next(responses)
        assert refused.sequence == 2 and refused.error.code == grpc.StatusCode.FAILED_PRECONDITION.value[0]
        assert "attached to shared memory" in refused.error.message
        responses.cancel()

