"""The documents name only what exists: every README.md and docs/*.md is scanned for

  - repository paths in code spans (`server/service/src/service.cc`, `multi_lunar_lander/_record.py`,
    a bare `convert.cc`): the file or folder must be in the repository;
  - `--flags`: one given after `mll_server`, `mll_cli` or `mll_rollout` (in a code span or a
    shell block) must be a flag of that program (its ABSL_FLAG definitions, the environment
    options of MLL_ENV_OPTIONS for the two that take them, and absl's own); a code span that is
    a flag alone must be a flag of a program of the repository (ABSL_FLAG, or a "--flag" string
    of its Python and shell sources) or of an outside tool the documents name (_OUTSIDE_FLAGS);
  - metric names (`mll_..._total`, `process_..._bytes`, ...): exported by the server
    (server/service/src/metrics.cc);
  - functions: `mll.name` must be an attribute of the package, and a call in a code span
    (`Client::GetServerInfo`, `find_server_binary()`) must name identifiers that the repository's
    sources define or use (the documents' own tests, test_docs_*.py, left out: they name removed
    functions to check that they are gone).

Failures list every unknown name with its document and line. Also checked: README.md's and
docs/README.md's tables of documents list the same documents, every document of docs/ among them.
"""

from __future__ import annotations

import functools
import pathlib
import re
import subprocess

import pytest

import multi_lunar_lander as mll

_REPO = pathlib.Path(__file__).resolve().parents[2]
_DOCUMENTS = ("README.md", *sorted(f"docs/{p.name}" for p in (_REPO / "docs").glob("*.md")))
_FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```[ \t]*$", re.MULTILINE | re.DOTALL)
_SPAN = re.compile(r"(?<!`)`([^`\n]+)`(?!`)")

# Folders a path may start from, other than the repository's root: a package's own files.
_BASES = {"multi_lunar_lander": "client_py", "mll_dqn": "examples/dqn"}
# Files the build or a command makes: a document may name them although git does not track them.
_MADE = ("build/", ".venv", "runs/", "out/")
# Bare file names of these kinds must be a tracked file's name.
_SOURCE_SUFFIXES = (".cc", ".h", ".py", ".proto", ".yaml", ".sh", ".cmake", ".toml")
# Flags of outside tools that documents mention in a code span of their own.
_OUTSIDE_FLAGS = {
    "--format": "podman build",
    "--previous": "kubectl logs",
    "--no-deps": "pip install",
    "--no-build-isolation": "pip install",
}
# design.md's example of a new RPC.
_PLACEHOLDERS = {"FooEnv", "kFooEnv", "FooEnvRequest", "FooEnvResponse"}
# Functions of outside tools and languages named in code spans.
_OUTSIDE_FUNCTIONS = {"rate", "sum", "getaddrinfo", "ctypes", "malloc", "free", "memcpy", "fork"}
_METRIC = re.compile(r"\b(?:mll|process)_[a-z_]+?(?:_total|_seconds|_bytes|_live)\b")


class Span:
    def __init__(self, document: str, line: int, text: str, block: bool):
        self.document, self.line, self.text, self.block = document, line, text, block

    def where(self) -> str:
        return f"{self.document}:{self.line}"


@functools.lru_cache(maxsize=None)
def _spans() -> tuple[Span, ...]:
    """Every code span of the documents, and every line of their sh blocks (block=True)."""
    found = []
    for document in _DOCUMENTS:
        text = (_REPO / document).read_text(encoding="utf-8")
        for match in _FENCE.finditer(text):
            if match.group(1).strip() != "sh":
                continue
            first = text.count("\n", 0, match.start(2)) + 1
            for offset, line in enumerate(match.group(2).split("\n")):
                found.append(Span(document, first + offset, line, True))
        prose = _FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)
        for match in _SPAN.finditer(prose):
            found.append(Span(document, prose.count("\n", 0, match.start()) + 1, match.group(1), False))
    return tuple(found)


@functools.lru_cache(maxsize=None)
def _tracked() -> frozenset[str]:
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=_REPO, capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip(f"not a git checkout: {listed.stderr.strip()}")
    files = set(filter(None, listed.stdout.split("\0")))
    # A file another change adds is in the work tree before it is committed.
    untracked = subprocess.run(
        ["git", "ls-files", "-z", "--others", "--exclude-standard"], cwd=_REPO, capture_output=True, text=True
    )
    files |= set(filter(None, untracked.stdout.split("\0")))
    return frozenset(path for path in files if (_REPO / path).exists())


