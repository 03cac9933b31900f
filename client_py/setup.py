"""Generates the gRPC stubs from ../proto whenever setuptools runs this file: metadata, wheel and
editable builds (`pip install -e client_py`) alike.

Into the source tree (multi_lunar_lander/_proto/) when they are missing or older than the proto:
it has to happen before setup() reads the package list, which names multi_lunar_lander._proto,
and it is what an editable install imports. A wheel build then generates them anew into the
wheel (build_py below), with this build's grpcio-tools, whatever the source tree holds: the
source tree's may come from another grpcio-tools (an editable install with
--no-build-isolation uses the environment's), and the stubs' generator decides which protobuf
and grpcio the package runs on (pyproject.toml pins it per Python version)."""

import importlib.util
import pathlib

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = pathlib.Path(__file__).resolve().parent
PROTO_ROOT = HERE.parent / "proto"


def _codegen():
    spec = importlib.util.spec_from_file_location("_mll_generate_stubs", HERE / "generate_stubs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class BuildPyWithFreshStubs(build_py):
    def run(self):
        super().run()
        # Not for editable installs (they import the source tree's), nor from an sdist without
        # ../proto (it ships the stubs it was made with).
        if not getattr(self, "editable_mode", False) and (PROTO_ROOT / _codegen().PROTO_RELATIVE).exists():
            _codegen().generate(PROTO_ROOT, pathlib.Path(self.build_lib) / "multi_lunar_lander" / "_proto")


_codegen().ensure(PROTO_ROOT, HERE / "multi_lunar_lander" / "_proto")
setup(cmdclass={"build_py": BuildPyWithFreshStubs})
