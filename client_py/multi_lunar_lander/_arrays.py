"""The one place where numpy arrays and the wire's `Array` message meet.

An `Array` is little-endian element bytes, row-major, with a dtype and a shape. Decoding is one
`np.frombuffer` with an explicit little-endian dtype per array (never a per-element loop); the
result is converted to the native byte order and copied, so callers get ordinary writable arrays
that do not keep the message alive.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ._errors import invalid_argument
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
