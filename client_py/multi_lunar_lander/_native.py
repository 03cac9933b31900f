"""The native library: `libmll_native_stream.so` (client_cpp/native, built with the C++ server),
loaded with ctypes. Its C interface over the C++ client's VectorEnv (vector_c_api.h) is the
engine of every Python vector env (vector.py): placement over servers, the Session streams
(through shared memory with a server on this host), pipelined send/recv and failover are the
C++ client's code, run in the calling thread with the GIL released while it waits.

Beside the library lies its companion, the extension module _fast_calls
(client_cpp/native/fast_calls_module.c, for CPython's stable ABI): the vector env's step and recv
as one call of the interpreter each. The two are built, shipped and loaded together.

Where the library is looked for: $MLL_NATIVE_LIBRARY when set (only there); else beside this
package (the binary wheel, and `pip install .` at the repository's root, install it there; the
wheel's RPATH points at the libraries it needs in multi_lunar_lander.libs/); else a source
checkout's build tree (scripts/build.sh). `pip install ./client_py` installs no library: the
AEC and parallel envs work without it, vector envs do not. Nor can a process forked from one
that has used the library use it (gRPC C++ does not survive a fork).
"""

from __future__ import annotations

import ctypes
import importlib.machinery
import importlib.util
import os
import pathlib
import threading
import types

import grpc

from ._errors import MLLError
from ._server import checkout_build_path

LIBRARY_ENV = "MLL_NATIVE_LIBRARY"
LIBRARY_NAME = "libmll_native_stream.so"
# The vector env's per-call path, a CPython extension built and shipped beside the library.
FAST_CALLS_NAME = "_fast_calls"
# MLL_NATIVE_STREAM_PENDING: a wait ran out (vector_c_api.h); and how long each wait is, so
# that Python handles signals (Ctrl-C) between waits.
PENDING = -1
READ_SLICE_MS = 100

_lock = threading.Lock()
_loaded: tuple[ctypes.CDLL | None, str] | None = None  # (library or None, why not)
_fast_calls: types.ModuleType | None = None  # Loaded with the library.
# The process that first used the library, which started its gRPC; gRPC C++ does not survive a
# fork, so a forked child of that process cannot use the library.
_started_in: int | None = None


def library_paths() -> list[pathlib.Path]:
    """Where the library is looked for, in order."""
    from_env = os.environ.get(LIBRARY_ENV)
    if from_env:
        return [pathlib.Path(from_env)]
    return [pathlib.Path(__file__).resolve().parent / LIBRARY_NAME, checkout_build_path("client_cpp", LIBRARY_NAME)]


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    """Sets the C signatures of client_cpp/native/vector_c_api.h."""
    handle, text, size, integer = ctypes.c_void_p, ctypes.c_char_p, ctypes.c_size_t, ctypes.c_int
    data = [handle, ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(size)]

    def declare(name: str, restype, *argtypes) -> None:
        function = getattr(lib, f"mll_vector_env_{name}")
        function.restype, function.argtypes = restype, list(argtypes)

    for name in ("column_count",):
        declare(name, integer)
    for name in ("column_dtype", "column_per_agent", "column_width"):
        declare(name, integer, integer)
    declare("column_name", text, integer)
    declare(
        "new", handle, text, text, size, text, text, integer, ctypes.c_char_p, size, integer, integer, integer,
        ctypes.c_double, ctypes.c_double,
    )
    for name in (
        "create_status", "num_envs", "n_landers", "continuous", "batch_size", "failover", "failovers", "rebalances",
        "server_count", "in_flight", "rows",
    ):
        declare(name, integer, handle)
    declare("message", text, handle)
    declare("free", None, handle)
    declare("spec", integer, *data)
    for name in ("name", "env_address", "server_address"):
        declare(name, text, handle, integer)
    declare("server_info", integer, handle, integer, *data[1:])
    declare("transport", text, handle)
    declare("take_events", text, handle)
    for name in ("reset", "async_reset"):
        declare(name, integer, handle, integer, ctypes.c_uint64)
    declare("step_async", integer, handle, ctypes.c_void_p, size, integer)
    declare("step", integer, handle, ctypes.c_void_p, size, integer, integer)
    declare("send", integer, handle, ctypes.c_void_p, size, integer, ctypes.c_void_p, size)
    for name in ("step_wait", "recv"):
        declare(name, integer, handle, integer)
    declare("results", None, handle, ctypes.c_void_p)
    declare("bind_results", integer, handle, integer, ctypes.c_void_p)
    declare("bind_results_offset", integer, handle, integer, ctypes.c_void_p)
    declare("bind_event_flag", None, handle, ctypes.c_void_p)
    declare("snapshot", integer, handle, integer, *data[1:])
    declare("restore", integer, handle, integer, ctypes.c_char_p, size, ctypes.c_void_p)
    return lib


