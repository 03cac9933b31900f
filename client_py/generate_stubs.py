"""Generates the Python stubs of the wire contract (proto/mll/v1) with grpcio-tools, at build
time only: client_py/setup.py loads this file by path (wheel and editable builds of the client
alone), and the top-level CMake build of `pip install .` runs it as a script:

    python client_py/generate_stubs.py proto client_py/multi_lunar_lander/_proto

Standalone on purpose (imports nothing from the package). The stubs are never committed.
"""

from __future__ import annotations

import os
import pathlib
import tempfile

PROTO_RELATIVE = "mll/v1/multi_lunar_lander.proto"
STUB_MODULES = ("multi_lunar_lander_pb2", "multi_lunar_lander_pb2_grpc")


def stubs_are_current(proto_root: pathlib.Path, out_dir: pathlib.Path) -> bool:
    proto = proto_root / PROTO_RELATIVE
    outputs = [out_dir / f"{name}.py" for name in STUB_MODULES]
    if not all(path.exists() for path in outputs):
        return False
    if not proto.exists():  # An installed copy without the repository: keep what is there.
        return True
    return min(path.stat().st_mtime for path in outputs) >= proto.stat().st_mtime


def generate(proto_root: pathlib.Path, out_dir: pathlib.Path) -> None:
    """Writes _proto/{multi_lunar_lander_pb2,_pb2_grpc}.py(i) and _proto/__init__.py."""
    from grpc_tools import protoc  # Only needed at build time.
    import grpc_tools

    proto = proto_root / PROTO_RELATIVE
    if not proto.exists():
        raise FileNotFoundError(
            f"cannot generate the gRPC stubs: {proto} does not exist; build the package from "
            "the repository (client_py/ beside proto/)"
        )
    well_known = pathlib.Path(grpc_tools.__file__).parent / "_proto"
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        status = protoc.main(
            [
                "grpc_tools.protoc",
                f"-I{proto_root}",
                f"-I{well_known}",
                f"--python_out={tmp}",
                f"--pyi_out={tmp}",
                f"--grpc_python_out={tmp}",
                str(proto),
            ]
        )
        if status != 0:
            raise RuntimeError(f"grpc_tools.protoc failed on {proto} with status {status}")
        generated = pathlib.Path(tmp) / pathlib.Path(PROTO_RELATIVE).parent
        for path in generated.iterdir():
            text = path.read_text()
            # protoc writes absolute imports (`from mll.v1 import ...`); the stubs live inside
            # this package, so make them relative.
            text = text.replace("from mll.v1 import ", "from . import ")
            target = out_dir / path.name
            target.write_text(text)
            os.utime(target)
    (out_dir / "__init__.py").write_text(
        '"""Generated from proto/mll/v1 by client_py/generate_stubs.py; not committed."""\n'
    )


def ensure(proto_root: pathlib.Path, out_dir: pathlib.Path) -> None:
    """Generates the stubs unless they are newer than the proto."""
    if not stubs_are_current(proto_root, out_dir):
        generate(proto_root, out_dir)


if __name__ == "__main__":
    import sys

    if len(sys.argv) != 3:
        sys.exit(f"usage: {sys.argv[0]} PROTO_ROOT OUT_DIR")
    generate(pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]))
