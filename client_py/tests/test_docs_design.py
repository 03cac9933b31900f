"""docs/design.md's "Adding an option" and "Adding an RPC" are true: the lists they say are
declared once are, every source that expands a list is named in the design's table (so a new
place that must change with the list cannot hide), each step's files define what the step
tells you to edit there, and the copies that cannot be derived (the proto, Python's options, the
names Python calls) agree with the lists. The C++ side of the same checks is in
tests/client_cpp/single_source_test.cc and tests/service/rpc_table_test.cc; this file checks
what the document claims."""

from __future__ import annotations

import pathlib
import re
import subprocess

import pytest

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb

_REPO = pathlib.Path(__file__).resolve().parents[2]
_DOC = _REPO / "docs" / "design.md"
_ENV_SPEC = _REPO / "proto" / "include" / "mll" / "env_spec.h"
_RPC_TABLE = _REPO / "proto" / "include" / "mll" / "session_ops.h"
_CLIENT_TYPES = _REPO / "client_cpp" / "include" / "mll" / "client_types.h"
# The lists, each with the macros that expand it (the RPC table's views included).
_LISTS = {
    "environment options": ("MLL_ENV_OPTIONS",),
    "the RPCs": ("MLL_RPCS", "MLL_SESSION_OPS", "MLL_SESSION_SYNC_OPS"),
    "result columns": ("MLL_RESULT_COLUMNS",),
}
# Python config keywords that are the service's or not plain options (design.md, env_spec.h).
_NOT_LISTED = ("render_mode", "auto_reset")


def _text(path: pathlib.Path) -> str:
    return path.read_text(encoding="utf-8")


def _section(title: str) -> str:
    text = _DOC.read_text(encoding="utf-8")
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end >= 0 else len(text)]


def _table_row(idea: str) -> list[str]:
    """The cells of the design's first table's row for `idea`."""
    for line in _DOC.read_text(encoding="utf-8").splitlines():
        if line.startswith(f"| {idea} "):
            return [cell.strip() for cell in line.strip("|").split(" | ")]
    raise AssertionError(f"docs/design.md's table has no row '{idea}'")


def _named_sources(text: str) -> set[str]:
    """Repository paths of C++ sources named in code spans of `text`."""
    return set(re.findall(r"`([\w/.-]+\.(?:h|cc))`", text))


def _tracked_sources() -> list[str]:
    listed = subprocess.run(
        ["git", "ls-files", "*.h", "*.cc"], cwd=_REPO, check=True, capture_output=True, text=True
    ).stdout.split()
    return [path for path in listed if (_REPO / path).is_file()]


def _expanders(macros: tuple[str, ...]) -> set[str]:
    """Tracked sources outside tests/, bench/ and fuzz/ that expand one of the macros (a use that
    is not its #define)."""
    found = set()
    use = re.compile(r"^(?!\s*#\s*define)[^\n]*\b(?:" + "|".join(macros) + r")\(", re.MULTILINE)
    for path in _tracked_sources():
        if path.split("/")[0] in ("tests", "bench", "fuzz"):
            continue
        if use.search(re.sub(r"//[^\n]*", "", _text(_REPO / path))):
            found.add(path)
    return found


def _listed_options() -> list[str]:
    text = _text(_ENV_SPEC)
    body = text[text.index("#define MLL_ENV_OPTIONS(X)") :]
    body = body[: body.index("\n\n")]
    return re.findall(r"X\(\s*\w+\s*,\s*(\w+)\s*,", body)


def _table_rows() -> list[tuple[str, str]]:
    """(row kind, rpc) of each row of MLL_RPCS, in order."""
    text = _text(_RPC_TABLE)
    body = text[text.index("#define MLL_RPCS(") :]
    body = body[body.index("\n") : body.index("\n\n")]
    rows = []
    for kind, args in re.findall(r"\b(SESSION_OP|SESSION_BATCH_OP|NOT_A_SESSION_OP)\(([^)]*)\)", body):
        fields = [field.strip() for field in args.split(",")]
        rows.append((kind, fields[1] if kind == "NOT_A_SESSION_OP" else fields[2]))
    return rows


def test_the_lists_are_defined_where_the_design_says():
    assert "`MLL_ENV_OPTIONS` in `proto/include/mll/env_spec.h`" in _table_row("environment options")[1]
    assert "#define MLL_ENV_OPTIONS(X)" in _text(_ENV_SPEC)
    assert "`MLL_RPCS` in `proto/include/mll/session_ops.h`" in _table_row("the RPCs")[2]
    assert "#define MLL_RPCS(" in _text(_RPC_TABLE)
    sizes = _table_row("observation and action sizes")
    for constant in ("kObservationSize", "kContinuousActionSize", "kDiscreteActionCount"):
        assert f"`{constant}`" in sizes[1]
        assert re.search(rf"inline constexpr int {constant} = \d+;", _text(_ENV_SPEC)), constant


