"""The client's one exception type, and the one function that turns a gRPC error into it."""

from __future__ import annotations

import grpc


class MLLError(Exception):
    """An error reported by the Multi Lunar Lander server (or found by the client before sending).

    Attributes:
      code: a `grpc.StatusCode` (e.g. INVALID_ARGUMENT, NOT_FOUND, FAILED_PRECONDITION).
      message: the server's message, naming the field, the value and what is allowed.
    """

    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(f"{code.name}: {message}")
        self.code = code
        self.message = message

    def __reduce__(self):
        # Picklable, so an error raised in a worker process (SuperSuit, Gymnasium's AsyncVectorEnv,
        # Ray) reaches the parent as itself, with its code and message.
        return (type(self), (self.code, self.message))


def from_rpc_error(error: grpc.RpcError, context: str = "") -> MLLError:
    """The MLLError for a failed call; `context` (e.g. the address) is prepended when the server
    was not reached, since then the message comes from the transport, not the server."""
    code = error.code() if hasattr(error, "code") else grpc.StatusCode.UNKNOWN
    message = error.details() if hasattr(error, "details") else str(error)
    return from_call_status(code, message, context)


_CODES_BY_VALUE = {status.value[0]: status for status in grpc.StatusCode}


def from_call_status(code: grpc.StatusCode | int, message: str | None, context: str = "") -> MLLError:
    """The MLLError for a call that ended with `code` (a grpc.StatusCode or its number) and
    `message`; `context` is prepended to UNAVAILABLE, as in from_rpc_error."""
    if isinstance(code, int):
        code = _CODES_BY_VALUE.get(code, grpc.StatusCode.UNKNOWN)
    if code == grpc.StatusCode.UNAVAILABLE and context:
        message = f"{context}: {message}"
    return MLLError(code, message or "")


def from_item_error(code: int, message: str, context: str = "") -> MLLError:
    """The MLLError for one failed item of a batch (`ItemError`, a canonical code number)."""
    status = _CODES_BY_VALUE.get(code, grpc.StatusCode.UNKNOWN)
    return MLLError(status, f"{context}{message}")


def invalid_argument(message: str) -> MLLError:
    """A client-side check that fails the way the server's INVALID_ARGUMENT would."""
    return MLLError(grpc.StatusCode.INVALID_ARGUMENT, message)
