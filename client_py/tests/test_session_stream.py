"""SessionStream, the grpcio Session stream vector_env steps on with transport="grpc": the same
bits as unary StepBatch calls, errors that leave the stream usable, and a broken stream replaced
by the next step."""

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander._remote import Connection, SessionStream
from multi_lunar_lander._stubs import pb


def test_vector_env_on_the_stream_gives_the_bits_of_unary_step_batch(address, raw_stub):
    options = dict(address=address, n_landers=3, max_cycles=50, transport="grpc")
    with mll.vector_env(4, **options) as streamed, mll.vector_env(4, **options) as unary:
        np.testing.assert_array_equal(streamed.reset(seed=11)[0], unary.reset(seed=11)[0])
        request = pb.StepBatchRequest()
        request.packed.names.extend(unary.names)
        request.packed.actions.dtype = pb.DTYPE_INT32
        request.packed.actions.shape.extend((4, 3))
        rng = np.random.default_rng(3)
        resets = 0
        for _ in range(150):
            actions = rng.integers(0, 4, size=(4, 3), dtype=np.int32)
            observations, rewards, terminations, _, _, infos = streamed.step(actions)
            request.packed.actions.data = actions.astype("<i4").tobytes()
            packed = raw_stub.StepBatch(request).packed
            assert not packed.errors
            np.testing.assert_array_equal(
                observations, np.frombuffer(packed.observations.data, "<f4").reshape(4, 3, 12))
            np.testing.assert_array_equal(rewards, np.frombuffer(packed.rewards.data, "<f4").reshape(4, 3))
            np.testing.assert_array_equal(
                terminations, np.frombuffer(packed.terminations.data, np.uint8).reshape(4, 3).astype(bool))
            np.testing.assert_array_equal(
                infos["auto_reset"], np.frombuffer(packed.auto_reset.data, np.uint8).astype(bool))
            resets += int(infos["auto_reset"].sum())
        assert resets >= 4  # The comparison went through auto-resets.


def test_an_operation_error_leaves_the_stream_usable(address, raw_stub):
    env = raw_stub.CreateEnv(pb.CreateEnvRequest(config=pb.EnvConfig(n_landers=2)))
    connection = Connection(address)
    stream = SessionStream(connection)
    try:
        missing = pb.SessionRequest(get_env=pb.GetEnvRequest(name="envs/no-such-env"))
        stream.send(missing)
        with pytest.raises(mll.MLLError) as error:
            stream.receive()
        assert error.value.code == grpc.StatusCode.NOT_FOUND and "envs/no-such-env" in error.value.message
        stream.send(pb.SessionRequest(get_env=pb.GetEnvRequest(name=env.name)))
        answer = stream.receive()
        assert answer.sequence == 2 and answer.env.name == env.name
    finally:
        stream.close()
        connection.close()
        raw_stub.DeleteEnv(pb.DeleteEnvRequest(name=env.name))


def test_a_broken_stream_fails_one_step_and_the_next_step_opens_a_new_one(address):
    with mll.vector_env(2, address=address, n_landers=2, transport="grpc") as vector:
        vector.reset(seed=5)
        actions = np.zeros((2, 2), np.int32)
        vector.step(actions)
        stream = vector._servers[0].stream
        stream._responses.cancel()  # As a connection that breaks between two steps.
        with pytest.raises(mll.MLLError) as error:
            vector.step(actions)
        assert error.value.code == grpc.StatusCode.CANCELLED
        observations = vector.step(actions)[0]
        assert observations.shape == (2, 2, 12) and np.isfinite(observations).all()
        assert vector.step(actions)[0].shape == (2, 2, 12)


def test_close_ends_the_stream_and_deletes_the_envs(address, raw_stub):
    vector = mll.vector_env(2, address=address, n_landers=2, transport="grpc")
    vector.reset(seed=1)
    vector.step(np.zeros((2, 2), np.int32))
    names = vector.names
    vector.close()
    assert vector._servers[0].stream._responses is None
    for name in names:
        with pytest.raises(grpc.RpcError) as error:
            raw_stub.GetEnv(pb.GetEnvRequest(name=name))
        assert error.value.code() == grpc.StatusCode.NOT_FOUND
