"""The README's examples, read from it, so that the tests run what a reader would."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

from service.infra.settings import PACKAGE_ROOT

README = PACKAGE_ROOT / "README.md"
FENCED_BASH = re.compile(r"^```bash\n(.*?)^```", re.MULTILINE | re.DOTALL)


def bash_blocks(text: str | None = None) -> list[str]:
    """Every ```bash block of the README (or of ``text``), in order."""
    return FENCED_BASH.findall(README.read_text(encoding="utf-8") if text is None else text)


def section(heading: str) -> str:
    """The README's text from ``## heading`` to the next ``## `` heading."""
    text = README.read_text(encoding="utf-8")
    start = text.index(f"\n## {heading}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end >= 0 else None]


def commands_and_outputs(block: str) -> list[tuple[str, str]]:
    """Each command of a block with the output its ``# `` comment lines after it show ("" if none);
    continued lines joined. ``...`` in an output stands for whatever the service says there."""
    pairs: list[tuple[str, str]] = []
    for line in re.sub(r"\\\n\s*", "", block).splitlines():
        stripped = line.strip()
        if stripped.startswith("# ") and pairs:
            pairs[-1] = (pairs[-1][0], pairs[-1][1] + stripped[2:].strip())
        elif stripped and not stripped.startswith("#"):
            pairs.append((stripped, ""))
    return pairs


def shows(output: str, shown: str) -> bool:
    """Whether ``output`` holds what the README ``shown`` for it: its pieces between ``...``, in order."""
    position = 0
    for piece in filter(None, shown.split("...")):
        position = output.find(piece, position)
        if position < 0:
            return False
        position += len(piece)
    return True


def predict_example(*, path: str = "/v1/predict") -> tuple[Path, dict, dict[str, str]]:
    """The image, request JSON and headers of the README's first curl to ``path`` (/v1/predict
    for the JSON answer, /v1/predict/png for the drawing)."""
    for block in bash_blocks():
        for command, _ in commands_and_outputs(block):
            words = shlex.split(command.split(" #")[0])
            if words[:1] != ["curl"] or not any(w.endswith(path) for w in words):
                continue
            options = list(zip(words, words[1:], strict=False))
            headers = dict(v.split(": ", 1) for k, v in options if k == "-H")
            form = dict(v.split("=", 1) for k, v in options if k == "-F")
            return PACKAGE_ROOT / form["image"].removeprefix("@"), json.loads(form["request"]), headers
    raise AssertionError(f"the README has no curl example of {path}")
