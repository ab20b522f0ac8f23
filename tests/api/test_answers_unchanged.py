"""Every recorded answer (tests/api/answers.py) is given again, as far as it can be on any x86-64 CPU.

The model runs in float32, and onnxruntime, numpy and OpenCV pick their kernels by instruction set
(AVX-512, AVX2 with FMA, ...): another CPU sums in another order, and the last bits of a heatmap
differ. What is exact by construction is compared exactly: every integer (n, t, ranks, versions,
counts), string (set types, names, problems) and flag, and the guarantee's numbers, which follow
from n, t, epsilon and delta alone. Every other number may move by ``FLOAT32_ACROSS_CPUS`` of its
scale: the largest magnitude among the numbers of its vector or matrix (a matrix moves as a whole),
90 degrees for an ellipse's angle. Measured between an AVX-512 machine and the one that recorded the
answers, the largest such move was 1e-3 (a heatmap pixel at the median flips in or out of the
anchor normalization's upper half, which moves the peak's probability); 77,000 numbers moved.
The PNG drawing's hash is compared only where every number came back bit for bit.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from tests.api.answers import collect, recorded

FLOAT32_ACROSS_CPUS = 5e-3
#: Functions of n, t, epsilon and delta: the same on every CPU but for libm's last bit.
EXACT_FLOATS = 1e-12
ANGLE_SCALE = 90.0


def _magnitudes(values: list[Any]) -> list[float]:
    flat: list[float] = []
    for value in values:
        if isinstance(value, list):
            flat += _magnitudes(value)
        elif isinstance(value, float | int) and not isinstance(value, bool):
            flat.append(abs(value))
    return flat


def _tolerance(path: str) -> float:
    return EXACT_FLOATS if "/guarantee/" in path else FLOAT32_ACROSS_CPUS


def _differences(before: Any, now: Any, path: str = "", scale: float = 0.0) -> list[str]:
    if isinstance(before, float) and isinstance(now, float | int) and not isinstance(now, bool):
        scale = ANGLE_SCALE if path.endswith("angle_deg") else scale
        close = abs(before - now) <= _tolerance(path) * max(abs(before), abs(now), scale)
        return [] if close or before == now else [f"{path}: {before!r} -> {now!r}"]
    if type(before) is not type(now):
        return [f"{path}: {before!r} -> {now!r}"]
    if isinstance(before, dict):
        if before.keys() != now.keys():
            return [f"{path}: keys {sorted(before)} -> {sorted(now)}"]
        return [d for key in before for d in _differences(before[key], now[key], f"{path}/{key}")]
    if isinstance(before, list):
        if len(before) != len(now):
            return [f"{path}: {len(before)} items -> {len(now)}"]
        scale = max(_magnitudes(before), default=0.0)
        return [
            d
            for i, (b, n) in enumerate(zip(before, now, strict=True))
            for d in _differences(b, n, f"{path}[{i}]", scale)
        ]
    return [] if before == now else [f"{path}: {before!r} -> {now!r}"]


def test_every_answer_is_unchanged(tmp_path: Path) -> None:
    before, now = recorded(), collect(tmp_path / "data")
    assert before.keys() == now.keys()
    drawn_before, drawn_now = before.pop("png"), now.pop("png")
    differences = _differences(before, now)
    assert not differences, f"{len(differences)} answers changed, first: {differences[:10]}"
    exact = sum(json.dumps(before[k], sort_keys=True) == json.dumps(now[k], sort_keys=True) for k in before)
    if exact == len(before):
        assert drawn_now == drawn_before
    else:
        assert _differences({**drawn_before, "png_sha256": ""}, {**drawn_now, "png_sha256": ""}) == []
    print(f"{exact} of {len(before)} answers bit for bit, the rest within float32's reach across CPUs")


def test_the_comparison_catches_a_changed_answer() -> None:
    ellipse = {"set": {"type": "ellipse", "semi_axes": [4.24, 6.01], "angle_deg": -30.1}, "n": 413}
    moved = {"set": {"type": "ellipse", "semi_axes": [4.24, 6.01 * 1.01], "angle_deg": -30.1}, "n": 413}
    assert _differences(ellipse, moved) == ["/set/semi_axes[1]: 6.01 -> 6.0701"]
    assert _differences(ellipse, {**ellipse, "n": 412}) == ["/n: 413 -> 412"]
    assert _differences(ellipse, {**ellipse, "set": {**ellipse["set"], "type": "ball"}})
    guarantee = {"guarantee": {"coverage_upper_bound": 0.9025706940874036}}
    assert _differences(guarantee, {"guarantee": {"coverage_upper_bound": 0.90257069}})
    assert not _differences({"m": [[5.0, 1e-5]]}, {"m": [[5.0, 2e-5]]})  # small beside its matrix
