"""Every code block of README.md, CHANGELOG.md and docs/*.md runs, compiles or parses as written,
and no command the documents give overwrites a file of the repository.

Each fenced block names its language, and the language says what is checked:

  python  run as its own program, in a fresh interpreter whose working directory is an empty
          temporary folder (so an example cannot lean on the repository's layout, nor write
          into it), with this test run's environment ($MLL_SERVER_BIN, set by scripts/test.sh,
          is how `address=None` finds the server);
  sh      run by bash (-e, -o pipefail) in an empty temporary folder in which `build`, `.venv`
          and `examples` are links to the repository's, so that the commands run as written
          from the repository's root; a block that calls `mll_cli` without starting a server
          of its own gets an `mll_server` on mll_cli's default address, 127.0.0.1:50051;
  cpp     compiled and linked against the installed package by ctest's
  cmake   client_cpp.consumer_package (tests/client_cpp/doc_blocks.cmake extracts them; the
          test below checks that it finds the same blocks as this file);
  yaml    parsed;
  text    output or a listing, not run. A text block under the marker
              <!-- test: output -->
          is the output of the sh block just above it: each line must match the line printed,
          where "..." stands for any text.

An sh block under the marker <!-- test: server --> starts a server that runs until stopped:
it runs until it has printed as many lines as its output block shows (at most 30 s), is
compared with them, then stopped with SIGTERM, and must exit 0. Tests stay on loopback: its
0.0.0.0 addresses are replaced by 127.0.0.1, in the command and in the output expected.

A block fails if it exits non-zero or runs longer than _TIMEOUT_S. A block that must not run is
skipped only when the last line above its fence is the marker

    <!-- test: skip REASON -->

with a non-empty REASON, which pytest reports (long trainings, installs, commands that need
docker, a cluster or a window). Keep such blocks rare: start servers with `address=None` or
`mll.ServerProcess`, and write files into the working directory.
"""

from __future__ import annotations

import os
import pathlib
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from typing import NamedTuple

import pytest

_REPO = pathlib.Path(__file__).resolve().parents[2]
_DOCUMENTS = ("README.md", "CHANGELOG.md", *sorted(f"docs/{p.name}" for p in (_REPO / "docs").glob("*.md")))
_TIMEOUT_S = 180
_LANGUAGES = ("python", "sh", "cpp", "cmake", "yaml", "text")
_FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```[ \t]*$", re.MULTILINE | re.DOTALL)
_MARKER = re.compile(r"^<!--\s*test:\s*(\w+)\b(.*?)-->\s*$")
_CLI_ADDRESS = ("127.0.0.1", 50051)  # mll_cli's default --address.
# Links in an sh block's working directory: what its commands read from the repository.
_LINKED = ("build", ".venv", "examples")


class Block(NamedTuple):
    document: str
    line: int  # Of the opening fence, 1-based.
    language: str
    code: str
    marker: str | None  # "skip", "output", ... (the marker's word), or None.
    reason: str  # The marker's text after its word.

    @property
    def id(self) -> str:
        return f"{self.document}:{self.line}"


def blocks(document: str) -> list[Block]:
    """Every fenced block of `document` (a path relative to the repository), in order."""
    path = _REPO / document
    if not path.exists():
        return []
    text = path.read_text(encoding="utf-8")
    found = []
    for match in _FENCE.finditer(text):
        line = text.count("\n", 0, match.start()) + 1
        before = text[: match.start()].rstrip("\n").rsplit("\n", 1)[-1].strip()
        marker = _MARKER.match(before)
        found.append(
            Block(
                document,
                line,
                match.group(1).strip(),
                match.group(2),
                marker.group(1) if marker else None,
                marker.group(2).strip() if marker else "",
            )
        )
    return found


_ALL = [block for document in _DOCUMENTS for block in blocks(document)]


def _of(language: str) -> list[Block]:
    return [block for block in _ALL if block.language == language]


def _ids(selected: list[Block]) -> list[str]:
    return [block.id for block in selected]


def test_the_documents_have_examples():
    for document in ("README.md", "docs/python.md", "docs/environment.md", "docs/cpp.md"):
        assert any(block.document == document for block in _ALL), f"{document} has no code block"


def test_every_block_names_a_known_language():
    bad = [f"{block.id}: ```{block.language}" for block in _ALL if block.language not in _LANGUAGES]
    assert not bad, (
        f"blocks without a known language (use one of {_LANGUAGES}; `text` for output and "
        f"listings): {bad}"
    )


