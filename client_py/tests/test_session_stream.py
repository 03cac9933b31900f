"""The Session streams vector_env steps on: the same bits as unary StepBatch calls of another
client on the same envs, and their end with close(), which deletes the envs."""

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb


@pytest.mark.parametrize("transport", ["native", "shared_memory"])
def test_vector_env_on_the_stream_gives_the_bits_of_unary_step_batch(address, raw_stub, transport):
    options = dict(address=address, n_landers=3, max_cycles=50, transport=transport)
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


def test_close_ends_the_stream_and_deletes_the_envs(address, raw_stub):
    vector = mll.vector_env(2, address=address, n_landers=2)
    vector.reset(seed=1)
    vector.step(np.zeros((2, 2), np.int32))
    names = vector.names
    vector.close()
    for name in names:
        with pytest.raises(grpc.RpcError) as error:
            raw_stub.GetEnv(pb.GetEnvRequest(name=name))
        assert error.value.code() == grpc.StatusCode.NOT_FOUND
