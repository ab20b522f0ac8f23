"""Non-blank, non-comment lines of Python per package: ``python tools/line_counts.py [folder ...]``.

A line counts unless it is blank or starts with ``#`` (docstrings count: they are read too).
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ("service", "calibration_store", "client", "benchmarks", "tests", "training")


def code_lines(path: Path) -> int:
    lines = path.read_text(encoding="utf-8").splitlines()
    return sum(1 for line in lines if line.strip() and not line.lstrip().startswith("#"))


def counts(folder: Path) -> Counter[str]:
    """Lines per package (the folder's direct subfolders; its own modules under its name)."""
    per_package: Counter[str] = Counter()
    for path in folder.rglob("*.py"):
        parts = path.relative_to(folder).parts
        per_package[f"{folder.name}/{parts[0]}" if len(parts) > 1 else folder.name] += code_lines(path)
    return per_package


def main(folders: list[str]) -> None:
    for name in folders or DEFAULT:
        per_package = counts(ROOT / name)
        for package, lines in sorted(per_package.items()):
            print(f"{package:36} {lines:7,}")
        print(f"{name + ' in all':36} {sum(per_package.values()):7,}\n")


if __name__ == "__main__":
    main(sys.argv[1:])
