"""The native transport of a vector env's steps: `libmll_native_stream.so` (the C interface of
the C++ client's Session stream, client_cpp/native, built with the C++ server), loaded with
ctypes, carries each StepBatch on a Session stream of gRPC C++ in the calling thread: the same
protocol code as the C++ client's. The grpcio stream it replaces hands every message between
threads; this one costs the Python side only the message's encoding and decoding (the GIL is
released while the library waits for the server). With a server on this host the library
attaches shared memory (attach_shared_memory in the proto): each message then passes through a
region both processes map, with one futex wake-up each way and no socket.

Where the library is looked for: $MLL_NATIVE_LIBRARY when set (only there); else beside this
package (`pip install .` at the repository's root installs it there); else a source checkout's
build tree (scripts/build.sh). The binary wheel (scripts/wheel.sh) has it beside the package
too, with the libraries it needs in multi_lunar_lander.libs/ (its RPATH points there).
`pip install ./client_py` installs no library: the "auto"
transport then uses grpcio. Nor does a process forked from one that has used the library (gRPC
C++ does not survive a fork): "auto" uses grpcio there too.
"""

from __future__ import annotations

import ctypes
import os
import pathlib
import threading
import weakref

import grpc

from ._errors import MLLError, from_call_status, invalid_argument
from ._remote import Connection, SessionStream
from ._server import checkout_build_path
from ._stubs import pb

LIBRARY_ENV = "MLL_NATIVE_LIBRARY"
LIBRARY_NAME = "libmll_native_stream.so"
TRANSPORTS = ("auto", "shared_memory", "native", "grpc")
# mll_native_stream_read's answer when its wait ran out (MLL_NATIVE_STREAM_PENDING), and how long
# each wait is: Python handles signals between waits.
_PENDING = -1
READ_SLICE_MS = 100

_lock = threading.Lock()
_loaded: tuple[ctypes.CDLL | None, str] | None = None  # (library or None, why not)
# The process that opened the first native stream, which started the library's gRPC; gRPC C++
# does not survive a fork, so a forked child of that process cannot use the library.
_started_in: int | None = None


def library_paths() -> list[pathlib.Path]:
    """Where the library is looked for, in order."""
    from_env = os.environ.get(LIBRARY_ENV)
    if from_env:
        return [pathlib.Path(from_env)]
    return [pathlib.Path(__file__).resolve().parent / LIBRARY_NAME, checkout_build_path("client_cpp", LIBRARY_NAME)]


# MLL_NATIVE_TRANSPORT_* of client_cpp/native/session_c_api.h, by NativeSessionStream's
# shared_memory= argument.
_SHARED_MEMORY_MODES = {"try": 0, "require": 1, "off": 2}


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    """Sets the C signatures of client_cpp/native/session_c_api.h."""
    handle, text, size = ctypes.c_void_p, ctypes.c_char_p, ctypes.c_size_t
    lib.mll_native_stream_new.restype = handle
    lib.mll_native_stream_new.argtypes = [text, text, size, text, text, ctypes.c_int]
    lib.mll_native_stream_open.restype = ctypes.c_int
    lib.mll_native_stream_open.argtypes = [handle]
    lib.mll_native_stream_write.restype = ctypes.c_int
    lib.mll_native_stream_write.argtypes = [handle, text, size]
    lib.mll_native_stream_read.restype = ctypes.c_int
    lib.mll_native_stream_read.argtypes = [
        handle,
        ctypes.POINTER(ctypes.c_void_p),
        ctypes.POINTER(size),
        ctypes.c_int,
    ]
    lib.mll_native_stream_message.restype = text
    lib.mll_native_stream_message.argtypes = [handle]
    lib.mll_native_stream_free.restype = None
    lib.mll_native_stream_free.argtypes = [handle]
    for flag in ("is_open", "shared_memory_in_use", "in_flight"):
        function = getattr(lib, f"mll_native_stream_{flag}")
        function.restype = ctypes.c_int
        function.argtypes = [handle]
    return lib


def _load() -> tuple[ctypes.CDLL | None, str]:
    global _loaded
    with _lock:
        if _loaded is None:
            problems = []
            for path in library_paths():
                if not path.is_file():
                    problems.append(f"{path}: no such file")
                    continue
                try:
                    _loaded = (_declare(ctypes.CDLL(str(path))), "")
                    break
                except (OSError, AttributeError) as error:
                    problems.append(f"{path}: cannot load it ({error})")
            else:
                _loaded = (None, "; ".join(problems))
        return _loaded


def _usable() -> tuple[ctypes.CDLL | None, str]:
    """The library if this process can use it, else None and why not."""
    lib, why_not = _load()
    if lib is not None and _started_in not in (None, os.getpid()):
        return None, (
            f"its gRPC was started by process {_started_in}, of which this one is a forked child, "
            "and gRPC C++ does not survive a fork"
        )
    return lib, why_not


def available() -> bool:
    """Whether the native library loads and can be used in this process."""
    return _usable()[0] is not None


