"""CI proves the README: its test command appears verbatim in .ci/run.

The command is the line running pytest in the first fenced code block after the
``<!-- test-command -->`` marker in README.md.
"""

from __future__ import annotations

import re

from service.infra.settings import PACKAGE_ROOT

README = PACKAGE_ROOT / "README.md"
CI_SCRIPT = PACKAGE_ROOT / ".ci" / "run"
MARKER = "<!-- test-command -->"
FENCED_BLOCK = re.compile(r"^```[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)


def readme_test_command(text: str) -> str:
    assert MARKER in text, f"README.md has no {MARKER} marker before the test command's code block"
    block = FENCED_BLOCK.search(text, text.index(MARKER) + len(MARKER))
    assert block, f"no fenced code block after {MARKER} in README.md"
    commands = [line.strip() for line in block.group(1).splitlines() if "pytest" in line]
    assert len(commands) == 1, f"expected one pytest line in the block after {MARKER}, got {commands}"
    return commands[0].removeprefix("$ ")


def test_readme_test_command_is_what_ci_runs() -> None:
    command = readme_test_command(README.read_text(encoding="utf-8"))
    ci_lines = [line.strip() for line in CI_SCRIPT.read_text(encoding="utf-8").splitlines()]
    assert command in ci_lines, f"README's test command {command!r} is not a line of .ci/run"


def test_the_parser_reads_the_block_after_the_marker() -> None:
    text = (
        "# Title\n\n```bash\npip install x && python -m pytest -k nothing\n```\n\n"
        f"{MARKER}\n```bash\n$ pip install -e '.[test]' && python -m pytest\n```\n"
    )
    assert readme_test_command(text) == "pip install -e '.[test]' && python -m pytest"
