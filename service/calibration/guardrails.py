"""Activation guardrails: refused (unless forced) when a keypoint's n falls below
CKS_MIN_CALIBRATION_INSTANCES or half the active version's. Per keypoint: n before and after, the
smallest epsilon with bounded sets (1 / (n + 1)), the set-area ratio (radii grow with the
threshold for peak and var, ellipse areas for cov), the active sets' coverage of the candidate.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from calibration_store import ScoreTable
from service.calibration.registry import ChannelThresholds, channel_thresholds
from service.detector.manifest import KeypointSpec, Manifest

REFERENCE_EPSILON = 0.1
REFERENCE_NONCONFORMITY = "cov"
#: a keypoint's n may not fall below this share of the active version's
LARGEST_DROP = 0.5
#: the exponent turning a threshold ratio into a set-area ratio, per function
_AREA_POWER = {"peak": 2, "var": 2, "cov": 1}


@dataclass(frozen=True)
class KeypointChange:
    keypoint: str
    object: str
    n_before: int | None
    n_after: int
    smallest_bounded_epsilon_before: float | None
    smallest_bounded_epsilon_after: float | None
    set_area_ratio: float | None
    active_coverage_of_candidate: float | None


@dataclass(frozen=True)
class Comparison:
    """A candidate version against the active one (``against`` None: nothing is active)."""

    candidate: int | None
    against: int | None
    nonconformity: str
    epsilon: float
    min_instances: int
    keypoints: tuple[KeypointChange, ...]
    median_set_area_ratio: float | None
    problems: tuple[str, ...]

    @property
    def allowed(self) -> bool:
        return not self.problems

    def as_dict(self) -> dict:
        """Plain JSON values, ``allowed`` included."""
        return {**asdict(self), "allowed": self.allowed}


def compare(
    candidate: ScoreTable,
    active: ScoreTable | None,
    manifest: Manifest,
    min_instances: int,
    candidate_version: int | None = None,
    active_version: int | None = None,
    epsilon: float = REFERENCE_EPSILON,
    nonconformity: str = REFERENCE_NONCONFORMITY,
) -> Comparison:
    """Compare per keypoint and list the reasons an activation would be refused."""
    k = manifest.num_keypoints
    after = channel_thresholds(candidate, k, nonconformity, "keypoint", epsilon, None)
    before = (
        None if active is None else channel_thresholds(active, k, nonconformity, "keypoint", epsilon, None)
    )
    columns = [np.empty(0)] * k  # the candidate's scores per channel (empty: no block for it)
    for block in candidate.objects:
        for j, channel in enumerate(block.keypoint_ids):
            columns[int(channel)] = block.scores[nonconformity][:, j]
    changes = tuple(_change(s, after, before, columns[s.index], nonconformity) for s in manifest.keypoints)
    problems = tuple(problem for change in changes for problem in _problems(change, min_instances))
    ratios = [c.set_area_ratio for c in changes if c.set_area_ratio is not None]
    median = float(np.median(ratios)) if ratios else None
    return Comparison(
        candidate_version, active_version, nonconformity, epsilon, min_instances, changes, median, problems
    )


def _change(
    spec: KeypointSpec,
    after: ChannelThresholds,
    before: ChannelThresholds | None,
    scores: np.ndarray,
    nonconformity: str,
) -> KeypointChange:
    c = spec.index
    n_after = after.guarantees[c].n
    if before is None:
        return KeypointChange(
            spec.name, spec.object, None, n_after, None, _smallest_epsilon(n_after), None, None
        )
    n_before, threshold = before.guarantees[c].n, before.values[c]
    labeled = scores[~np.isnan(scores)]
    ratio = None
    if math.isfinite(after.values[c]) and math.isfinite(threshold) and threshold > 0:
        ratio = float((after.values[c] / threshold) ** _AREA_POWER[nonconformity])
    coverage = float(np.mean(labeled <= threshold)) if labeled.size else None
    epsilons = _smallest_epsilon(n_before), _smallest_epsilon(n_after)
    return KeypointChange(spec.name, spec.object, n_before, n_after, *epsilons, ratio, coverage)


def refusal_detail(comparison: Comparison) -> str:
    return (
        f"activation refused: {len(comparison.problems)} keypoint(s) would be calibrated on too few"
        f" instances (first: {comparison.problems[0]}). Calibrate with more labeled images (append_to"
        " the active version), or activate anyway with force=true and a reason"
    )


def _problems(change: KeypointChange, min_instances: int) -> list[str]:
    """The keypoint's problem, one line whatever rules it breaks (none: an empty list)."""
    n_before, n_after, reasons = change.n_before, change.n_after, []
    if n_after < min_instances:
        reasons.append(f"below the floor of {min_instances} (CKS_MIN_CALIBRATION_INSTANCES)")
    if n_before is not None and n_after < LARGEST_DROP * n_before:
        reasons.append(f"below half of the active version's {n_before}")
    if not reasons:
        return []
    return [f"keypoint {change.keypoint!r}: n = {n_after} calibration scores, " + " and ".join(reasons)]


def _smallest_epsilon(n: int) -> float | None:
    """The smallest epsilon with a bounded set (t >= 1), None when no epsilon < 1 gives one."""
    return 1.0 / (n + 1) if n >= 1 else None