def test_markers_are_known_and_skips_give_a_reason():
    for block in _ALL:
        if block.marker is None:
            continue
        assert block.marker in ("skip", "output", "server"), (
            f"{block.id}: unknown marker '<!-- test: {block.marker} -->'"
        )
        if block.marker == "server":
            assert block.language == "sh" and _output_of(block), f"{block.id}: a server block needs an output block"
        if block.marker == "skip":
            assert block.reason, f"{block.id}: '<!-- test: skip -->' without a reason"
            assert block.language in ("python", "sh", "cpp", "cmake"), f"{block.id}: a {block.language} block is never run"
        if block.marker == "output":
            assert block.language == "text", f"{block.id}: '<!-- test: output -->' marks a ```text block"


def _output_of(block: Block) -> Block | None:
    """The ```text block marked as `block`'s output, if any: the next block of its document."""
    following = [b for b in _ALL if b.document == block.document and b.line > block.line]
    if following and following[0].marker == "output":
        return following[0]
    return None


def test_output_blocks_follow_a_shell_block_that_runs():
    for index, block in enumerate(_ALL):
        if block.marker != "output":
            continue
        previous = _ALL[index - 1]
        assert previous.document == block.document and previous.language == "sh" and previous.marker != "skip", (
            f"{block.id}: an output block must follow the sh block (not skipped) that prints it"
        )


def _environment() -> dict:
    env = dict(os.environ, SDL_VIDEODRIVER="dummy", SDL_AUDIODRIVER="dummy", PYTHONDONTWRITEBYTECODE="1")
    env.pop("MLL_TOKEN", None)
    return env


def _fail_message(block: Block, result) -> str:
    return (
        f"{block.id}: the {block.language} block exited with {result.returncode}\n"
        f"--- stdout\n{result.stdout[-3000:]}\n--- stderr\n{result.stderr[-3000:]}"
    )


@pytest.mark.parametrize("block", _of("python"), ids=_ids(_of("python")))
def test_python_block_runs(block, tmp_path):
    if block.marker == "skip":
        pytest.skip(f"{block.id}: {block.reason}")
    result = subprocess.run(
        [sys.executable, "-c", block.code],
        cwd=tmp_path,
        env=_environment(),
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=_TIMEOUT_S,
    )
    assert result.returncode == 0, _fail_message(block, result)


def _starts_a_server(code: str) -> bool:
    return re.search(r"(^|[\s/])mll_server\b", code) is not None


def _port_free(host: str, port: int) -> bool:
    with socket.socket() as probe:
        try:
            probe.bind((host, port))
        except OSError:
            return False
    return True


class _CliServer:
    """An mll_server on mll_cli's default address for the duration of one block."""

    def __init__(self, workdir: pathlib.Path):
        import multi_lunar_lander as mll

        host, port = _CLI_ADDRESS
        self.process = subprocess.Popen(
            [mll.find_server_binary(), f"--address={host}:{port}", "--threads=2"],
            stdin=subprocess.DEVNULL,
            stdout=(workdir / "server.log").open("wb"),
            stderr=subprocess.STDOUT,
        )
        from multi_lunar_lander._server import wait_until_serving

        wait_until_serving(f"{host}:{port}", 30.0)

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(timeout=30)


def _expect_output(block: Block, expected: Block, printed: str) -> None:
    want = expected.code.rstrip("\n").split("\n")
    got = printed.rstrip("\n").split("\n")
    assert len(got) == len(want), (
        f"{expected.id}: {block.id} printed {len(got)} lines, the document shows {len(want)}:\n{printed}"
    )
    for shown, line in zip(want, got):
        pattern = ".*".join(re.escape(part) for part in re.split(r"\.\.\.|…", shown))
        assert re.fullmatch(pattern, line), (
            f"{expected.id}: the document shows\n  {shown}\nbut {block.id} printed\n  {line}"
        )


