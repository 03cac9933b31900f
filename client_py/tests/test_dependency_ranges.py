"""The dependency ranges as declared (issue 31): both pyproject files say the same, the floors file
that scripts/dependency-ranges.sh installs is exactly their floors, the stubs' generator is pinned
for every Python and the protobuf and grpcio floors cover what its stubs need, and an upper bound
comes with a comment naming the incompatibility. Reads files only; the script is what installs
the floors and the newest and runs the client with them."""

from __future__ import annotations

import pathlib
import re
import tomllib

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

REPO = pathlib.Path(__file__).resolve().parents[2]
TOP = REPO / "pyproject.toml"
CLIENT = REPO / "client_py" / "pyproject.toml"
FLOORS = REPO / "client_py" / "constraints-floor.txt"

# Python versions the ranges must cover (requires-python's floor up to one not yet released).
PYTHONS = [f"3.{minor}" for minor in range(9, 16)]

# What the stubs each pinned grpcio-tools generates need (checked by hand on protobuf 4.21.6 to
# 7.36.2, pure Python and upb, and grpcio 1.51.1 to 1.85; docs/python.md#install): the protobuf
# version protoc writes into the stubs (from 1.63 on, also checked by them at import), and the
# grpcio version the grpc stubs check for (None: no check; they run on grpcio 1.51.1).
STUBS_NEED = {
    "1.62.3": ("4.25.1", None),
    "1.66.2": ("5.27.2", "1.66.2"),
    "1.75.1": ("6.31.1", "1.75.1"),
}


def _toml(path: pathlib.Path) -> dict:
    return tomllib.loads(path.read_text())


def test_the_client_alone_has_the_projects_version():
    """pyproject.toml takes its version from CMakeLists.txt's project(VERSION), as the programs'
    --version and GetServerInfo do; client_py/pyproject.toml, a setuptools build, writes it."""
    regex = _toml(TOP)["tool"]["scikit-build"]["metadata"]["version"]["regex"]
    project_version = re.search(regex, (REPO / "CMakeLists.txt").read_text()).group("value")
    assert _toml(CLIENT)["project"]["version"] == project_version, (
        f"client_py/pyproject.toml's version is not CMakeLists.txt's project version {project_version}"
    )


def _generator(path: pathlib.Path) -> list[str]:
    return [r for r in _toml(path)["build-system"]["requires"] if Requirement(r).name == "grpcio-tools"]


@pytest.mark.parametrize("key", ["dependencies", "optional-dependencies", "requires-python"])
def test_both_pyproject_files_declare_the_same(key):
    assert _toml(TOP)["project"][key] == _toml(CLIENT)["project"][key], (
        f"[project] {key} differs between pyproject.toml and client_py/pyproject.toml"
    )


def test_both_builds_pin_the_same_stub_generator():
    assert _generator(TOP) == _generator(CLIENT)


def _applying(requirements: list[str], name: str, python: str) -> list[Requirement]:
    environment = {"python_version": python, "python_full_version": python + ".0"}
    parsed = [Requirement(r) for r in requirements]
    return [r for r in parsed if r.name == name and (r.marker is None or r.marker.evaluate(environment))]


def _floor(requirement: Requirement) -> str:
    (floor,) = [s.version for s in requirement.specifier if s.operator in (">=", "==")]
    return floor


@pytest.mark.parametrize("python", PYTHONS)
def test_every_python_gets_one_pinned_generator_and_floors_that_cover_its_stubs(python):
    (tools,) = _applying(_generator(CLIENT), "grpcio-tools", python)
    (pin,) = tools.specifier
    assert pin.operator == "==", f"grpcio-tools is not pinned for Python {python}: {tools}"
    protobuf_needed, grpcio_needed = STUBS_NEED[pin.version]
    dependencies = _toml(CLIENT)["project"]["dependencies"]
    (protobuf,) = _applying(dependencies, "protobuf", python)
    (grpcio,) = _applying(dependencies, "grpcio", python)
    assert Version(_floor(protobuf)) >= Version(protobuf_needed), (python, protobuf)
    if grpcio_needed:
        assert Version(_floor(grpcio)) >= Version(grpcio_needed), (python, grpcio)


def _declared_floors() -> set[str]:
    project = _toml(CLIENT)["project"]
    requirements = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        requirements += extra
    floors = set()
    for text in requirements:
        requirement = Requirement(text)
        marker = f"; {requirement.marker}" if requirement.marker else ""
        floors.add(f"{requirement.name}=={_floor(requirement)}{marker}")
    return floors


def test_the_floors_file_is_exactly_the_declared_floors():
    listed = set()
    for line in FLOORS.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            requirement = Requirement(line)
            marker = f"; {requirement.marker}" if requirement.marker else ""
            listed.add(f"{requirement.name}{requirement.specifier}{marker}")
    assert listed == _declared_floors(), "client_py/constraints-floor.txt and the pyproject floors differ"


def test_every_runtime_and_extra_requirement_has_a_floor():
    for requirement in _declared_floors():
        assert "==" in requirement


def _requirement_lines(path: pathlib.Path):
    """(requirement, its line, the line above) for every quoted requirement in [project]."""
    lines = path.read_text().splitlines()
    project = _toml(path)["project"]
    declared = set(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        declared.update(extra)
    for number, line in enumerate(lines):
        for quoted in re.findall(r'"([^"]+)"', line):
            if quoted in declared:
                yield quoted, line, lines[number - 1] if number else ""


@pytest.mark.parametrize("path", [TOP, CLIENT], ids=["pyproject.toml", "client_py/pyproject.toml"])
def test_an_upper_bound_comes_with_a_comment_naming_the_incompatibility(path):
    for requirement, line, above in _requirement_lines(path):
        bounds = [s for s in Requirement(requirement).specifier if s.operator in ("<", "<=", "!=", "~=", "==")]
        if bounds:
            comment = line.partition("#")[2] or (above.strip().startswith("#") and above)
            assert comment and len(comment.strip("# ")) > 10, (
                f"{path.name}: {requirement} has an upper bound without a comment that names the "
                "known incompatibility"
            )


def test_requires_python_is_the_floor_of_the_covered_pythons():
    assert _toml(CLIENT)["project"]["requires-python"] == f">={PYTHONS[0]}"
