"""docs/server.md's flags table is mll_server's: every flag `mll_server --help` lists is in the
table and every flag of the table exists, and a default the table gives as a number is the one
--help prints (defaults that depend on the machine or on other flags are written in words)."""

from __future__ import annotations

import pathlib
import re
import subprocess

import multi_lunar_lander as mll

_DOC = pathlib.Path(__file__).resolve().parents[2] / "docs" / "server.md"


def _help_flags() -> dict[str, str]:
    """flag -> default as --help prints it."""
    printed = subprocess.run(
        [mll.find_server_binary(), "--help"], capture_output=True, text=True, timeout=30
    )
    text = printed.stdout + printed.stderr
    return dict(re.findall(r"^  --(\w+)=(\S*)$", text, re.MULTILINE))


def _table_flags() -> dict[str, str]:
    """flag -> default cell, for every row of the Flags table (a row may name two flags)."""
    text = _DOC.read_text(encoding="utf-8")
    section = text[text.index("## Flags"):]
    section = section[: section.index("\n## ", 1)]
    rows = {}
    for line in section.split("\n"):
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) < 3 or not cells[0].startswith("`--"):
            continue
        for flag in re.findall(r"`--(\w+)`", cells[0]):
            rows[flag] = cells[1]
    return rows


def test_every_flag_is_documented_and_every_documented_flag_exists():
    printed, documented = _help_flags(), _table_flags()
    assert printed, "mll_server --help listed no flags"
    missing = sorted(set(printed) - set(documented))
    unknown = sorted(set(documented) - set(printed))
    assert not missing and not unknown, (
        f"docs/server.md's Flags table lacks {missing} and lists flags mll_server does not have: {unknown}"
    )


def test_numeric_defaults_are_the_servers():
    printed = _help_flags()
    wrong = []
    for flag, cell in _table_flags().items():
        match = re.match(r"`?(-?\d+(?:\.\d+)?)`?(\s|$)", cell)
        if match and flag in printed and float(match.group(1)) != float(printed[flag] or "nan"):
            wrong.append(f"--{flag}: documented {cell}, --help {printed[flag]}")
    assert not wrong, wrong
