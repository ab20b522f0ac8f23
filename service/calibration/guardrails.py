"""Activation guardrails: compare a candidate version with the active one before it goes live.

Thresholds from a small or unrepresentative batch would go live for every request, so an
activation is refused when any keypoint's n falls below a floor (setting
``CKS_MIN_CALIBRATION_INSTANCES``) or below half of the active version's, unless the
operator forces it with a reason. The comparison is also what a dry run shows.

Per keypoint, at a reference epsilon and nonconformity function:
- n before and after, and the smallest epsilon whose sets stay bounded: t >= 1 needs
  floor((n + 1) epsilon) >= 1, i.e. epsilon >= 1 / (n + 1);
- the area ratio of the sets, candidate over active, for the same heatmap: set radii grow
  linearly with the threshold for ``peak`` and ``var`` (area: its square) and ellipse areas
  linearly for ``cov``;
- the active version's coverage of the candidate's own scores: the share of the candidate's
  calibration scores inside the active sets (near 1 - epsilon when both batches come from
  the same distribution; far below warns of a shift).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from calibration_store import ScoreTable
from service.calibration.registry import ChannelThresholds, channel_thresholds
from service.detector.manifest import KeypointSpec, Manifest

MIN_INSTANCES_SETTING = "CKS_MIN_CALIBRATION_INSTANCES"
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
    *,
    candidate_version: int | None = None,
    active_version: int | None = None,
    epsilon: float = REFERENCE_EPSILON,
    nonconformity: str = REFERENCE_NONCONFORMITY,
) -> Comparison:
    """Compare per keypoint and list the reasons an activation would be refused."""
    k = manifest.num_keypoints
    after = channel_thresholds(candidate, k, nonconformity, "keypoint", epsilon, None)
    before = None
    if active is not None:
        before = channel_thresholds(active, k, nonconformity, "keypoint", epsilon, None)
    columns = _score_columns(candidate, nonconformity, k)
    changes, problems = [], []
    for spec in manifest.keypoints:
        change = _change(spec, after, before, columns[spec.index], nonconformity)
        changes.append(change)
        problems.extend(_problems(spec.name, change.n_before, change.n_after, min_instances))
    ratios = [c.set_area_ratio for c in changes if c.set_area_ratio is not None]
    return Comparison(
        candidate=candidate_version,
        against=active_version,
        nonconformity=nonconformity,
        epsilon=epsilon,
        min_instances=min_instances,
        keypoints=tuple(changes),
        median_set_area_ratio=float(np.median(ratios)) if ratios else None,
        problems=tuple(problems),
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
        epsilon_after = _smallest_epsilon(n_after)
        return KeypointChange(spec.name, spec.object, None, n_after, None, epsilon_after, None, None)
    n_before = before.guarantees[c].n
    return KeypointChange(
        keypoint=spec.name,
        object=spec.object,
        n_before=n_before,
        n_after=n_after,
        smallest_bounded_epsilon_before=_smallest_epsilon(n_before),
        smallest_bounded_epsilon_after=_smallest_epsilon(n_after),
        set_area_ratio=_area_ratio(after.values[c], before.values[c], nonconformity),
        active_coverage_of_candidate=_coverage(scores, before.values[c]),
    )


def refusal_detail(comparison: Comparison) -> str:
    """One sentence on why an activation is refused and what to do."""
    return (
        f"activation refused: {len(comparison.problems)} keypoint(s) would be calibrated on too few"
        f" instances (first: {comparison.problems[0]}). Calibrate with more labeled images (append_to"
        " the active version), or activate anyway with force=true and a reason"
    )


def _problems(name: str, n_before: int | None, n_after: int, min_instances: int) -> list[str]:
    """The keypoint's problem, one line whatever rules it breaks (none: an empty list)."""
    reasons = []
    if n_after < min_instances:
        reasons.append(f"below the floor of {min_instances} ({MIN_INSTANCES_SETTING})")
    if n_before is not None and n_after < LARGEST_DROP * n_before:
        reasons.append(f"below half of the active version's {n_before}")
    if not reasons:
        return []
    return [f"keypoint {name!r}: n = {n_after} calibration scores, " + " and ".join(reasons)]


def _smallest_epsilon(n: int) -> float | None:
    """The smallest epsilon with a bounded set (t >= 1), None when no epsilon < 1 gives one."""
    return 1.0 / (n + 1) if n >= 1 else None


def _area_ratio(after: float, before: float, nonconformity: str) -> float | None:
    if not (math.isfinite(after) and math.isfinite(before)) or before <= 0:
        return None
    return float((after / before) ** _AREA_POWER[nonconformity])


def _coverage(scores: np.ndarray, threshold: float) -> float | None:
    labeled = scores[~np.isnan(scores)]
    return float(np.mean(labeled <= threshold)) if labeled.size else None


def _score_columns(table: ScoreTable, nonconformity: str, num_keypoints: int) -> list[np.ndarray]:
    """The scores of each keypoint channel (empty for channels the table has no block for)."""
    columns = [np.empty(0)] * num_keypoints
    for block in table.objects:
        matrix = block.scores[nonconformity]
        for j, channel in enumerate(block.keypoint_ids):
            columns[int(channel)] = matrix[:, j]
    return columns
