"""Every recorded answer (tests/api/answers.py) is given again: byte for byte, or where a removed
mechanism computed in another floating-point order, with numbers within 1e-12 relative (1e-9 in
pose sets, whose solvers iterate)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from tests.api.answers import collect, recorded

RELATIVE = 1e-12
# A pose's bounds come from iterative solvers (SLSQP, Clarabel) whose last digits follow the BLAS
# threads of the process (a pinned test worker or not): 3e-12 relative was seen between runs.
POSE_RELATIVE = 1e-9


def _differences(before: Any, now: Any, path: str = "") -> list[str]:
    if isinstance(before, float) and isinstance(now, float | int) and not isinstance(now, bool):
        tolerance = POSE_RELATIVE if "/pose/" in path else RELATIVE
        close = math.isclose(before, now, rel_tol=tolerance, abs_tol=0.0) or before == now
        return [] if close else [f"{path}: {before!r} -> {now!r}"]
    if type(before) is not type(now):
        return [f"{path}: {before!r} -> {now!r}"]
    if isinstance(before, dict):
        if before.keys() != now.keys():
            return [f"{path}: keys {sorted(before)} -> {sorted(now)}"]
        return [d for key in before for d in _differences(before[key], now[key], f"{path}/{key}")]
    if isinstance(before, list):
        if len(before) != len(now):
            return [f"{path}: {len(before)} items -> {len(now)}"]
        return [
            d
            for i, (b, n) in enumerate(zip(before, now, strict=True))
            for d in _differences(b, n, f"{path}[{i}]")
        ]
    return [] if before == now else [f"{path}: {before!r} -> {now!r}"]


def test_every_answer_is_unchanged(tmp_path: Path) -> None:
    before, now = recorded(), collect(tmp_path / "data")
    assert before.keys() == now.keys()
    differences = _differences(before, now)
    assert not differences, f"{len(differences)} answers changed, first: {differences[:10]}"
    exact = sum(json.dumps(before[k], sort_keys=True) == json.dumps(now[k], sort_keys=True) for k in before)
    print(f"{exact} of {len(before)} answers byte-identical, the rest within {RELATIVE} relative")