_bare: dict[int, ctypes.CDLL] = {}  # id(library) -> its bare twin.


def bare(lib: ctypes.CDLL) -> ctypes.CDLL:
    """The same library as a second ctypes.CDLL whose functions declare no argument types: a call
    passes its ctypes objects (c_void_p for pointers) and ints (C int) as they are, with none of the
    per-argument conversion of declared signatures, for the calls made on every step (each
    returns a C int)."""
    twin = _bare.get(id(lib))
    if twin is None:
        twin = _bare[id(lib)] = ctypes.CDLL(lib._name)
    return twin


def address_of(function) -> int:
    """The address of a ctypes function of the library, for _fast_calls.Call."""
    return ctypes.cast(function, ctypes.c_void_p).value


def _load_fast_calls(directory: pathlib.Path) -> types.ModuleType:
    """The extension module FAST_CALLS_NAME in `directory` (built beside the library, for this
    interpreter's stable ABI or its own); ImportError when there is none that loads."""
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = directory / (FAST_CALLS_NAME + suffix)
        if path.is_file():
            spec = importlib.util.spec_from_file_location(f"{__package__}.{FAST_CALLS_NAME}", path)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            return module
    raise ImportError(f"no {FAST_CALLS_NAME} extension for this interpreter beside it")


def _load() -> tuple[ctypes.CDLL | None, str]:
    global _loaded, _fast_calls
    with _lock:
        if _loaded is None:
            problems = []
            for path in library_paths():
                if not path.is_file():
                    problems.append(f"{path}: no such file")
                    continue
                try:
                    lib = _declare(ctypes.CDLL(str(path)))
                    _fast_calls = _load_fast_calls(path.parent)
                    _loaded = (lib, "")
                    break
                except (OSError, AttributeError, ImportError) as error:
                    problems.append(f"{path}: cannot load it ({error})")
            else:
                _loaded = (None, "; ".join(problems))
        return _loaded


def fast_calls() -> types.ModuleType:
    """The extension module of the vector env's per-call path (client_cpp/native/fast_calls_module.c),
    loaded with the library (library() first)."""
    assert _fast_calls is not None, "library() loads it"
    return _fast_calls


def _forked_from() -> int | None:
    """The process whose gRPC this one inherited by a fork, else None."""
    return _started_in if _started_in not in (None, os.getpid()) else None


def available() -> bool:
    """Whether the native library loads and can be used in this process."""
    return _load()[0] is not None and _forked_from() is None


def library(feature: str) -> ctypes.CDLL:
    """The library, marked as started by this process; FAILED_PRECONDITION naming why not and how
    to get it when `feature` (e.g. "vector_env") cannot have it."""
    global _started_in
    lib, why_not = _load()
    if lib is None:
        raise MLLError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"{feature} needs {LIBRARY_NAME}, which is not available here ({why_not}); it ships in the "
            f"binary wheel and with `pip install .` at the repository's root (a pure-Python `pip install "
            f"./client_py` has none; scripts/build.sh builds it in a clone), or set ${LIBRARY_ENV} to its "
            f"path. env() and parallel_env() work without it",
        )
    parent = _forked_from()
    if parent is not None:
        raise MLLError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"{feature} cannot use {LIBRARY_NAME} in this process: its gRPC was started by process {parent}, of "
            "which this one is a forked child, and gRPC C++ does not survive a fork; start worker processes "
            "with the 'spawn' or 'forkserver' method (multiprocessing.get_context('spawn')), or make no vector "
            "env in the parent before it forks",
        )
    _started_in = _started_in or os.getpid()
    return lib