@functools.lru_cache(maxsize=None)
def _folders() -> frozenset[str]:
    return frozenset(str(parent) for path in _tracked() for parent in pathlib.PurePath(path).parents)


def _sources(*suffixes: str) -> str:
    return "\n".join(
        (_REPO / path).read_text(encoding="utf-8", errors="replace") for path in sorted(_tracked()) if path.endswith(suffixes)
    )


# --- Paths. ---

_PATH_TOKEN = re.compile(r"^[\w.+-]+(?:/[\w.+-]*)+$|^[\w+-][\w.+-]*\.[a-z]+$")


def _path_candidates(span: Span) -> list[str]:
    """The paths a code span names: the span itself, or in a shell line each of its words."""
    words = span.text.split() if span.block else [span.text.strip()]
    found = []
    for word in words:
        word = re.sub(r"^[\"'(]+|[\"'),;:]+$", "", word)
        word = re.sub(r"(:\d+)?(#.*)?$", "", word)  # file:line, file#anchor.
        if "=" in word or word.startswith(("-", "/", "~", "$")) or "://" in word:
            continue
        if any(mark in word for mark in ("*", "<", "{", "…", "...", "%")):
            continue
        if _PATH_TOKEN.match(word):
            found.append(word)
    return found


def _path_exists(path: str) -> bool | None:
    """True or False for a path of the repository; None when `path` is not one (an output, a URL,
    another machine's path)."""
    path = path.rstrip("/")
    if path.startswith(_MADE) or path in ("build", ".venv"):
        return None
    head = path.split("/", 1)[0]
    if "/" not in path:
        if not path.endswith(_SOURCE_SUFFIXES):
            return None
        return any(pathlib.PurePath(tracked).name == path for tracked in _tracked()) or path in _folders()
    roots = {pathlib.PurePath(p).parts[0] for p in _tracked()}
    if head in roots:
        return path in _tracked() or path in _folders()
    if head in _BASES:
        full = f"{_BASES[head]}/{path}"
        return full in _tracked() or full in _folders()
    # A path relative to a folder of the repository (`include/mll/core/`, `src/`, `tools/core_bridge.h`)
    # is left to its context; report it only if no tracked path ends with it.
    if head in {pathlib.PurePath(p).name for p in _folders()}:
        return any(p == path or p.endswith("/" + path) for p in _tracked() | _folders())
    return None


def test_named_paths_exist():
    missing = []
    for span in _spans():
        for path in _path_candidates(span):
            if _path_exists(path) is False:
                missing.append(f"{span.where()}: {path}")
    assert not missing, "documents name files the repository does not have: " + "; ".join(sorted(set(missing)))


# --- Flags. ---

_ABSL_BUILTIN = {"help", "helpfull", "helpshort", "helppackage", "version", "only_check_args", "flagfile",
                 "fromenv", "tryfromenv", "undefok"}


def _absl_flags(*paths: str) -> set[str]:
    text = "\n".join((_REPO / path).read_text(encoding="utf-8") for path in paths)
    return set(re.findall(r"ABSL_FLAG\(\s*[\w:<>]+\s*,\s*(\w+)\s*,", text))


@functools.lru_cache(maxsize=None)
def _option_names() -> set[str]:
    header = (_REPO / "proto/include/mll/env_spec.h").read_text(encoding="utf-8")
    body = header[header.index("#define MLL_ENV_OPTIONS"):]
    body = body[: body.index("\n\n")]
    return set(re.findall(r"X\(\s*[\w:]+\s*,\s*(\w+)\s*,", body))


@functools.lru_cache(maxsize=None)
def _program_flags() -> dict[str, set[str]]:
    config = _option_names() | _absl_flags("server/core/tools/config_flags.cc")
    return {
        "mll_server": _absl_flags("server/service/mll_server_main.cc") | _ABSL_BUILTIN,
        "mll_cli": _absl_flags("client_cpp/tools/mll_cli.cc") | config | _ABSL_BUILTIN,
        "mll_rollout": _absl_flags("server/core/tools/mll_rollout.cc") | config | _ABSL_BUILTIN,
    }


