"""Build hook: generates the gRPC stubs from ../proto before build_py, which setuptools runs
for wheels and for editable installs alike (`pip install -e client_py`)."""

import importlib.util
import pathlib

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = pathlib.Path(__file__).resolve().parent


def _codegen():
    spec = importlib.util.spec_from_file_location(
        "_mll_codegen", HERE / "multi_lunar_lander" / "_codegen.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class BuildPyWithStubs(build_py):
    def run(self):
        _codegen().generate(HERE.parent / "proto", HERE / "multi_lunar_lander" / "_proto")
        super().run()


setup(cmdclass={"build_py": BuildPyWithStubs})
