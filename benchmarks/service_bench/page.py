"""docs/performance.md is written by three commands, each owning one marked section of the page.

``bench_peers`` (the service against the frameworks a user would pick instead) comes first, then
``bench_frames`` (a camera frame in memory to sets), then ``bench_service`` (the service against
its bare model). Each command replaces only its own section, so any can be rerun alone; a page
from before the sections counts as bench_service's.
"""

from __future__ import annotations

import re
from pathlib import Path

TITLE = "# Performance"
ORDER = ("bench_peers", "bench_peers_gpu", "bench_frames", "bench_service")
INTRO = (
    "Three commands write this page, each its own section: `python -m benchmarks.bench_peers` (the service"
    " against the frameworks a user would pick instead, ratios first; with `--gpu`, its own section for"
    " the model on a GPU), `python -m benchmarks.bench_frames` (a camera frame in memory to sets: regions"
    " and raw pixels against the whole JPEG) and"
    " `python -m benchmarks.bench_service` "
    "(the service against its bare model: stage breakdown, memory, tuning). Do not edit by hand."
)


def _marker(name: str, end: bool = False) -> str:
    return f"<!-- {name}:{'end' if end else 'begin'} -->"


def _sections(text: str) -> dict[str, str]:
    found = {}
    for name in ORDER:
        pattern = re.escape(_marker(name)) + r"(.*?)" + re.escape(_marker(name, True))
        if match := re.search(pattern, text, re.S):
            found[name] = match[1].strip()
    if not found and text.strip():  # the page bench_service wrote before there were sections
        found["bench_service"] = demote(text)
    return found


def demote(text: str) -> str:
    """A whole page as a section: its title dropped, every other heading one level down."""
    lines = text.strip().splitlines()
    if lines and lines[0].startswith("# "):
        lines = lines[1:]
    return "\n".join("#" + line if line.startswith("#") else line for line in lines).strip()


def write_section(path: Path, name: str, text: str) -> None:
    """Replace section ``name`` of the page at ``path`` (created if missing) with ``text``."""
    sections = _sections(path.read_text()) if path.exists() else {}
    sections[name] = text.strip()
    parts = [TITLE, INTRO]
    parts += [f"{_marker(n)}\n{sections[n]}\n{_marker(n, True)}" for n in ORDER if n in sections]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n\n".join(parts) + "\n")
