"""The one place where numpy arrays and the wire's `Array` message meet.

An `Array` is little-endian element bytes, row-major, with a dtype and a shape. Decoding is one
`np.frombuffer` with an explicit little-endian dtype per array (never a per-element loop); the
result is converted to the native byte order and copied, so callers get ordinary writable arrays
that do not keep the message alive.
"""

from __future__ import annotations

import math
from typing import Sequence

import grpc
import numpy as np

from ._errors import MLLError, invalid_argument
from ._stubs import pb

# Wire dtype -> little-endian numpy dtype.
_WIRE_TO_NUMPY = {
    pb.DTYPE_FLOAT32: np.dtype("<f4"),
    pb.DTYPE_UINT8: np.dtype("<u1"),
    pb.DTYPE_INT32: np.dtype("<i4"),
}
_WIRE_TO_NATIVE = {wire: dtype.newbyteorder("=") for wire, dtype in _WIRE_TO_NUMPY.items()}


def wire_dtype_to_numpy(dtype: int) -> np.dtype:
    """The native-order numpy dtype of a wire DType."""
    try:
        return _WIRE_TO_NATIVE[dtype]
    except KeyError:
        raise invalid_argument(
            f"Array.dtype is {pb.DType.Name(dtype) if dtype in pb.DType.values() else dtype}; "
            "expected one of DTYPE_FLOAT32, DTYPE_UINT8, DTYPE_INT32"
        ) from None


def from_bytes(data: bytes, dtype: int, shape: Sequence[int], as_dtype=None) -> np.ndarray:
    """Decodes little-endian bytes of a wire dtype into a writable array of `shape`, of the native
    dtype (or `as_dtype`, e.g. bool for 0/1 flags: one conversion, not two)."""
    little = _WIRE_TO_NUMPY.get(dtype)
    if little is None:
        wire_dtype_to_numpy(dtype)  # Raises the error naming the dtype.
    shape = tuple(shape)
    if len(data) != math.prod(shape) * little.itemsize:
        raise invalid_argument(
            f"Array.data has {len(data)} bytes; shape {list(shape)} of "
            f"{pb.DType.Name(dtype)} needs {math.prod(shape) * little.itemsize}"
        )
    return np.frombuffer(data, dtype=little).astype(as_dtype or _WIRE_TO_NATIVE[dtype]).reshape(shape)


def to_list(array: "pb.Array") -> list:
    """Decodes one `Array` message straight into a (nested) list of Python numbers."""
    little = _WIRE_TO_NUMPY.get(array.dtype)
    if little is None or len(array.data) != math.prod(array.shape) * little.itemsize:
        return to_numpy(array).tolist()  # Raises the error naming the dtype or the sizes.
    return np.frombuffer(array.data, dtype=little).reshape(tuple(array.shape)).tolist()


def to_numpy(array: "pb.Array") -> np.ndarray:
    """Decodes one `Array` message."""
    return from_bytes(array.data, array.dtype, array.shape)


class Column:
    """A result column whose wire dtype and shape the caller knows (e.g. one field of a packed
    StepBatch): `decode` checks that the message says the same and decodes it with one
    frombuffer and one conversion, to `as_dtype` (default: the native dtype; bool for 0/1
    flags). Everything that does not change between calls is worked out once, here."""

    __slots__ = ("name", "dtype", "shape", "as_dtype", "_little", "_shape_list", "_nbytes")

    def __init__(self, name: str, dtype: int, shape: Sequence[int], as_dtype=None):
        self.name, self.dtype, self.shape = name, dtype, tuple(shape)
        self._little = _WIRE_TO_NUMPY.get(dtype) or wire_dtype_to_numpy(dtype)
        self.as_dtype = np.dtype(as_dtype or _WIRE_TO_NATIVE[dtype])
        self._shape_list = list(self.shape)
        self._nbytes = math.prod(self.shape) * self._little.itemsize

    def decode(self, array: "pb.Array") -> np.ndarray:
        data = array.data
        if array.dtype != self.dtype or len(data) != self._nbytes or array.shape != self._shape_list:
            dtype = pb.DType.Name(array.dtype) if array.dtype in pb.DType.values() else array.dtype
            raise MLLError(
                grpc.StatusCode.INTERNAL,
                f"{self.name} arrived as {dtype} {list(array.shape)} in {len(data)} bytes; expected "
                f"{pb.DType.Name(self.dtype)} {self._shape_list} in {self._nbytes} bytes",
            )
        return np.frombuffer(data, self._little).astype(self.as_dtype).reshape(self.shape)


def to_proto(values, dtype: int, out: "pb.Array | None" = None) -> "pb.Array":
    """Encodes `values` (anything np.asarray accepts) as an `Array` of the wire dtype `dtype`.

    Fills `out` in place when given (e.g. a field of a request), else returns a new message.
    Values are cast to the wire dtype; casting that changes a value (e.g. 2.5 -> int32) is an
    INVALID_ARGUMENT error rather than a silent truncation.
    """
    little = _WIRE_TO_NUMPY.get(dtype)
    if little is None:
        wire_dtype_to_numpy(dtype)
    source = np.asarray(values)
    converted = source.astype(little, copy=False)
    if source.dtype.kind in "fc" and little.kind in "iu":
        finite = np.isfinite(source)
        if not finite.all() or not np.array_equal(converted, source):
            raise invalid_argument(
                f"actions: {source.ravel()[:8].tolist()} cannot be encoded as "
                f"{pb.DType.Name(dtype)} without changing a value; discrete actions are integers"
            )
    if out is None:
        out = pb.Array()
    out.dtype = dtype
    del out.shape[:]
    out.shape.extend(converted.shape)
    out.data = np.ascontiguousarray(converted).tobytes()
    return out


def stack_bytes(chunks: Sequence[bytes], dtype: int, shape: Sequence[int], as_dtype=None) -> np.ndarray:
    """Decodes many same-shaped arrays' bytes (e.g. one field of every env of a batch) with one
    join and one frombuffer; `shape` is the shape of the stacked result."""
    return from_bytes(b"".join(chunks), dtype, shape, as_dtype)


def to_rows(values: np.ndarray, dtype: int) -> np.ndarray:
    """A copy of `values` as the little-endian bytes of the wire dtype `dtype`, one uint8 row per
    item of the first dimension (e.g. each env's actions)."""
    return np.array(values, dtype=_WIRE_TO_NUMPY[dtype]).view(np.uint8).reshape(len(values), -1)
