"""The Python examples of README.md and docs/python.md run exactly as written.

Every fenced ```python block of those files is run as its own program, in a fresh interpreter
whose working directory is an empty temporary folder (so an example cannot lean on the
repository's layout), with this test run's environment ($MLL_SERVER_BIN, set by
scripts/test.sh, is how `address=None` finds the server). A block fails the test if it exits
non-zero or runs longer than _TIMEOUT_S.

A block that cannot run here is skipped only when the line just above its fence is the marker

    <!-- test: skip REASON -->

with a non-empty REASON, which pytest reports. Write examples so that they run instead (start
servers with `address=None` or `mll.ServerProcess`) and keep the marker for the rare block that
needs something a test machine lacks.
"""

from __future__ import annotations

import os
import pathlib
import re
import subprocess
import sys

import pytest

_REPO = pathlib.Path(__file__).resolve().parents[2]
_DOCUMENTS = ("README.md", "docs/python.md")
_TIMEOUT_S = 180
_FENCE = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.MULTILINE | re.DOTALL)
_SKIP = re.compile(r"<!--\s*test:\s*skip\b(.*?)-->\s*$")


def _blocks(document: str) -> list[tuple[str, int, str, str | None]]:
    """(document, line of the fence, code, skip reason or None) of every python block."""
    text = (_REPO / document).read_text(encoding="utf-8")
    found = []
    for match in _FENCE.finditer(text):
        line = text.count("\n", 0, match.start()) + 1
        before = text[: match.start()].rstrip("\n").rsplit("\n", 1)[-1]
        skip = _SKIP.search(before)
        reason = skip.group(1).strip() if skip else None
        found.append((document, line, match.group(1), reason))
    return found


_ALL = [block for document in _DOCUMENTS for block in _blocks(document)]


def test_every_document_has_examples():
    for document in _DOCUMENTS:
        assert any(block[0] == document for block in _ALL), f"{document} has no ```python block"


def test_skip_markers_give_a_reason():
    for document, line, _, reason in _ALL:
        assert reason is None or reason, f"{document}:{line}: '<!-- test: skip -->' without a reason"


@pytest.mark.parametrize("document,line,code,reason", _ALL, ids=[f"{b[0]}:{b[1]}" for b in _ALL])
def test_example_runs(document, line, code, reason, tmp_path):
    if reason is not None:
        pytest.skip(f"{document}:{line}: {reason}")
    env = dict(os.environ, SDL_VIDEODRIVER="dummy", SDL_AUDIODRIVER="dummy")
    result = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        env=env,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=_TIMEOUT_S,
    )
    assert result.returncode == 0, (
        f"{document}:{line}: the example exited with {result.returncode}\n"
        f"--- stdout\n{result.stdout[-3000:]}\n--- stderr\n{result.stderr[-3000:]}"
    )
