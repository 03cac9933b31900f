"""docs/server.md's Limits table is the code's: for every row, each flag named in its "set by"
column has its default, and each constant named there (`kName` or `NAME` in the file named
beside it) its value, among the numbers of the row's value column (a number followed by MiB
counts in bytes too). The limits a server reports in GetServerInfo are checked against a real
server started with its defaults. The table itself must have every row below (_REQUIRED), so a
limit cannot leave the table unnoticed."""

from __future__ import annotations

import ast
import operator
import pathlib
import re

import pytest

import multi_lunar_lander as mll

_REPO = pathlib.Path(__file__).resolve().parents[2]
_DOC = _REPO / "docs" / "server.md"
_SERVER_FLAGS = _REPO / "server" / "service" / "mll_server_main.cc"
_MIB = 1 << 20
# Limits the table must list, by what sets them.
_REQUIRED = (
    "kMaxLanders", "--max_envs", "--max_envs_per_token", "--max_message_mb", "--idle_timeout_s",
    "kMaxReclaimedNames", "kMaxKeepAliveNames", "kMaxPageSize", "--shared_memory_sessions", "kCapacity",
    "MAX_RECORD_STEPS", "kMaxRecordSteps", "kMaxVectorEnvs", "kMaxViewers", "kMaxUnixPathBytes",
    "kMaxShutdownGraceS", "kMaxHandle", "kMaxDeclaredEnvs",
)


def _rows() -> list[list[str]]:
    text = _DOC.read_text(encoding="utf-8")
    assert "\n## Limits\n" in text, "docs/server.md has no Limits section"
    section = text[text.index("\n## Limits\n") + 1:]
    section = section[: section.index("\n## ")]
    rows = []
    for line in section.split("\n"):
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if line.startswith("|") and len(cells) == 4 and cells[0] not in ("limit",) and not set(cells[0]) <= set("-"):
            rows.append(cells)
    return rows


def _numbers(cell: str) -> set[float]:
    """The numbers of a value cell (1,000 and 2,047 as one number each); n MiB also as bytes."""
    found = set()
    for match in re.finditer(r"(\d[\d,]*(?:\.\d+)?)(\s*MiB)?", cell):
        number = float(match.group(1).replace(",", ""))
        found.add(number)
        if match.group(2):
            found.add(number * _MIB)
    return found


_OPERATORS = {ast.LShift: operator.lshift, ast.Mult: operator.mul, ast.Add: operator.add, ast.Sub: operator.sub}


def _evaluate(expression: str) -> float:
    """A constant's initializer: a number, or numbers with << * + - (C++ `uint64_t{64} << 20`)."""
    expression = re.sub(r"\b\w+\{([^}]*)\}", r"(\1)", expression)  # uint64_t{64} -> (64)
    expression = re.sub(r"(?<=\d)(?:u|U|l|L|ul|UL|ull|ULL)\b", "", expression)

    def value(node):
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)):
            return node.value
        if isinstance(node, ast.BinOp) and type(node.op) in _OPERATORS:
            return _OPERATORS[type(node.op)](value(node.left), value(node.right))
        raise ValueError(f"not a constant expression: {expression!r}")

    return float(value(ast.parse(expression.strip(), mode="eval").body))


def _constant(name: str, path: pathlib.Path) -> float:
    text = path.read_text(encoding="utf-8")
    match = re.search(rf"\b{re.escape(name)}\s*=\s*([^;\n]+)", text)
    assert match, f"{path.relative_to(_REPO)} does not define {name}"
    return _evaluate(match.group(1).rstrip(";"))


def _flag_default(flag: str) -> float:
    text = _SERVER_FLAGS.read_text(encoding="utf-8")
    match = re.search(rf"ABSL_FLAG\(\s*[\w:]+\s*,\s*{flag}\s*,\s*([^,]+),", text)
    assert match, f"mll_server has no flag --{flag}"
    return _evaluate(match.group(1))


def _sources(cell: str) -> list[tuple[str, float]]:
    """(what, value) for every flag and constant a "set by" cell names."""
    found = [(f"--{flag}", _flag_default(flag)) for flag in re.findall(r"`--(\w+)`", cell)]
    for name, path in re.findall(r"`(k[A-Z]\w*|[A-Z][A-Z0-9_]+)` in `([^`]+)`", cell):
        file = _REPO / path
        assert file.is_file(), f"the Limits table names {path}, which does not exist"
        found.append((name, _constant(name, file)))
    return found


def test_the_table_lists_every_limit():
    named = " ".join(cells[2] for cells in _rows())
    missing = [what for what in _REQUIRED if f"`{what}`" not in named]
    assert not missing, f"docs/server.md's Limits table lacks {missing}"


def test_every_value_is_the_codes():
    wrong, checked = [], 0
    for limit, value, set_by, _ in _rows():
        sources = _sources(set_by)
        assert sources, f"the Limits row '{limit}' names no flag or constant that sets it"
        numbers = _numbers(value)
        for what, actual in sources:
            checked += 1
            if numbers and actual not in numbers and not (what.startswith("--") and actual == 0):
                wrong.append(f"{limit}: the table says {value!r}, {what} is {actual:g}")
    assert checked >= len(_REQUIRED)
    assert not wrong, wrong


def test_the_table_says_what_a_server_reports(server):
    """The limits GetServerInfo reports, for a server with its defaults but --threads, are the
    table's."""
    limits = mll.server_info(server.address).limits
    rows = {cells[2].split("`")[1]: _numbers(cells[1]) for cells in _rows()}
    assert limits.max_envs in rows["--max_envs"]
    assert limits.max_message_bytes in rows["--max_message_mb"]
    assert limits.idle_timeout_s in rows["--idle_timeout_s"]
    assert limits.shared_memory_sessions in rows["--shared_memory_sessions"]
    assert limits.max_landers in rows["kMaxLanders"]
    assert limits.max_envs_per_token == 0  # No tokens: no quota, as the table says.


def test_the_record_limit_is_the_python_clients():
    from multi_lunar_lander import _record

    rows = {cells[2].split("`")[1]: _numbers(cells[1]) for cells in _rows()}
    assert _record.MAX_RECORD_STEPS in rows["MAX_RECORD_STEPS"]


@pytest.mark.parametrize("n_landers", [0, 33])
def test_past_the_lander_limit_is_invalid_argument(address, n_landers):
    import grpc

    with pytest.raises(mll.MLLError) as caught:
        mll.parallel_env(address=address, n_landers=n_landers)
    assert caught.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert "1..32" in caught.value.message
