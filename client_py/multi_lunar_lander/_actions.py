"""The one check of the actions every client class accepts (AEC, parallel, vector), before
anything is sent: what is not an action of the env's action space (an unknown agent, a string,
None, a float or bool for a discrete action, the wrong shape, a ragged list) raises MLLError
INVALID_ARGUMENT naming the agent, the value and what is allowed, and nothing reaches the
server, so the env stays usable. Values of the right type (a discrete action outside 0..3, a NaN
in a continuous one) are the server's to check, against the agents still active: it answers
INVALID_ARGUMENT naming the lander, as for any client."""

from __future__ import annotations

from typing import Collection, Iterable, Sequence

import numpy as np

from ._errors import invalid_argument

# What one agent's action may be, by action type (continuous or not).
ALLOWED = {
    False: "an integer 0..3 (a Python or numpy integer; not a float, bool, string or None)",
    True: "[main, lateral]: 2 numbers (a sequence or array of shape (2,)), each clipped to [-1, 1]",
}
# numpy dtype kinds an action array may have: signed/unsigned integers, and floats if continuous.
_KINDS = {False: "iu", True: "iuf"}
_INT32 = np.iinfo(np.int32)


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _problem(array: np.ndarray | None, expected: tuple[int, ...], continuous: bool) -> str | None:
    """Why `array` (None: not convertible to a rectangular array) is not a block of actions of
    shape `expected`; None when it is."""
    if array is None:
        return "not a rectangular array of numbers"
    if array.shape != expected:
        return f"shape {array.shape}, expected {expected}"
    if array.size and array.dtype.kind not in _KINDS[continuous]:
        return f"of type {array.dtype if array.ndim else type(array.item()).__name__}"
    wide = array.dtype.itemsize > 4 or (array.dtype.kind == "u" and array.dtype.itemsize == 4)
    if not continuous and array.size and wide and (array.min() < _INT32.min or array.max() > _INT32.max):
        return "out of the 32-bit range"
    return None


def _is_plain(value, continuous: bool) -> bool:
    """The common forms of one agent's action, recognised without building an array: an int or
    numpy integer (not a bool) in the 32-bit range, or a numeric array of shape (2,)."""
    if continuous:
        return isinstance(value, np.ndarray) and value.shape == (2,) and value.dtype.kind in "iuf"
    return (type(value) is int or isinstance(value, np.integer)) and _INT32.min <= value <= _INT32.max


def _as_array(values) -> np.ndarray | None:
    try:
        return np.asarray(values)
    except (ValueError, TypeError):  # Ragged nesting, or an object numpy cannot take.
        return None


def check_actions(
    values, continuous: bool, shape_prefix: tuple[int, ...], what: str, labels: Sequence[str] | None = None
) -> np.ndarray:
    """`values` as the wire's element type (int32, or float32 with a trailing 2 when continuous)
    after checking it is a block of actions of shape `shape_prefix`. `labels` name the items of
    the first dimension when `values` holds one agent's action per item (e.g. the agents of a
    parallel step): an error then names the first bad item's agent; else it names `what`."""
    expected = tuple(shape_prefix) + ((2,) if continuous else ())
    if labels is not None:  # Item by item first: numpy would turn [True, 2] into [1, 2].
        plain = True
        for label, value in zip(labels, values):
            if _is_plain(value, continuous):
                continue
            plain = False
            item = _problem(_as_array(value), expected[1:], continuous)
            if item is not None:
                raise invalid_argument(
                    f"the action of {label} is {_short(value)}: {item}; allowed: {ALLOWED[continuous]}"
                )
        if plain and not continuous and len(values) == expected[0]:
            return np.array(values, dtype=np.int32)  # Integers already known to fit.
    array = _as_array(values)
    problem = _problem(array, expected, continuous)
    if problem is None:
        return array.astype(np.float32 if continuous else np.int32, copy=False)
    verb, per_agent = ("are", " per agent") if shape_prefix else ("is", "")
    raise invalid_argument(f"{what} {verb} {_short(values)}: {problem}; allowed{per_agent}: {ALLOWED[continuous]}")


def check_agents(keys: Iterable, possible_agents: Collection[str], active: Sequence[str]) -> None:
    """A parallel step's action keys must be agents of the env (`possible_agents`, best a dict
    or set): an unknown key (e.g. "lander_99") would otherwise be dropped silently. Keys of
    agents already done are allowed and ignored, as PettingZoo's parallel envs do."""
    unknown = [key for key in keys if key not in possible_agents]
    if unknown:
        raise invalid_argument(
            f"actions has key(s) {_short(unknown)} that are not agents of this env; allowed: "
            f"{list(possible_agents)} (active now: {list(active)})"
        )