@functools.lru_cache(maxsize=None)
def _any_program_flags() -> set[str]:
    flags = {f"--{flag}" for names in _program_flags().values() for flag in names}
    flags |= {f"--{flag}" for flag in re.findall(r"ABSL_FLAG\(\s*[\w:<>]+\s*,\s*(\w+)\s*,", _sources(".cc"))}
    flags |= set(re.findall(r"[\"'](--[A-Za-z][\w-]*)", _sources(".py", ".sh")))
    # Flags built from a dataclass's fields (mll_dqn: every TrainConfig field is a flag).
    config = (_REPO / "examples/dqn/mll_dqn/config.py").read_text(encoding="utf-8")
    flags |= {"--" + field.replace("_", "-") for field in re.findall(r"^    (\w+): ", config, re.MULTILINE)}
    return flags


def test_program_flag_lists_are_read():
    flags = _program_flags()
    assert {"address", "max_envs", "drain_s"} <= flags["mll_server"]
    assert {"address", "token", "n_landers", "policy"} <= flags["mll_cli"]
    assert {"n_landers", "episodes"} <= flags["mll_rollout"]


def _command_flags(text: str) -> list[tuple[str, str]]:
    """(program, flag) for every --flag given to mll_server, mll_cli or mll_rollout in `text` (a
    command line): the flags of a command whose program (its first word after any VAR=value) is
    one of them, up to the end of that command (|, &&, ;, &, or a # comment)."""
    found = []
    for command in re.split(r"\|\|?|&&?|;|\(|\)", text.split(" #", 1)[0]):
        words = [word for word in command.split() if not re.match(r"^[A-Z_]+=", word)]
        if words and words[0] in ("exec", "sudo", "nohup"):
            words = words[1:]
        named = re.search(r"(?:^|/)(mll_server|mll_cli|mll_rollout)$", words[0]) if words else None
        if named:
            found += [(named.group(1), flag) for flag in re.findall(r"(?:^|\s)--([A-Za-z]\w*)", " ".join(words[1:]))]
    return found


def test_command_flags_split():
    assert _command_flags("build/client_cpp/mll_cli play --n_landers=3 --episodes=5 # --x") == [
        ("mll_cli", "n_landers"), ("mll_cli", "episodes")]
    assert _command_flags("mll_server --address=x & python t.py --out y") == [("mll_server", "address")]
    assert _command_flags("python b.py --server build/server/service/mll_server --seconds 2") == []


def test_flags_exist():
    unknown = []
    programs = _program_flags()
    for span in _spans():
        for program, flag in _command_flags(span.text):
            if flag not in programs[program]:
                unknown.append(f"{span.where()}: {program} --{flag}")
        alone = re.fullmatch(r"(--[A-Za-z][\w-]*)(?:[= ][^`]*)?", span.text.strip()) if not span.block else None
        if alone and alone.group(1) not in _any_program_flags() and alone.group(1) not in _OUTSIDE_FLAGS:
            unknown.append(f"{span.where()}: {alone.group(1)}")
    assert not unknown, "documents name flags that do not exist: " + "; ".join(sorted(set(unknown)))


# --- Metrics. ---


@functools.lru_cache(maxsize=None)
def _exported_metrics() -> set[str]:
    source = (_REPO / "server/service/src/metrics.cc").read_text(encoding="utf-8")
    return set(re.findall(r"\"((?:mll|process)_[a-z_]+)", source))


def test_metric_names_are_exported():
    assert {"mll_envs_live", "mll_rpc_errors_total"} <= _exported_metrics()
    unknown = []
    for document in _DOCUMENTS:
        text = (_REPO / document).read_text(encoding="utf-8")
        for match in _METRIC.finditer(text):
            if match.group(0) not in _exported_metrics():
                unknown.append(f"{document}:{text.count(chr(10), 0, match.start()) + 1}: {match.group(0)}")
    assert not unknown, "documents name metrics the server does not export: " + "; ".join(unknown)


def test_method_labels_are_the_services_methods():
    """server.md's list of the `method` label's values is the service's methods, in the proto's order."""
    from multi_lunar_lander._stubs import pb

    methods = [method.name for method in pb.DESCRIPTOR.services_by_name["MultiLunarLander"].methods]
    text = (_REPO / "docs/server.md").read_text(encoding="utf-8")
    listed = re.search(r"`method` is one of `([^`]+)`", text)
    assert listed, "docs/server.md does not list the method label's values"
    assert listed.group(1).split() == methods


# --- Functions. ---


