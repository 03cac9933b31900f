"""How vector_env hands out results and takes actions: the engine writes each call's results in
place into buffers the adapter owns (mll_vector_env_bind_results); with copy=True (the default)
every call returns arrays of the caller's own, with copy=False the adapter's arrays, overwritten
by the next call of the same shape. Actions of the wire's type are taken as they are, any other
form is converted; the same bits either way."""

import gc
import pickle
import weakref

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from mll_test_helpers import random_actions, same_bits


def _arrays(result) -> list[np.ndarray]:
    """A call's result (arrays, then the infos dict) as copies of its arrays, infos by key."""
    *arrays, infos = result
    return [array.copy() for array in arrays] + [infos[key].copy() for key in sorted(infos)]


def _same(got: list, expected: list) -> bool:
    """Lists of results (each as _arrays gives it) equal bit for bit."""
    return len(got) == len(expected) and all(
        len(a) == len(b) and all(same_bits(x, y) for x, y in zip(a, b)) for a, b in zip(got, expected)
    )


def _rollout(vector, actions):
    """reset's and each step's results, for comparison."""
    return [_arrays(vector.reset(seed=5))] + [_arrays(vector.step(block)) for block in actions]


def test_copy_false_reuses_its_arrays_with_the_same_bits_as_copy_true(address, continuous):
    options = dict(n_landers=2, continuous=continuous, max_cycles=15)  # Auto-resets within the run.
    rng = np.random.default_rng(3)
    actions = [random_actions(rng, (4, 2), continuous) for _ in range(40)]
    with mll.vector_env(4, address=address, **options) as fresh, mll.vector_env(
        4, address=address, copy=False, **options
    ) as reused:
        assert _same(_rollout(fresh, actions), _rollout(reused, actions))
        first = reused.step(actions[0])
        second = reused.step(actions[1])
        # The same arrays, now holding the second step's results; the infos dict is new each call.
        assert all(a is b for a, b in zip(first[:5], second[:5]))
        assert all(first[5][key] is second[5][key] for key in first[5]) and first[5] is not second[5]
        kept = fresh.step(actions[0])
        again = fresh.step(actions[1])
        assert not any(np.shares_memory(a, b) for a, b in zip(kept[:5], again[:5]))
        assert not any(np.shares_memory(kept[5][key], again[5][key]) for key in kept[5])


def _block_of(array: np.ndarray) -> np.ndarray:
    """The allocation an array of results is a view of (through arrays and memoryviews)."""
    while True:
        if isinstance(array, np.ndarray) and array.base is not None:
            array = array.base
        elif isinstance(array, memoryview):
            array = array.obj
        else:
            return array


def test_copy_true_results_stay_the_callers_across_blocks_and_blocks_are_freed(address):
    """copy=True hands out each call's results from a block of records made beforehand: across
    several blocks, no call's arrays are written by a later call (sync steps, and recv's batches),
    and a block no array refers to any more is freed."""
    rng = np.random.default_rng(12)
    actions = random_actions(rng, (4, 1), False)
    with mll.vector_env(4, address=address, n_landers=1, max_cycles=20) as vector:
        kept = [vector.reset(seed=3)]
        taken = [_arrays(kept[0])]
        for _ in range(150):  # More than two blocks of 64 records.
            kept.append(vector.step(actions))
            taken.append(_arrays(kept[-1]))
        assert _same([_arrays(result) for result in kept], taken)
        blocks = {id(_block_of(result[0])) for result in kept}
        assert len(blocks) >= 3
        assert not np.shares_memory(kept[0][0], kept[1][0])  # reset's observations, then a step's.
        for before, after in zip(kept[1:], kept[2:]):
            assert not any(np.shares_memory(a, b) for a, b in zip(before[:5], after[:5]))
            assert before[5] is not after[5]
        first_block = weakref.ref(_block_of(kept[0][0]))
        del kept, taken
        gc.collect()
        assert first_block() is None
    with mll.vector_env(4, address=address, n_landers=1, batch_size=2, max_cycles=20) as vector:
        vector.async_reset(seed=7)
        kept, taken = [], []
        for _ in range(140):
            result = vector.recv()
            kept.append(result)
            taken.append(_arrays(result))
            vector.send(np.zeros((2, 1), np.int32), result[5]["env_id"])
        assert _same([_arrays(result) for result in kept], taken)


