"""The README's examples, read from it, so that the tests run what a reader would."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

from service.runtime.settings import PACKAGE_ROOT

README = PACKAGE_ROOT / "README.md"
FENCED_BASH = re.compile(r"^```bash\n(.*?)^```", re.MULTILINE | re.DOTALL)


def bash_blocks(text: str | None = None) -> list[str]:
    """Every ```bash block of the README (or of ``text``), in order."""
    return FENCED_BASH.findall(README.read_text(encoding="utf-8") if text is None else text)


def shell_commands(block: str) -> list[str]:
    """The commands of a block: continued lines joined, comments and blank lines left out."""
    joined = re.sub(r"\\\n\s*", "", block)
    return [
        line.strip() for line in joined.splitlines() if line.strip() and not line.lstrip().startswith("#")
    ]


def predict_example(*, accept: str = "application/json") -> tuple[Path, dict, dict[str, str]]:
    """The image, request JSON and headers of the README's first curl to /v1/predict that asks
    for ``accept`` (the JSON answer unless a ``-H 'Accept: ...'`` says otherwise)."""
    for block in bash_blocks():
        for command in shell_commands(block):
            words = shlex.split(command.split(" #")[0])
            if words[:1] != ["curl"] or not any(w.endswith("/v1/predict") for w in words):
                continue
            options = list(zip(words, words[1:], strict=False))
            headers = dict(v.split(": ", 1) for k, v in options if k == "-H")
            if headers.get("Accept", "application/json") != accept:
                continue
            form = dict(v.split("=", 1) for k, v in options if k == "-F")
            return PACKAGE_ROOT / form["image"].removeprefix("@"), json.loads(form["request"]), headers
    raise AssertionError(f"the README has no curl example of /v1/predict answering {accept}")
