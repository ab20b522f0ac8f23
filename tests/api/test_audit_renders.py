"""Audits of new renders: heavily occluded images fail on their overall figure, ordinary ones pass.

The pooled bands (service/monitoring/coverage_law.py ``pooled_test``) count an image once, not
once per keypoint, and are tight enough to flag the overall coverage of heavy occlusion (about
0.82 where 0.9 is promised), which the union-bound band they replaced could not.
"""

from __future__ import annotations

import json

import pytest

from tests.api.in_process import InProcess
from tests.api.test_audits import run_audit
from tests.samples import batch_zip
from training.coco import ANNOTATIONS_FILENAME
from training.generate import generate

#: (images, a seed the bundled splits never used, extra occluders)
BATCHES = {"ordinary": (30, 9301, 0), "heavy": (60, 9302, 3)}


@pytest.fixture(scope="module")
def renders(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    batches = {}
    for name, (images, seed, occluders) in BATCHES.items():
        folder = tmp_path_factory.mktemp(name)
        generate(folder, images, seed, name, extra_occluders=occluders, progress=False)
        batches[name] = batch_zip(folder, json.loads((folder / ANNOTATIONS_FILENAME).read_text()))
    return batches


def _overall(report: dict, kind: str, epsilon: float, scope: str) -> dict:
    return next(
        s["overall"]
        for s in report["sections"]
        if (s["nonconformity"], s["epsilon"], s["scope"]) == (kind, epsilon, scope)
    )


def test_heavy_occlusion_fails_on_its_overall_figure(api: InProcess, renders: dict[str, bytes]) -> None:
    report = run_audit(api, renders["heavy"], name="heavy")["report"]
    overall = _overall(report, "cov", 0.1, "keypoint")
    assert overall["coverage"] < overall["band"][0] and overall["flagged"], overall
    assert not report["passed"]
    assert any(f["object"] is None and f["scope"] == "keypoint" for f in report["flagged"])


def test_ordinary_renders_pass(api: InProcess, renders: dict[str, bytes]) -> None:
    report = run_audit(api, renders["ordinary"], name="ordinary")["report"]
    assert report["passed"], report["flagged"][:3]
    overall = _overall(report, "cov", 0.1, "keypoint")
    assert overall["in_band"] and overall["band"][1] - overall["band"][0] < 0.1, overall