@pytest.mark.parametrize("copy", [True, False])
def test_a_closed_vector_env_frees_its_results_without_the_cycle_collector(address, copy):
    """Nothing of a vector env's results refers back to it: dropped, its blocks go at once."""
    gc.collect()
    gc.disable()
    try:
        vector = mll.vector_env(4, address=address, n_landers=1, copy=copy)
        vector.reset(seed=1)
        vector.step(np.zeros((4, 1), np.int32))
        results = [weakref.ref(results) for results in vector._results_of.values()]
        vector.close()
        del vector
        assert all(ref() is None for ref in results)
    finally:
        gc.enable()


def test_copy_true_reuses_the_memory_of_results_nothing_refers_to_and_only_that(address):
    """A call's arrays are written again only once nothing of the caller's refers to them: results
    dropped at once are written again within a few calls; one array of a step kept alone, in a
    variable, as a view of a view, a memoryview, a tensor sharing its memory or an infos array, is
    never written."""
    torch = pytest.importorskip("torch")
    holds = {
        "observations": lambda result: result[0],
        "view of a view": lambda result: result[1][1:].reshape(-1)[::2],
        "memoryview": lambda result: memoryview(result[2]),
        "tensor": lambda result: torch.from_numpy(result[4]),
        "infos array": lambda result: result[5]["episode_return"],
    }
    rng = np.random.default_rng(21)
    table = [random_actions(rng, (3, 2), False) for _ in range(60)]
    with mll.vector_env(3, address=address, n_landers=2, max_cycles=12) as vector:
        vector.reset(seed=2)
        kept, expected = {}, {}
        for name, hold in holds.items():  # Each from a step of its own, the rest of it dropped.
            kept[name] = hold(vector.step(table[len(kept)]))
            expected[name] = np.array(kept[name], copy=True)
        blocks = set()
        for actions in table[len(kept):]:
            latest = vector.step(actions)  # The previous step's results dropped here.
            blocks.add(id(_block_of(latest[0])))  # The vector env holds its blocks: ids stay theirs.
        for name, value in kept.items():
            assert same_bits(np.asarray(value), expected[name]), name
        # Dropped results' memory was used again: 55 steps in one block of 4 records.
        assert len(blocks) == 1


def test_copy_true_without_exact_reference_counts_makes_new_arrays_every_call(address, monkeypatch):
    """Where reference counts are not exact (a free-threaded build), every call's results go into a
    new record: no two calls share memory, with the same bits."""
    from multi_lunar_lander import vector as vector_module

    monkeypatch.setattr(vector_module, "_COUNTS_ARE_EXACT", False)
    rng = np.random.default_rng(5)
    table = [random_actions(rng, (2, 1), False) for _ in range(10)]
    with mll.vector_env(2, address=address, n_landers=1) as fresh, mll.vector_env(
        2, address=address, n_landers=1, copy=False
    ) as reused:
        assert _same(_rollout(fresh, table), _rollout(reused, table))
        results = [fresh.step(actions) for actions in table]
        for before, after in zip(results, results[1:]):
            assert not any(np.shares_memory(a, b) for a, b in zip(before[:5], after[:5]))


def test_copy_false_recv_reuses_its_batch_arrays(address):
    with mll.vector_env(4, address=address, n_landers=1, batch_size=2, copy=False) as vector:
        vector.async_reset(seed=2)
        first = vector.recv()
        ids = first[5]["env_id"].copy()
        assert ids.dtype == np.int64
        vector.send(np.zeros((2, 1), np.int32), ids)
        second = vector.recv()
        assert first[0] is second[0] and sorted(np.concatenate([ids, second[5]["env_id"]])) == [0, 1, 2, 3]


def test_actions_in_any_accepted_form_give_the_same_bits(address, continuous):
    """An array of the wire's type and shape is taken as it is; lists, other integer or float
    types and non-contiguous views are converted; the caller's array is neither changed nor kept
    (changing it between step_async and step_wait changes nothing)."""
    rng = np.random.default_rng(8)
    blocks = [random_actions(rng, (3, 2), continuous).astype(np.float32 if continuous else np.int32)
              for _ in range(12)]
    forms = [
        lambda block: block,
        lambda block: block.tolist(),
        lambda block: block.astype(np.float64 if continuous else np.int64),
        lambda block: np.asfortranarray(block),
        lambda block: np.repeat(block, 2, axis=0)[::2],  # A strided view.
    ]
    results = []
    for form in forms:
        with mll.vector_env(3, address=address, n_landers=2, continuous=continuous) as vector:
            vector.reset(seed=9)
            out = []
            for block in blocks:
                given = form(block)
                before = np.array(given, copy=True)
                out.append(_arrays(vector.step(given)))
                assert np.array_equal(np.asarray(given), before)  # Not written to.
            results.append(out)
    for other in results[1:]:
        assert _same(results[0], other)
    with mll.vector_env(3, address=address, n_landers=2, continuous=continuous) as vector:
        vector.reset(seed=9)
        block = blocks[0].copy()
        vector.step_async(block)
        block[...] = blocks[1]  # Too late to change the step in flight.
        assert _same([_arrays(vector.step_wait())], results[0][:1])


