"""Every number the evaluation shows, computed from a batch's rows and a version's scores
(no drawing, no text)."""

from __future__ import annotations

from dataclasses import dataclass, field

from calibration_store import ScoreTable, VersionInfo
from service.calibration.registry import channel_thresholds
from service.calibration.scoring import NONCONFORMITY_KINDS
from service.detector.manifest import Manifest
from service.evaluation.adaptiveness import Adaptiveness, adaptiveness
from service.evaluation.coverage import ValiditySummary, keypoint_groups, object_groups
from service.evaluation.row_sets import covered_by_score, row_sets
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
    manifest: Manifest,
    model_hash: str,
    version: VersionInfo,
    epsilons: tuple[float, ...],
    delta: float | None = None,
) -> Evaluation:
    """Thresholds of the version (the service's ``channel_thresholds``), the batch's sets and
    their coverage, sizes and adaptiveness, for every function and epsilon."""
    evaluation = Evaluation(manifest, model_hash, version, table.n_instances, rows, tuple(epsilons), delta)
    for kind in NONCONFORMITY_KINDS:
        for epsilon in evaluation.epsilons:
            for scope in evaluation.scopes:
                _validity(evaluation, table, kind, epsilon, scope)
    return evaluation


def _validity(evaluation: Evaluation, table: ScoreTable, kind: str, epsilon: float, scope: str) -> None:
    manifest, rows = evaluation.manifest, evaluation.rows
    delta = evaluation.delta if scope == PAC else None
    result = channel_thresholds(
        table, manifest.num_keypoints, kind, "object" if scope == "object" else "keypoint", epsilon, delta
    )
    sets = row_sets(rows, kind, result.values)
    if scope == "object":
        objects = [(o.name, tuple(o.keypoints)) for o in manifest.objects]
        groups = object_groups(
            sets.covered, rows.labeled, rows.channel, rows.instance, result.guarantees, objects
        )
    else:
        names = [k.name for k in manifest.keypoints]
        groups = keypoint_groups(sets.covered, rows.labeled, rows.channel, result.guarantees, names)
    evaluation.validity[(kind, epsilon, scope)] = ValiditySummary(kind, epsilon, scope, delta, groups)
    if scope == "keypoint":
        labeled = rows.labeled
        by_score = covered_by_score(rows, kind, result.values)
        evaluation.agreement[(kind, epsilon)] = float((by_score[labeled] == sets.covered[labeled]).mean())
        sizes = set_sizes(kind, sets.shapes[labeled])
        evaluation.sizes[(kind, epsilon)] = sizes
        evaluation.adaptive[(kind, epsilon)] = adaptiveness(
            kind, sizes.area, rows.visibility[labeled], rows.visib_fract[labeled], rows.box_side[labeled]
        )
