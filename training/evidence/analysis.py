"""Everything the report shows, computed from the two cached splits (no drawing, no text)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service.calibration.scoring import NONCONFORMITY_KINDS
from service.detector.manifest import Manifest
from service.detector.runtime import Detector
from training.evidence.adaptiveness import Adaptiveness, adaptiveness, easy_and_hard
from training.evidence.baseline import BASELINE_KIND, OUTSIDE_SCORE
from training.evidence.inference import SplitData, concatenate, load_split
from training.evidence.resplits import ResplitResult, resplit
from training.evidence.sets import RowSets, covered_by_score, row_sets, score_table, thresholds
from training.evidence.tightness import SetSizes, set_sizes
from training.evidence.validity import ValiditySummary, keypoint_groups, object_groups

EPSILONS = (0.05, 0.1, 0.2)
MAIN_EPSILON = 0.1
PAC_DELTA = 0.1
SCOPES = ("keypoint", "object", "pac")


@dataclass(frozen=True)
class BaselineResult:
    epsilon: float
    validity: ValiditySummary
    area: np.ndarray  # (R,) image px^2 of each labeled test row's pixel set


@dataclass
class Evidence:
    manifest: Manifest
    model_hash: str
    calibration: SplitData
    test: SplitData
    validity: dict[tuple[str, float, str], ValiditySummary] = field(default_factory=dict)
    agreement: dict[tuple[str, float], float] = field(default_factory=dict)
    sets: dict[tuple[str, float], RowSets] = field(default_factory=dict)
    sizes: dict[tuple[str, float], SetSizes] = field(default_factory=dict)
    adaptive: dict[str, Adaptiveness] = field(default_factory=dict)
    resplits: dict[tuple[str, float], ResplitResult] = field(default_factory=dict)
    baseline: dict[float, BaselineResult] = field(default_factory=dict)
    overlay_instances: tuple[int, int] = (0, 0)
    splits: int = 0


def collect_evidence(
    detector: Detector, calibration_dir: Path, test_dir: Path, cache_dir: Path, splits: int, seed: int
) -> Evidence:
    """Run (or read from the cache) both splits and compute every section's numbers."""
    manifest = detector.manifest
    calibration = load_split(calibration_dir, detector, cache_dir)
    table = score_table(calibration, manifest)
    baseline_thresholds = {e: thresholds(table, manifest, BASELINE_KIND, e).values for e in EPSILONS}
    test = load_split(test_dir, detector, cache_dir, baseline_thresholds)
    evidence = Evidence(manifest, detector.model_hash, calibration, test, splits=splits)
    for kind in NONCONFORMITY_KINDS:
        for epsilon in EPSILONS:
            _validity(evidence, table, kind, epsilon)
    for epsilon in EPSILONS:
        evidence.baseline[epsilon] = _baseline(evidence, table, epsilon, baseline_thresholds[epsilon])
    _adaptiveness(evidence)
    pooled = concatenate(calibration, test)
    evidence.resplits = resplit(
        pooled, calibration.images, manifest, NONCONFORMITY_KINDS, EPSILONS, splits, seed
    )
    return evidence


def _validity(evidence: Evidence, table, kind: str, epsilon: float) -> None:
    manifest, test = evidence.manifest, evidence.test
    names = [k.name for k in manifest.keypoints]
    objects = [(o.name, tuple(o.keypoints)) for o in manifest.objects]
    for scope in SCOPES:
        delta = PAC_DELTA if scope == "pac" else None
        result = thresholds(
            table, manifest, kind, epsilon, "object" if scope == "object" else "keypoint", delta
        )
        sets = row_sets(test, kind, result.values)
        if scope == "object":
            groups = object_groups(
                sets.covered, test.labeled, test.channel, test.instance, result.guarantees, objects
            )
        else:
            groups = keypoint_groups(sets.covered, test.labeled, test.channel, result.guarantees, names)
        evidence.validity[(kind, epsilon, scope)] = ValiditySummary(kind, epsilon, scope, delta, groups)
        if scope == "keypoint":
            by_score = covered_by_score(test, kind, result.values)
            labeled = test.labeled
            evidence.agreement[(kind, epsilon)] = float((by_score[labeled] == sets.covered[labeled]).mean())
            evidence.sets[(kind, epsilon)] = sets
            evidence.sizes[(kind, epsilon)] = set_sizes(kind, sets.shapes[labeled])


def _baseline(evidence: Evidence, table, epsilon: float, channel_values: np.ndarray) -> BaselineResult:
    manifest, test = evidence.manifest, evidence.test
    result = thresholds(table, manifest, BASELINE_KIND, epsilon)
    scores = test.scores[BASELINE_KIND]
    with np.errstate(invalid="ignore"):
        covered = (scores <= channel_values[test.channel]) & (scores < OUTSIDE_SCORE)
    names = [k.name for k in manifest.keypoints]
    groups = keypoint_groups(covered, test.labeled, test.channel, result.guarantees, names)
    pixel_area = 1.0 / np.abs(np.linalg.det(test.affine[:, :, :2]))
    area = (test.baseline_pixels[epsilon] * pixel_area)[test.labeled]
    return BaselineResult(epsilon, ValiditySummary(BASELINE_KIND, epsilon, "keypoint", None, groups), area)


def _adaptiveness(evidence: Evidence) -> None:
    test = evidence.test
    labeled = test.labeled
    for kind in NONCONFORMITY_KINDS:
        area = evidence.sizes[(kind, MAIN_EPSILON)].area
        evidence.adaptive[kind] = adaptiveness(
            kind, area, test.visibility[labeled], test.visib_fract[labeled], test.box_side[labeled]
        )
    relative = evidence.sizes[("cov", MAIN_EPSILON)].area / test.box_side[labeled] ** 2
    evidence.overlay_instances = easy_and_hard(test.instance[labeled], relative, test.visib_fract[labeled])