def uses_native(transport: str) -> bool:
    """Whether a vector env with `transport=` steps over the native library: "shared_memory" and
    "native" (which must load), "grpc" (never) or "auto" (when it loads)."""
    if transport not in TRANSPORTS:
        raise invalid_argument(f"transport is {transport!r}; allowed: {', '.join(map(repr, TRANSPORTS))}")
    if transport == "grpc":
        return False
    lib, why_not = _usable()
    if lib is None and transport != "auto":
        raise MLLError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"transport={transport!r} needs {LIBRARY_NAME}, which is not available ({why_not}); it is "
            f"in the binary wheel and built with the server (scripts/build.sh in a clone, or pip "
            f"install . at its root), or "
            f"set ${LIBRARY_ENV} to its path; transport='auto' falls back to grpcio",
        )
    return lib is not None


def _close_handle(lib: ctypes.CDLL, handle: int, pid: int) -> None:
    if os.getpid() == pid:  # A forked child's copy is the parent's to close.
        lib.mll_native_stream_free(handle)


class NativeSessionStream(SessionStream):
    """SessionStream over the native library: send() starts writing the request (it does not
    wait for the server), receive() waits for the answer; the same errors, sequence numbers and
    reopening of a broken stream as SessionStream.

    shared_memory= "try": each stream it opens asks the server for shared memory and uses it
    when granted and mappable here (a server on this host, outside other containers), else goes
    on over the stream; "require": as "try", but a refusal raises FAILED_PRECONDITION with the
    reason; "off": never asks. The choice and its messages are the C++ client's
    (SessionTransport). `shared_memory_in_use` says whether the open stream passes its messages
    through it."""

    def __init__(self, connection: Connection, shared_memory: str = "off"):
        super().__init__(connection)
        self._lib = _usable()[0]
        if self._lib is None:
            uses_native("native")  # Raises, saying why.
        self._shared_memory = shared_memory
        self._handle: int | None = None
        self._send_failure: MLLError | None = None  # A stream that did not open, raised by receive().

    @property
    def shared_memory_in_use(self) -> bool:
        return self._handle is not None and bool(self._lib.mll_native_stream_shared_memory_in_use(self._handle))

    def open(self) -> None:
        """Opens the stream now, if it is not open (attaching shared memory as asked)."""
        self._connection.check_process()
        if self._handle is None:
            self._new_handle()
        code = self._lib.mll_native_stream_open(self._handle)
        if code:
            failure = self._failure(code)
            self.close()
            raise failure

    def _new_handle(self) -> None:
        global _started_in
        _started_in = _started_in or os.getpid()
        security = self._connection.security
        root = security.root_certificates
        self._handle = self._lib.mll_native_stream_new(
            self._connection.address.encode(),
            root,
            len(root or b""),
            (security.server_name or "").encode(),
            (security.token or "").encode(),
            _SHARED_MEMORY_MODES[self._shared_memory],
        )
        self._finalizer = weakref.finalize(self, _close_handle, self._lib, self._handle, os.getpid())

    def _write(self, request: "pb.SessionRequest") -> None:
        self._number(request)
        data = request.SerializeToString()
        code = self._lib.mll_native_stream_write(self._handle, data, len(data))
        if code:
            raise self._failure(code)
        self._awaited.append(request.sequence)

    def _read(self) -> "pb.SessionResponse":
        """The answer to the last write (its sequence not yet checked); the stream's failure raised. The
        library waits in slices of READ_SLICE_MS, so that Ctrl-C (KeyboardInterrupt) and other
        signals are handled while a server is slow; an interrupted read closes the stream (the
        next send opens a new one)."""
        data, size = ctypes.c_void_p(), ctypes.c_size_t()
        try:
            code = _PENDING
            while code == _PENDING:
                code = self._lib.mll_native_stream_read(
                    self._handle, ctypes.byref(data), ctypes.byref(size), READ_SLICE_MS
                )
        except BaseException:
            self.close()
            raise
        if code:
            raise self._failure(code)
        return pb.SessionResponse.FromString(ctypes.string_at(data, size.value))

    def send(self, request: "pb.SessionRequest") -> None:
        """As SessionStream.send; the request is encoded here, so the caller may change it at once."""
        self._send_failure = None
        try:
            self.open()
            self._write(request)
        except MLLError as failure:  # Raised by receive(), as a stream's failure is.
            self._send_failure = failure

    def receive(self) -> "pb.SessionResponse":
        if self._send_failure is not None:
            failure, self._send_failure = self._send_failure, None
            raise failure
        try:
            response = self._read()
        except MLLError:  # The stream broke: this request's answer is lost with it.
            if self._awaited:
                self._awaited.popleft()
            raise
        return self._answer(response)

    def _failure(self, code: int) -> MLLError:
        message = self._lib.mll_native_stream_message(self._handle).decode(errors="replace")
        return from_call_status(code, message, self._connection._what)

    def close(self) -> None:
        """Cancels the stream (idempotent); the next send() opens a new one. What was in flight is
        lost."""
        self._awaited.clear()
        self.closes += 1
        if self._handle is not None:
            self._finalizer()
            self._handle = self._finalizer = None