def test_bad_arguments_get_clear_errors(address):
    with pytest.raises(mll.MLLError) as error:
        mll.vector_env(2, address=address, copy="no")
    assert error.value.code == grpc.StatusCode.INVALID_ARGUMENT and "copy is 'no'" in error.value.message
    with mll.vector_env(2, address=address, n_landers=1, copy=False) as vector:
        vector.reset(seed=0)
        with pytest.raises(mll.MLLError) as error:
            vector.step(np.zeros((2, 1), np.float32))  # Discrete envs: floats refused, nothing sent.
        assert error.value.code == grpc.StatusCode.INVALID_ARGUMENT
        # The library refuses a binding for a row count the handle never returns.
        lib = vector._lib
        assert lib.mll_vector_env_bind_results(vector._handle, 3, None) == grpc.StatusCode.INVALID_ARGUMENT.value[0]
        assert "rows is 3; allowed: num_envs = 2 or batch_size = 2" in lib.mll_vector_env_message(
            vector._handle
        ).decode()
        copy = pickle.loads(pickle.dumps(vector))  # Unpickles with copy=False too.
        try:
            copy.reset(seed=0)
            assert copy.step(np.zeros((2, 1), np.int32))[0] is copy.step(np.zeros((2, 1), np.int32))[0]
        finally:
            copy.close()


def test_env_ids_in_any_integer_form_give_the_same_bits(address):
    """send() takes recv's int64 env_id as it is, other integer arrays and lists converted; an index
    beyond any int is refused in Python's words, not wrapped onto a valid env."""
    forms = [
        lambda ids: ids,
        lambda ids: ids.astype(np.int32),
        lambda ids: ids.astype(np.uint8),
        lambda ids: ids.tolist(),
    ]
    rng = np.random.default_rng(4)
    table = rng.integers(0, 4, size=(20, 2, 1), dtype=np.int32)
    runs = []
    for form in forms:
        with mll.vector_env(4, address=address, n_landers=1, batch_size=2) as vector:
            vector.async_reset(seed=6)
            out = []
            for actions in table:
                result = vector.recv()
                out.append(_arrays(result))
                vector.send(actions, form(result[5]["env_id"]))
            runs.append(out)
    for other in runs[1:]:
        assert _same(runs[0], other)
    with mll.vector_env(4, address=address, n_landers=1, batch_size=2) as vector:
        vector.async_reset(seed=6)
        vector.recv()
        for bad in (np.array([0, 2**32 + 2], np.int64), np.array([2**64 - 1, 1], np.uint64)):
            with pytest.raises(mll.MLLError) as error:
                vector.send(np.zeros((2, 1), np.int32), bad)
            assert error.value.code == grpc.StatusCode.INVALID_ARGUMENT
            assert f"env_id holds {bad.max() if bad.dtype == np.uint64 else bad[1]}; allowed: 0..3" in error.value.message


_INHERITED = []  # The parent's vector env, inherited by a forked child through memory.


def _use_inherited():
    """In a forked child: each call of the parent's vector env, refused before it reaches the library."""
    vector = _INHERITED[0]
    refused = []
    for call in (lambda: vector.step(np.zeros((2, 1), np.int32)), lambda: vector.send(np.zeros((2, 1), np.int32),
                 np.arange(2)), vector.recv):
        try:
            call()
            refused.append(None)
        except mll.MLLError as error:
            refused.append((error.code.name, error.message))
    return refused


def test_a_forked_child_cannot_step_the_parents_vector_env(address):
    """step, send and recv look up nothing per call to know their process: a fork turns their
    one-call paths off in the child, which then refuses them as every other call."""
    import multiprocessing

    with mll.vector_env(2, address=address, n_landers=1) as vector:
        vector.reset(seed=1)
        _INHERITED[:] = [vector]
        try:
            with multiprocessing.get_context("fork").Pool(1) as pool:
                refused = pool.apply_async(_use_inherited).get(timeout=60)
        finally:
            _INHERITED.clear()
        for code, message in refused:
            assert code == "FAILED_PRECONDITION" and "forked process must make its own environments" in message
        assert vector.step(np.zeros((2, 1), np.int32))[0].shape == (2, 1, 12)  # The parent's still steps.