def _run_server_block(block: Block, workdir: pathlib.Path) -> None:
    expected = _output_of(block)
    want = len(expected.code.rstrip("\n").split("\n"))
    code = block.code.replace("0.0.0.0:", "127.0.0.1:")
    for port in sorted(set(re.findall(r"127\.0\.0\.1:(\d+)", code))):
        if int(port) and not _port_free("127.0.0.1", int(port)):
            pytest.skip(f"{block.id}: needs 127.0.0.1:{port}, which is in use")
    process = subprocess.Popen(
        ["bash", "-c", "exec " + code.strip()],
        cwd=workdir,
        env=_environment(),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines = []
    try:
        deadline = time.monotonic() + 30
        while len(lines) < want and time.monotonic() < deadline:
            line = process.stdout.readline()
            if not line:
                break
            lines.append(line)
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            rest, _ = process.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            rest, _ = process.communicate()
    shown = expected._replace(code=expected.code.replace("0.0.0.0:", "127.0.0.1:"))
    _expect_output(block, shown, "".join(lines))
    assert process.returncode == 0, f"{block.id}: exited with {process.returncode} on SIGTERM:\n{rest[-3000:]}"


@pytest.mark.parametrize("block", _of("sh"), ids=_ids(_of("sh")))
def test_shell_block_runs(block, tmp_path):
    if block.marker == "skip":
        pytest.skip(f"{block.id}: {block.reason}")
    for name in _LINKED:
        (tmp_path / name).symlink_to(_REPO / name)
    if block.marker == "server":
        _run_server_block(block, tmp_path)
        return
    server = None
    if "mll_cli" in block.code and not _starts_a_server(block.code):
        if not _port_free(*_CLI_ADDRESS):
            pytest.skip(f"{block.id}: needs mll_cli's default address 127.0.0.1:50051, which is in use")
        server = _CliServer(tmp_path)
    process = subprocess.Popen(
        ["bash", "-e", "-o", "pipefail", "-c", block.code],
        cwd=tmp_path,
        env=_environment(),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # Its own process group: whatever it leaves running is stopped below.
    )
    try:
        stdout, stderr = process.communicate(timeout=_TIMEOUT_S)
    finally:
        try:
            os.killpg(process.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        if process.poll() is None:
            process.kill()
            process.wait()
        if server is not None:
            server.stop()
    result = subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)
    assert result.returncode == 0, _fail_message(block, result)
    expected = _output_of(block)
    if expected is not None:
        _expect_output(block, expected, stdout)


@pytest.mark.parametrize("block", _of("yaml"), ids=_ids(_of("yaml")))
def test_yaml_block_parses(block):
    yaml = pytest.importorskip("yaml")
    yaml.safe_load(block.code)


def test_cpp_and_cmake_blocks_are_the_ones_the_consumer_test_compiles(tmp_path):
    """tests/client_cpp/doc_blocks.cmake, which ctest's client_cpp.consumer_package uses to
    build the C++ blocks against the installed package, finds the blocks this file finds."""
    script = _REPO / "tests" / "client_cpp" / "doc_blocks.cmake"
    result = subprocess.run(
        ["cmake", f"-DSOURCE_ROOT={_REPO}", f"-DOUT_DIR={tmp_path}", "-P", str(script)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    listed = (tmp_path / "blocks.txt").read_text().split()
    expected = [block.id for block in _ALL if block.language in ("cpp", "cmake") and block.marker != "skip"]
    assert listed == expected
    for block in _ALL:
        if block.language == "cpp" and block.marker != "skip":
            body = "\n".join(line for line in block.code.split("\n") if not line.startswith("#include"))
            generated = [p.read_text() for p in tmp_path.glob("doc_block_*.cc")]
            assert any(body.strip() in text for text in generated), f"{block.id} was not extracted as written"


# --- Commands must not overwrite the repository's files. ---

# Options after which a command names a file it writes.
_OUTPUT_OPTIONS = ("--out", "--gif", "--csv", "--episodes-csv", "--port_file", "-keyout", "-out", "-o")
_INLINE_CODE = re.compile(r"(?<!`)`([^`\n]+)`(?!`)")


def _tracked_files() -> set[str]:
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=_REPO, capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip(f"not a git checkout, so no list of the repository's files: {listed.stderr.strip()}")
    return set(filter(None, listed.stdout.split("\0")))


def _written_paths(command: str) -> list[tuple[str, str]]:
    """(working directory relative to the repository, path) of every file `command` (shell text,
    run from the repository's root) names as an output: the argument of an output option or of
    a > / >> redirection. `cd DIR` moves the working directory for what follows."""
    written, cwd = [], "."
    command = command.replace("\\\n", " ")
    for line in command.split("\n"):
        try:
            tokens = shlex.split(line, comments=True)
        except ValueError:
            continue
        saved = None  # The directory outside the ( subshell ) being read, if any.
        for index, token in enumerate(tokens):
            previous = tokens[index - 1] if index else ""
            head = token.lstrip("(")
            if token.startswith("("):
                saved = cwd
            if previous.lstrip("(") == "cd":
                cwd = os.path.normpath(os.path.join(cwd, token.rstrip(")")))
            option, _, value = head.partition("=")
            if value and option in _OUTPUT_OPTIONS:
                written.append((cwd, value.rstrip(")")))
            elif previous in _OUTPUT_OPTIONS or previous in (">", ">>"):
                written.append((cwd, token.rstrip(")")))
            elif head.startswith((">", ">>")) and head.lstrip(">"):
                written.append((cwd, head.lstrip(">").rstrip(")")))
            if token.endswith(")") and saved is not None:
                cwd, saved = saved, None
    return written


def _commands() -> list[tuple[str, str]]:
    """(where, shell text) of every command the documents give: sh blocks, and inline code
    that runs a program of the repository or a tool."""
    found = [(block.id, block.code) for block in _ALL if block.language == "sh"]
    for document in _DOCUMENTS:
        path = _REPO / document
        if not path.exists():
            continue
        text = re.sub(r"^```.*?^```", "", path.read_text(encoding="utf-8"), flags=re.MULTILINE | re.DOTALL)
        for match in _INLINE_CODE.finditer(text):
            code = match.group(1)
            if re.match(r"(\S+=\S+ )*(\.venv/|build/|scripts/|examples/|bench/|fuzz/|python|cd |\.\./|\./)", code):
                found.append((f"{document}:{text.count(chr(10), 0, match.start()) + 1}", code))
    return found


def test_written_paths_are_found():
    assert _written_paths("a --gif docs/x.gif --out=y.png > z.txt") == [(".", "docs/x.gif"), (".", "y.png"), (".", "z.txt")]
    assert _written_paths("cd examples/dqn\nrun --out s.qnet") == [("examples/dqn", "s.qnet")]
    assert _written_paths("(cd examples/dqn && run --out a) && b --out c") == [("examples/dqn", "a"), (".", "c")]


def test_no_command_overwrites_a_file_of_the_repository():
    tracked = _tracked_files()
    bad = []
    for where, command in _commands():
        for cwd, path in _written_paths(command):
            resolved = os.path.normpath(os.path.join(cwd, path))
            if resolved in tracked:
                bad.append(f"{where}: writes {resolved}")
    assert not bad, "documented commands overwrite files of the repository: " + "; ".join(bad)


def test_extras_the_documents_install_exist():
    """Every `pip install 'PATH[extra,...]'` of the documents names extras that PATH's
    pyproject.toml defines (PATH: the repository's root or client_py)."""
    import tomllib

    pattern = re.compile(r"pip install '?\"?(\.|\./client_py)\[([\w,-]+)\]")
    checked = 0
    for document in _DOCUMENTS:
        path = _REPO / document
        if not path.exists():
            continue
        for match in pattern.finditer(path.read_text(encoding="utf-8")):
            project = tomllib.loads((_REPO / match.group(1) / "pyproject.toml").read_text())
            extras = project["project"].get("optional-dependencies", {})
            for extra in match.group(2).split(","):
                assert extra in extras, f"{document}: pip install '{match.group(1)}[{extra}]': no such extra"
                checked += 1
    assert checked


# --- Links between the documents. ---

_LINK = re.compile(r"\]\(([^)\s]+)\)")


def _anchors(path: pathlib.Path) -> set[str]:
    """GitHub's anchors of the headings of `path`: lower case, punctuation but - and _ dropped,
    spaces as -, repeats numbered."""
    text = re.sub(r"^```.*?^```", "", path.read_text(encoding="utf-8"), flags=re.MULTILINE | re.DOTALL)
    anchors: dict[str, int] = {}
    found = set()
    for heading in re.findall(r"^#+ (.*?)[ \t]*$", text, re.MULTILINE):
        slug = re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")
        count = anchors.get(slug, 0)
        anchors[slug] = count + 1
        found.add(slug if count == 0 else f"{slug}-{count}")
    return found


def test_links_between_documents_resolve():
    """Every relative link of the documents names a file of the repository and, with #anchor,
    a heading of it."""
    bad = []
    for document in _DOCUMENTS:
        path = _REPO / document
        if not path.exists():
            continue
        text = re.sub(r"^```.*?^```", "", path.read_text(encoding="utf-8"), flags=re.MULTILINE | re.DOTALL)
        for target in _LINK.findall(text):
            if re.match(r"[a-z]+:", target):
                continue  # http:, https:, mailto:
            file, _, anchor = target.partition("#")
            linked = (path.parent / file).resolve() if file else path
            if not linked.exists():
                bad.append(f"{document}: {target} (no such file)")
            elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
                bad.append(f"{document}: {target} (no such heading)")
    assert not bad, "broken links: " + "; ".join(bad)
