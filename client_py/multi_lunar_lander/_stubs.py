"""The generated messages and service stub (multi_lunar_lander._proto), generated on first
import when an uninstalled source checkout lacks them."""

from . import _codegen

try:
    from ._proto import multi_lunar_lander_pb2 as pb
    from ._proto import multi_lunar_lander_pb2_grpc as pb_grpc
except ImportError:  # pragma: no cover - exercised only in a never-installed checkout.
    _codegen.ensure()
    from ._proto import multi_lunar_lander_pb2 as pb
    from ._proto import multi_lunar_lander_pb2_grpc as pb_grpc

__all__ = ["pb", "pb_grpc"]