@pytest.mark.parametrize("idea", sorted(_LISTS))
def test_every_source_that_expands_a_list_is_named_in_its_row(idea):
    expanders = _expanders(_LISTS[idea])
    assert expanders, f"nothing expands {_LISTS[idea]}: the search is broken"
    named = _named_sources(" ".join(_table_row(idea)))
    assert not expanders - named, (
        f"docs/design.md's row '{idea}' does not name these sources that expand {_LISTS[idea]}: "
        f"{sorted(expanders - named)}"
    )


def test_every_option_is_in_the_proto_the_cpp_client_and_python():
    options = _listed_options()
    assert "n_landers" in options and "terminate_reward" in options
    # The proto's EnvConfig: the same fields, in the same order, each optional (unset = default).
    fields = [f for f in pb.EnvConfig.DESCRIPTOR.fields if f.name not in _NOT_LISTED]
    assert [f.name for f in fields] == options
    assert all(f.has_presence for f in fields)
    # Python reads its options from the proto.
    assert list(mll.CONFIG_OPTIONS) == options
    # The C++ client's RemoteEnvConfig has one member per option: it expands the list.
    types = _text(_CLIENT_TYPES)
    remote = types[types.index("struct RemoteEnvConfig {") :]
    remote = remote[: remote.index("\n};")]
    assert re.search(r"^\s*MLL_ENV_OPTIONS\(\w+\)", remote, re.MULTILINE)
    assert '#include "mll/env_spec.h"' in types


def test_the_cpp_client_includes_no_server_header_and_nothing_above_it():
    for path in _tracked_sources():
        if not path.startswith("client_cpp/") or path.startswith("client_cpp/tools/"):
            continue  # tools/ is mll::client_core, which links the core on purpose.
        for include in re.findall(r'^\s*#\s*include\s+"([^"]+)"', _text(_REPO / path), re.MULTILINE):
            assert not include.startswith(("mll/core/", "mll/service/")), f"{path} includes {include}"
            assert "../" not in include, f"{path} includes {include}"


def test_the_rpc_table_is_the_proto_service():
    service = pb.DESCRIPTOR.services_by_name["MultiLunarLander"]
    rows = _table_rows()
    assert [rpc for _, rpc in rows] == [method.name for method in service.methods]
    ops = pb.SessionRequest.DESCRIPTOR.oneofs_by_name["op"].fields
    session_ops = {field.name for field in ops} - {"attach_shared_memory"}
    assert sum(kind != "NOT_A_SESSION_OP" for kind, _ in rows) == len(session_ops)


def test_python_calls_rpcs_by_name_and_only_real_ones():
    service = pb.DESCRIPTOR.services_by_name["MultiLunarLander"]
    methods = {method.name for method in service.methods}
    called = {}
    for path in sorted((_REPO / "client_py" / "multi_lunar_lander").glob("*.py")):
        for name in re.findall(r"\b_?(?:call|future)\(\s*\"(\w+)\"", _text(path)):
            called.setdefault(name, path.name)
    assert {"CreateEnv", "ResetEnv", "StepAgent"} <= set(called), called
    unknown = {name: where for name, where in called.items() if name not in methods}
    assert not unknown, f"Python calls names that are no RPC of the proto's service: {unknown}"


@pytest.mark.parametrize("title", ["Adding an option", "Adding an RPC"])
def test_each_step_names_files_that_define_what_it_asks_for(title):
    steps = re.split(r"^\d+\. ", _section(title), flags=re.MULTILINE)[1:]
    assert len(steps) >= 4, f"'{title}' has no numbered steps"
    for step in steps:
        files = [path for path in re.findall(r"`([\w/.-]+\.(?:h|cc|proto|py|md))`", step) if "/" in path]
        assert files, f"a step of '{title}' names no file: {step[:80]!r}"
        for path in files:
            assert (_REPO / path).is_file(), f"'{title}' names {path}, which does not exist"
        text = "".join(_text(_REPO / path) for path in files)
        for macro in re.findall(r"`(MLL_[A-Z_]+)`", step):
            assert re.search(rf"#define {macro}\(", text), f"'{title}': {macro} is not defined in {files}"
    if title == "Adding an option":
        assert "`MLL_ENV_OPTIONS`" in steps[1] and "`proto/include/mll/env_spec.h`" in steps[1]
    else:
        assert any("`MLL_RPCS`" in step and "`proto/include/mll/session_ops.h`" in step for step in steps)
