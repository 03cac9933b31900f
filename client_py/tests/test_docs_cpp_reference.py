"""docs/cpp.md's API references cover the C++ client's public headers, client_cpp/include/mll/
client.h (with the plain types of client_types.h, which it includes) and vector_env.h: every
class, struct and enum of namespace mll::client has a heading `### \\`Name\\`` in the reference,
every public method of a class or struct is named in its section (as `Method` or
`Name::Method`), and every free function is named in the reference. A declaration added to a
header without its documentation fails this test, which lists everything missing.

The header is read with a few regular expressions (comments, then brace-balanced blocks), not a
C++ parser: it expects the header's style (Google C++ style, one declaration per statement).
"""

from __future__ import annotations

import pathlib
import re

import pytest

_REPO = pathlib.Path(__file__).resolve().parents[2]
_INCLUDE = _REPO / "client_cpp" / "include" / "mll"
_DOC = _REPO / "docs" / "cpp.md"
_HEADERS = ("client.h", "vector_env.h")


def _reference_title(header: str) -> str:
    return f"## API reference: `<mll/{header}>`"
_NOT_METHODS = {"operator", "decltype", "sizeof", "static_assert", "alignof", "noexcept"}


def _strip_comments(text: str) -> str:
    """`text` without comments and preprocessor lines (with their continuations)."""
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.DOTALL)
    text = re.sub(r"//[^\n]*", "", text)
    return re.sub(r"^[ \t]*#(?:[^\n]*\\\n)*[^\n]*", "", text, flags=re.MULTILINE)


def _block_end(text: str, start: int) -> int:
    """The index just past the } that closes the { at `start`."""
    depth = 0
    for index in range(start, len(text)):
        if text[index] == "{":
            depth += 1
        elif text[index] == "}":
            depth -= 1
            if depth == 0:
                return index + 1
    raise ValueError("unbalanced braces")


def _flatten(text: str) -> str:
    """`text` with every {...} block replaced by {} (bodies of functions, nested types)."""
    out, index = [], 0
    while True:
        start = text.find("{", index)
        if start < 0:
            out.append(text[index:])
            return "".join(out)
        out.append(text[index:start] + "{}")
        index = _block_end(text, start)


def _namespace_body(text: str) -> str:
    match = re.search(r"namespace mll::client \{", text)
    assert match, "the header has no namespace mll::client"
    body = text[match.end() - 1:_block_end(text, match.end() - 1)][1:-1]
    # Drop namespace internal { ... }.
    while (inner := re.search(r"namespace \w+ \{", body)) is not None:
        end = _block_end(body, inner.end() - 1)
        body = body[: inner.start()] + body[end:]
    return body


def _declarations(header: str) -> str:
    """The header's namespace mll::client, followed by that of each client header it includes
    that has no reference of its own (client.h's client_types.h)."""
    text = (_INCLUDE / header).read_text()
    bodies = [_namespace_body(_strip_comments(text))]
    for included in re.findall(r'^#include "mll/(\w+\.h)"', text, flags=re.MULTILINE):
        if included not in _HEADERS and (_INCLUDE / included).exists():
            bodies.append(_declarations(included))
    return "\n".join(bodies)


def public_api(header: str = "client.h") -> tuple[dict[str, list[str]], list[str]]:
    """({type name: its public methods}, free functions) declared in the header (and the client
    headers it includes that have no reference of their own)."""
    body = _declarations(header)
    types: dict[str, list[str]] = {}
    for match in re.finditer(r"\b(class|struct|enum class|enum)\s+(\w+)\s*(?::[^{;]*)?\{", body):
        # Only declarations at namespace level: skip those inside an earlier type's block.
        prefix = body[: match.start()]
        if prefix.count("{") != prefix.count("}"):
            continue
        kind, name = match.group(1), match.group(2)
        start = match.end() - 1
        block = body[start + 1:_block_end(body, start) - 1]
        methods: list[str] = []
        if kind in ("class", "struct"):
            public = kind == "struct"
            for piece in re.split(r"\b(public|private|protected)\s*:", _flatten(block)):
                if piece in ("public", "private", "protected"):
                    public = piece == "public"
                    continue
                if not public:
                    continue
                for method in re.findall(r"(?<![\w:~])([A-Za-z_]\w*)\s*\(", piece):
                    macro = re.fullmatch(r"[A-Z][A-Z0-9_]*", method)
                    if method not in _NOT_METHODS and not macro and method != name and method not in methods:
                        methods.append(method)
        types[name] = methods
    namespace_level = _flatten(body)
    functions = []
    for statement in namespace_level.split(";"):
        statement = statement.strip()
        if not statement or re.match(r"(class|struct|enum|using|inline constexpr|template)\b", statement):
            continue
        match = re.search(r"([A-Za-z_]\w*)\s*\([^()]*\)\s*(const)?\s*$", statement)
        if match and match.group(1) not in functions:
            functions.append(match.group(1))
    return types, functions


def _reference(header: str) -> str:
    text = _DOC.read_text(encoding="utf-8")
    title = _reference_title(header)
    assert title in text, f"docs/cpp.md has no section '{title}'"
    rest = text[text.index(title) + len(title):]
    end = re.search(r"^## ", rest, re.MULTILINE)
    return rest[: end.start()] if end else rest


def _subsections(reference: str) -> dict[str, str]:
    parts = re.split(r"^### `([\w:]+)`.*$", reference, flags=re.MULTILINE)
    return {parts[index]: parts[index + 1] for index in range(1, len(parts) - 1, 2)}


def _named(name: str, text: str) -> bool:
    return re.search(rf"`(?:[\w:]*::)?{re.escape(name)}\b", text) is not None


def test_the_header_is_read():
    types, functions = public_api()
    assert {"Client", "RemoteEnv", "ClientOptions", "StepData"} <= set(types)
    assert "CreateEnv" in types["Client"] and "Reset" in types["RemoteEnv"]
    assert "ServerOf" not in types["Client"]  # Private.
    assert "LanderOutcomeName" in functions
    assert {"Create", "Step", "Recv", "env_ids"} <= set(public_api("vector_env.h")[0]["VectorEnv"])


@pytest.mark.parametrize("header", _HEADERS)
def test_the_reference_covers_every_public_declaration_of_the_header(header):
    types, functions = public_api(header)
    reference = _reference(header)
    sections = _subsections(reference)
    missing = []
    for name, methods in types.items():
        if name not in sections:
            missing.append(f"{name} (no '### `{name}`' heading)")
            continue
        missing.extend(f"{name}::{method}" for method in methods if not _named(method, sections[name]))
    missing.extend(f"{function}()" for function in functions if not _named(function, reference))
    assert not missing, (
        f"docs/cpp.md's '{_reference_title(header)}' does not document these declarations of "
        f"client_cpp/include/mll/{header}: {missing}"
    )
