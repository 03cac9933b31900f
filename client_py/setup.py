"""Generates the gRPC stubs from ../proto into multi_lunar_lander/_proto/ whenever setuptools
runs this file: metadata, wheel and editable builds (`pip install -e client_py`) alike. It has
to happen before setup() reads the package list, which names multi_lunar_lander._proto."""

import importlib.util
import pathlib

from setuptools import setup

HERE = pathlib.Path(__file__).resolve().parent


def _codegen():
    spec = importlib.util.spec_from_file_location("_mll_generate_stubs", HERE / "generate_stubs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_codegen().ensure(HERE.parent / "proto", HERE / "multi_lunar_lander" / "_proto")
setup()
