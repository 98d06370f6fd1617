"""Every command a user can type has an example in the docs, inside a code block."""

from __future__ import annotations

import re
from pathlib import Path

from swarmrec.cli import COMMANDS

REPO = Path(__file__).resolve().parents[2]


def code_lines() -> list[str]:
    """Every line inside a fenced code block of README.md and docs/*.md."""
    lines: list[str] = []
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        inside = False
        for line in path.read_text(encoding="utf-8").splitlines():
            if line.lstrip().startswith("```"):
                inside = not inside
            elif inside:
                lines.append(line)
    return lines


def test_every_command_has_an_example_in_a_code_block() -> None:
    lines = code_lines()
    missing = [
        command
        for command in COMMANDS
        if not any(re.search(rf"\bswarmrec {re.escape(command)}(\s|$)", line) for line in lines)
    ]
    assert not missing, f"commands with no example in README.md or docs/*.md: {missing}"
