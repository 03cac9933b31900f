"""The generated messages and service stub (multi_lunar_lander._proto), generated when the
package is built (`pip install ./client_py`, `pip install .`, or scripts/setup.sh's editable
install), never at import time."""

try:
    from ._proto import multi_lunar_lander_pb2 as pb
    from ._proto import multi_lunar_lander_pb2_grpc as pb_grpc
except ImportError as error:  # pragma: no cover - a source tree that was never built.
    raise ImportError(
        "multi_lunar_lander's generated gRPC stubs are missing: install the package "
        "(pip install ./client_py, or pip install . for the client with the server) rather "
        "than importing it from a source tree"
    ) from error

__all__ = ["pb", "pb_grpc"]