@functools.lru_cache(maxsize=None)
def _identifiers() -> set[str]:
    """The identifiers of the repository's sources but the documents' own tests (this one's text
    names functions that no longer exist)."""
    sources = "\n".join(
        (_REPO / path).read_text(encoding="utf-8", errors="replace")
        for path in sorted(_tracked())
        if path.endswith((".py", ".cc", ".h", ".proto", ".pyi"))
        and not re.fullmatch(r"client_py/tests/test_docs_\w+\.py", path)
    )
    return set(re.findall(r"[A-Za-z_]\w*", sources))


def test_a_removed_function_is_not_an_identifier():
    """The names design.md once gave for steps that are gone are not found (not even in this file)."""
    assert {"GetServerInfo", "find_server_binary", "EnvSnapshot"} <= _identifiers()
    assert not {"ConfigFields", "EnvState", "env_state"} & _identifiers()


_CALL = re.compile(r"(?<![\w.$-])((?:[A-Z]\w*::)*[A-Za-z_]\w*)\(")
_QUALIFIED = re.compile(r"(?<![\w:])((?:[A-Z]\w*::)+[A-Za-z_]\w*)")


def test_python_names_exist():
    unknown = []
    for span in _spans():
        if span.block:
            continue
        for name in re.findall(r"(?<![\w./])mll\.([A-Za-z_]\w*)", span.text):
            if re.fullmatch(r"v\d+", name):  # The proto package, mll.v1.
                continue
            if not hasattr(mll, name):
                unknown.append(f"{span.where()}: mll.{name}")
    assert not unknown, "documents name attributes multi_lunar_lander does not have: " + "; ".join(unknown)


def test_called_and_qualified_names_exist():
    unknown = []
    for span in _spans():
        if span.block or re.match(r"\s*(\$|\.venv/|build/|python|pip|kubectl|docker|podman|rate\()", span.text):
            continue
        names = _CALL.findall(span.text) + _QUALIFIED.findall(span.text)
        for name in names:
            for part in name.split("::"):
                if part in _OUTSIDE_FUNCTIONS or part in _PLACEHOLDERS or part in ("std", "absl", "grpc", "mll", "core", "client", "service"):
                    continue
                if part not in _identifiers():
                    unknown.append(f"{span.where()}: {part} (in `{span.text}`)")
    assert not unknown, "documents name functions or types the sources do not have: " + "; ".join(unknown)


# --- The lists of documents. ---


def _listed(document: str) -> set[str]:
    """The documents the table of `document` links, as paths from the repository's root."""
    path = _REPO / document
    text = path.read_text(encoding="utf-8")
    links = re.findall(r"^\| \[[^\]]+\]\(([^)#]+\.md)\)", text, re.MULTILINE)
    return {str((path.parent / link).resolve().relative_to(_REPO)) for link in links}


def test_both_lists_of_documents_name_the_same_documents():
    top, docs = _listed("README.md"), _listed("docs/README.md")
    every = {f"docs/{p.name}" for p in (_REPO / "docs").glob("*.md") if p.name != "README.md"}
    assert top - {"CHANGELOG.md"} == docs - {"CHANGELOG.md"}, (
        f"README.md lists {sorted(top - docs)} that docs/README.md does not, and docs/README.md "
        f"{sorted(docs - top)} that README.md does not"
    )
    assert every <= docs, f"docs/README.md does not list {sorted(every - docs)}"


def test_the_error_code_table_lists_every_code_the_server_returns():
    """server.md's Error codes table has a row for every canonical code that the server's sources
    (server/core/src, server/service/src) return."""
    sources = "\n".join(
        (_REPO / path).read_text(encoding="utf-8")
        for path in sorted(_tracked())
        if path.startswith(("server/core/src/", "server/service/src/")) and path.endswith(".cc")
    )
    words = set(re.findall(r"absl::(\w+?)Error\(", sources))
    codes = {re.sub(r"(?<!^)([A-Z])", r"_\1", word).upper() for word in words}
    text = (_REPO / "docs/server.md").read_text(encoding="utf-8")
    section = text[text.index("## Error codes"):]
    section = section[: section.index("\n## ", 1)]
    table = set(re.findall(r"^\| ([A-Z_]+) \|", section, re.MULTILINE))
    assert {"INVALID_ARGUMENT", "NOT_FOUND", "PERMISSION_DENIED"} <= codes
    assert not codes - table, f"docs/server.md's Error codes table lacks {sorted(codes - table)}"
