"""vector_env's result arrays come from the engine's column table (mll_vector_env_column_* of
the native library): every column the library describes reaches the caller, with the shape and
element type the table gives it, in arrays of the caller's own."""

import numpy as np

import multi_lunar_lander as mll
from multi_lunar_lander import _native, vector
from multi_lunar_lander._stubs import pb

# The wire dtypes the table may name, as numpy's.
_NUMPY = {pb.DTYPE_FLOAT32: np.float32, pb.DTYPE_UINT8: np.uint8, pb.DTYPE_INT32: np.int32}


def _table():
    """The library's column table, read here with ctypes on its own."""
    lib = _native.library("test")
    return [
        (
            lib.mll_vector_env_column_name(i).decode(),
            lib.mll_vector_env_column_dtype(i),
            bool(lib.mll_vector_env_column_per_agent(i)),
            lib.mll_vector_env_column_width(i),
        )
        for i in range(lib.mll_vector_env_column_count())
    ]


def _by_column(arrays, infos):
    """Returned arrays (step()'s first ones, in order) and infos by column name (the table's)."""
    named = dict(zip(vector._RETURNED, arrays))
    keys = {key: name for name, key in vector._INFO_KEYS.items()}
    named.update((keys.get(key, key), value) for key, value in infos.items())
    return named


def _check(named, rows, n_landers, left_out=()):
    """`named` holds every column of the table but `left_out`, shaped and typed as it says."""
    table = _table()
    assert set(named) == {name for name, *_ in table} - set(left_out)
    for name, dtype, per_agent, width in table:
        if name in left_out:
            continue
        array = named[name]
        shape = (rows,) + ((n_landers,) if per_agent else ()) + ((width,) if width > 1 else ())
        assert array.shape == shape, name
        if name in vector._FLAGS:
            assert dtype == pb.DTYPE_UINT8 and array.dtype == bool, name
        elif name == "env_ids":  # Widened to NumPy's and torch's index type.
            assert dtype == pb.DTYPE_INT32 and array.dtype == np.int64, name
        else:
            assert array.dtype == _NUMPY[dtype], name
        assert array.flags.writeable and array.flags.c_contiguous, name


def test_the_table_names_the_columns_python_returns():
    names = [name for name, *_ in _table()]
    assert names[: len(vector._RETURNED)] == list(vector._RETURNED)
    assert set(vector._FLAGS) <= set(names) and set(vector._INFO_KEYS) <= set(names)
    assert dict((name, width) for name, _, _, width in _table())["observations"] == 12


def test_every_column_reaches_the_caller_shaped_by_the_table(address):
    with mll.vector_env(3, address=address, n_landers=2, batch_size=2) as envs:
        observations, infos = envs.reset(seed=1)
        # reset returns the observations and the infos; its rows are env order (no env_id).
        _check(_by_column([observations], infos), 3, 2, ("rewards", "terminations", "truncations", "active", "env_ids"))
        envs.async_reset(seed=1)
        first = envs.recv()
        _check(_by_column(first[:-1], first[-1]), 2, 2)
        envs.send(np.zeros((2, 2), np.int32), first[-1]["env_id"])
        second = envs.recv()
        _check(_by_column(second[:-1], second[-1]), 2, 2)
        # Each call's arrays are new: the next results do not overwrite the earlier ones.
        kept = [array.copy() for array in first[:-1]]
        envs.send(np.ones((2, 2), np.int32), second[-1]["env_id"])
        envs.recv()
        assert all(np.array_equal(array, copy) for array, copy in zip(first[:-1], kept))
    with mll.vector_env(3, address=address, n_landers=2) as envs:
        envs.reset(seed=1)
        result = envs.step(np.zeros((3, 2), np.int32))
        _check(_by_column(result[:-1], result[-1]), 3, 2, ("env_ids",))
