"""The numpy <-> proto Array conversion (no server needed)."""

import grpc
import numpy as np
import pytest

from multi_lunar_lander import MLLError, _arrays
from multi_lunar_lander._stubs import pb


@pytest.mark.parametrize(
    "wire, values",
    [
        (pb.DTYPE_FLOAT32, np.arange(36, dtype=np.float32).reshape(3, 12) * -1.25),
        (pb.DTYPE_UINT8, np.array([0, 1, 255], dtype=np.uint8)),
        (pb.DTYPE_INT32, np.array([[-(2**31), 7], [3, 2**31 - 1]], dtype=np.int32)),
    ],
)
def test_round_trip_keeps_values_shape_and_dtype(wire, values):
    message = _arrays.to_proto(values, wire)
    assert list(message.shape) == list(values.shape)
    decoded = _arrays.to_numpy(pb.Array.FromString(message.SerializeToString()))
    assert decoded.dtype == values.dtype and decoded.shape == values.shape
    np.testing.assert_array_equal(decoded, values)
    decoded[...] = 0  # Writable, and not a view of the message.
    assert _arrays.to_numpy(message).tolist() == values.tolist()


def test_bytes_are_little_endian_whatever_the_input_byte_order():
    big = np.array([1.5, -2.0], dtype=">f4")
    message = _arrays.to_proto(big, pb.DTYPE_FLOAT32)
    assert message.data == np.array([1.5, -2.0], dtype="<f4").tobytes()
    assert _arrays.from_bytes(b"\x01\x00\x00\x00\x00\x01\x00\x00", pb.DTYPE_INT32, [2]).tolist() == [1, 256]


def test_size_mismatch_is_an_invalid_argument_naming_sizes():
    with pytest.raises(MLLError) as caught:
        _arrays.from_bytes(b"\x00" * 10, pb.DTYPE_FLOAT32, [3])
    assert caught.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert "10 bytes" in caught.value.message and "needs 12" in caught.value.message


def test_unknown_dtype_is_rejected():
    with pytest.raises(MLLError, match="DTYPE_UNSPECIFIED"):
        _arrays.from_bytes(b"", pb.DTYPE_UNSPECIFIED, [0])


def test_non_integral_values_are_not_truncated_into_int32():
    with pytest.raises(MLLError) as caught:
        _arrays.to_proto(np.array([1.0, 2.5]), pb.DTYPE_INT32)
    assert caught.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert _arrays.to_numpy(_arrays.to_proto(np.array([1.0, 3.0]), pb.DTYPE_INT32)).tolist() == [1, 3]
