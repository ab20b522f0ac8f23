"""Every number the evaluation shows, computed from a batch's rows and a version's scores (no drawing,
no text). The sets are built by the steps ``predict`` takes (the function's ``region``, then
``map_sets_to_image``) and cover a label when it lies in them (``contains``); the ICP definition
(score <= threshold) is computed too, and the report says on how many keypoints both agree."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration_store import ScoreTable, VersionInfo
from service.calibration.registry import channel_thresholds
from service.calibration.scoring import NONCONFORMITY_KINDS
from service.conformal import contains, get_nonconformity_score, map_sets_to_image
from service.detector.manifest import Manifest
from service.detector.session import Detector
from service.evaluation.adaptiveness import Adaptiveness, adaptiveness
from service.evaluation.coverage import ValiditySummary, unit_groups
from service.evaluation.rows import Rows
from service.evaluation.sizes import SetSizes, set_sizes

SCOPES = ("keypoint", "object")
PAC = "pac"  # keypoint scope with the PAC rank (a --delta given)


@dataclass
class Evaluation:
    """The validity per (function, epsilon, scope), the set sizes and adaptiveness at each
    epsilon (keypoint scope), and how often set membership and ``score <= threshold`` agree."""

    manifest: Manifest
    model_hash: str
    version: VersionInfo
    calibration_instances: int
    rows: Rows
    epsilons: tuple[float, ...]
    delta: float | None
    validity: dict[tuple[str, float, str], ValiditySummary] = field(default_factory=dict)
    agreement: dict[tuple[str, float], float] = field(default_factory=dict)
    sizes: dict[tuple[str, float], SetSizes] = field(default_factory=dict)
    adaptive: dict[tuple[str, float], Adaptiveness] = field(default_factory=dict)

    @property
    def scopes(self) -> tuple[str, ...]:
        return SCOPES + ((PAC,) if self.delta is not None else ())

    @property
    def main_epsilon(self) -> float:
        """The epsilon the figures of sizes and adaptiveness are drawn at: 0.1 when asked, else the first."""
        return 0.1 if 0.1 in self.epsilons else self.epsilons[0]

    @property
    def has_occlusion_flags(self) -> bool:
        """Adaptiveness needs both COCO flags: v = 1 (occluded) and v = 2 (visible)."""
        visibility = self.rows.visibility
        return bool((visibility == 1).any() and (visibility == 2).any())


def evaluate(
    rows: Rows,
    table: ScoreTable,
    detector: Detector,
    version: VersionInfo,
    epsilons: tuple[float, ...],
    delta: float | None = None,
) -> Evaluation:
    """Thresholds of the version (the service's ``channel_thresholds``), the batch's sets and
    their coverage, sizes and adaptiveness, for every function and epsilon."""
    manifest, model_hash = detector.manifest, detector.model_hash
    evaluation = Evaluation(manifest, model_hash, version, table.n_instances, rows, tuple(epsilons), delta)
    for kind in NONCONFORMITY_KINDS:
        for epsilon in evaluation.epsilons:
            for scope in evaluation.scopes:
                _validity(evaluation, table, kind, epsilon, scope)
    return evaluation


def _validity(evaluation: Evaluation, table: ScoreTable, kind: str, epsilon: float, scope: str) -> None:
    manifest, rows, labeled = evaluation.manifest, evaluation.rows, evaluation.rows.labeled
    delta = evaluation.delta if scope == PAC else None
    thresholds_scope = "object" if scope == "object" else "keypoint"  # PAC: keypoint scope
    result = channel_thresholds(table, manifest.num_keypoints, kind, thresholds_scope, epsilon, delta)
    centers, shapes = get_nonconformity_score(kind).region(rows.statistics, result.values[rows.channel])
    centers, shapes = map_sets_to_image(centers, shapes, rows.affine)
    covered = np.zeros(len(centers), dtype=bool)
    covered[labeled] = contains(rows.label[labeled], centers[labeled], shapes[labeled])
    if scope == "object":
        units = [(o.name, tuple(o.keypoints)) for o in manifest.objects]
    else:
        units = [(k.name, (k.index,)) for k in manifest.keypoints]
    groups = unit_groups(rows, covered, result.guarantees, units)
    evaluation.validity[(kind, epsilon, scope)] = ValiditySummary(kind, epsilon, scope, delta, groups)
    if scope == "keypoint":
        with np.errstate(invalid="ignore"):  # unlabeled rows: NaN scores, not covered
            by_score = rows.scores[kind] <= result.values[rows.channel]
        evaluation.agreement[(kind, epsilon)] = float((by_score[labeled] == covered[labeled]).mean())
        sizes = evaluation.sizes[(kind, epsilon)] = set_sizes(kind, shapes[labeled])
        evaluation.adaptive[(kind, epsilon)] = adaptiveness(
            sizes.area, rows.visibility[labeled], rows.visib_fract[labeled], rows.box_side[labeled]
        )
