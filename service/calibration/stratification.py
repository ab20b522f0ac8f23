"""Mondrian strata of a calibration version: what was asked (difficulty bins, caller groups),
the bins fitted on the version's own instances (stored with it as JSON), and per-request
thresholds. The math (quantile bins, one ICP threshold per stratum) is ``conformal.strata``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration_store import ObjectScores, ScoreTable
from service.conformal import CoverageGuarantee, calibrate, coverage_guarantee, object_scores
from service.conformal.strata import (
    ALL_GROUPS,
    DifficultyBins,
    DifficultySpec,
    fit_difficulty_bins,
    stratum_calibrations,
)
from service.errors import InvalidInput

DIFFICULTY, GROUP = "difficulty", "group"
STRATIFY_CHOICES = ("none", DIFFICULTY, GROUP, f"{DIFFICULTY}+{GROUP}")


def parse_stratify(value: str | Sequence[str]) -> frozenset[str]:
    """``none``, ``difficulty``, ``group``, ``difficulty+group`` or a list of them -> the kinds."""
    kinds: set[str] = set()
    for part in [value] if isinstance(value, str) else list(value):
        for kind in re.split(r"[+\s,]+", str(part).strip()):  # a "+" in a query string arrives as " "
            if kind not in (DIFFICULTY, GROUP, "none"):
                choices = ", ".join(STRATIFY_CHOICES)
                raise InvalidInput(f"stratify {part!r} is not one of {choices} (or a list of them)")
            if kind != "none":
                kinds.add(kind)
    return frozenset(kinds)


def stored_kinds(strata: Mapping[str, Any] | None) -> frozenset[str]:
    return frozenset() if strata is None else StrataSpec.from_dict(strata["spec"]).kinds


def describe_kinds(kinds: Iterable[str]) -> str:
    return "+".join(k for k in (DIFFICULTY, GROUP) if k in kinds) or "none"


@dataclass(frozen=True)
class StrataSpec:
    """What a version is stratified by: difficulty bins (how), caller groups, both or neither."""

    difficulty: DifficultySpec | None = None
    group: bool = False

    @property
    def kinds(self) -> frozenset[str]:
        return frozenset(k for k, on in ((DIFFICULTY, self.difficulty), (GROUP, self.group)) if on)

    def as_dict(self) -> dict[str, Any]:
        difficulty = None if self.difficulty is None else self.difficulty.as_dict()
        return {"difficulty": difficulty, "group": self.group}

    @classmethod
    def from_dict(cls, value: Mapping[str, Any]) -> StrataSpec:
        difficulty = value.get("difficulty")
        spec = None if difficulty is None else DifficultySpec.from_dict(difficulty)
        return cls(spec, bool(value.get("group")))


@dataclass(frozen=True)
class VersionStrata:
    """A version's strata: spec, groups and difficulty bins per channel and group (or ALL_GROUPS)."""

    spec: StrataSpec
    groups: tuple[str, ...] = ()
    bins: Mapping[int, Mapping[str, DifficultyBins]] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        bins = {str(c): {k: b.as_dict() for k, b in keyed.items()} for c, keyed in self.bins.items()}
        return {"spec": self.spec.as_dict(), "groups": list(self.groups), "bins": bins}

    @classmethod
    def from_dict(cls, value: Mapping[str, Any]) -> VersionStrata:
        bins = {
            int(c): {k: DifficultyBins.from_dict(b) for k, b in keyed.items()}
            for c, keyed in value.get("bins", {}).items()
        }
        return cls(StrataSpec.from_dict(value["spec"]), tuple(value.get("groups", ())), bins)


def fit_strata(table: ScoreTable, spec: StrataSpec) -> VersionStrata:
    """Fit ``spec``: bins per keypoint on its labeled instances (and per group, when both are asked)."""
    groups = tuple(sorted({str(g) for block in table.objects for g in block.groups if g}))
    if spec.group and not groups:
        raise InvalidInput(
            'stratify=group needs group labels, and no instance carries one: add "group":'
            ' "<label>" to the COCO annotations, or stratify by difficulty only'
        )
    bins: dict[int, dict[str, DifficultyBins]] = {}
    if spec.difficulty is not None:
        if not all(block.has_features for block in table.objects):
            raise InvalidInput(
                "stratify=difficulty needs the heatmap features of every instance, and this"
                " calibration has instances scored before features were kept: upload the"
                " batches again without append_to, or stratify=none"
            )
        keys, difficulty = (ALL_GROUPS, *groups) if spec.group else (ALL_GROUPS,), spec.difficulty
        for block in table.objects:
            labeled = ~np.isnan(next(iter(block.scores.values())))  # NaN marks the same keypoints in each
            for j, channel in enumerate(block.keypoint_ids):
                bins[int(channel)] = {}
                for key in keys:
                    rows = labeled[:, j] & _members(block, key)
                    signals = {s: block.features[s][rows, j] for s in difficulty.signals}
                    bins[int(channel)][key] = fit_difficulty_bins(signals, difficulty)
    return VersionStrata(spec, groups if spec.group else (), bins)


def version_strata(table: ScoreTable, stratify: frozenset[str] | None) -> VersionStrata | None:
    """The strata asked, or (None) difficulty strata when every instance carries heatmap features."""
    if stratify is None:
        stratify = frozenset({DIFFICULTY} if all(b.has_features for b in table.objects) else ())
    if not stratify:
        return None
    spec = StrataSpec(DifficultySpec() if DIFFICULTY in stratify else None, GROUP in stratify)
    return fit_strata(table, spec)


def _members(block: ObjectScores, key: str) -> np.ndarray:
    if key == ALL_GROUPS:
        return np.ones(block.n_instances, dtype=bool)
    return np.asarray(block.groups if block.has_groups else [""] * block.n_instances) == key


@dataclass(frozen=True)
class Stratum:
    """Which stratum answered a keypoint: a group, a difficulty bin (signal ranges), both, or none."""

    kinds: str  # "pooled", "difficulty", "group" or "difficulty+group"
    group: str | None = None
    bin: int | None = None
    ranges: tuple[tuple[str, float | None, float | None], ...] = ()
    fallback: str | None = None  # why the pooled threshold answered instead of a stratum


@dataclass(frozen=True)
class StratumAnswer:
    threshold: float
    guarantee: CoverageGuarantee
    stratum: Stratum


@dataclass(frozen=True)
class StratifiedThresholds:
    """Per channel, per group key, one answer per difficulty bin (one bin when not by difficulty)."""

    kinds: frozenset[str]
    answers: Mapping[int, Mapping[str, tuple[StratumAnswer, ...]]]
    bins: Mapping[int, Mapping[str, DifficultyBins]]
    groups: tuple[str, ...]


def stratified_thresholds(
    table: ScoreTable,
    strata: VersionStrata,
    kinds: frozenset[str],
    kind: str,
    scope: str,
    epsilon: float,
    delta: float | None,
) -> StratifiedThresholds:
    """Thresholds of every stratum of ``kinds`` (a subset of the version's): eq. (3) per stratum."""
    keys = strata.groups if GROUP in kinds else (ALL_GROUPS,)
    described = describe_kinds(kinds)
    answers: dict[int, dict[str, tuple[StratumAnswer, ...]]] = {}
    for block in table.objects:
        matrix = block.scores[kind]
        if scope == "object":  # one threshold per group covers all of an object's keypoints at once
            per_key = {}
            for key in keys:
                calibration = calibrate(object_scores(matrix[_members(block, key)]), epsilon, delta)
                stratum = Stratum(GROUP, None if key == ALL_GROUPS else key)
                per_key[key] = (StratumAnswer(calibration.threshold, calibration.guarantee, stratum),)
            answers.update({int(channel): per_key for channel in block.keypoint_ids})
            continue
        for j, channel in enumerate(block.keypoint_ids):
            answers[int(channel)] = {}
            for key in keys:
                rows, group = _members(block, key), None if key == ALL_GROUPS else key
                if DIFFICULTY in kinds:
                    bins = strata.bins[int(channel)][key]
                    assigned = bins.assign({s: block.features[s][rows, j] for s in bins.signals})
                    count = bins.n_bins
                else:
                    bins, assigned, count = None, np.zeros(int(rows.sum()), dtype=np.intp), 1
                calibrations = stratum_calibrations(matrix[rows, j], assigned, count, epsilon, delta)
                answers[int(channel)][key] = tuple(
                    StratumAnswer(c.threshold, c.guarantee, _stratum(described, group, bins, b))
                    for b, c in enumerate(calibrations)
                )
    return StratifiedThresholds(kinds, answers, strata.bins, strata.groups)


def _stratum(kinds: str, group: str | None, bins: DifficultyBins | None, index: int) -> Stratum:
    if bins is None:
        return Stratum(kinds, group)
    return Stratum(kinds, group, index, tuple((s, *bounds) for s, bounds in bins.ranges(index).items()))


@dataclass(frozen=True)
class RowAnswers:
    """Per row of a detector result: threshold, guarantee and the stratum that answered."""

    values: np.ndarray
    guarantees: list[CoverageGuarantee]
    strata: list[Stratum]


def answer_rows(
    thresholds: StratifiedThresholds | None,
    refusal: str | None,
    pooled: tuple[np.ndarray, Sequence[CoverageGuarantee]],
    channels: np.ndarray,
    row_instances: np.ndarray,
    row_groups: Sequence[str | None],
    features: Mapping[str, np.ndarray] | None,
    fallback: str,
) -> RowAnswers:
    """Each row's stratum threshold; without a bounded one (``refusal``, an unknown group, t = 0),
    the pooled threshold with ``fallback`` ``pooled``, else a 422 listing every such row."""
    values, guarantees = pooled
    out = RowAnswers(np.empty(len(channels)), [], [])
    problems: list[str] = []
    bins_of_row = _row_bins(thresholds, channels, row_groups, features)
    for row, channel in enumerate(channels):
        answer, problem = _row_answer(thresholds, refusal, int(channel), row_groups[row], bins_of_row[row])
        if answer is None:
            if refusal is None:
                problem = f"instances[{int(row_instances[row])}]: {problem}"
            problems.append(problem)
            answer = StratumAnswer(values[channel], guarantees[channel], Stratum("pooled", fallback=problem))
        out.values[row] = answer.threshold
        out.guarantees.append(answer.guarantee)
        out.strata.append(answer.stratum)
    if problems and fallback != "pooled":
        unique = list(dict.fromkeys(problems))
        raise InvalidInput(
            "; ".join(unique[:5]) + ' (or set group_fallback="pooled" to use the pooled threshold there)',
            errors=unique,
        )
    return out


def _row_bins(
    thresholds: StratifiedThresholds | None,
    channels: np.ndarray,
    row_groups: Sequence[str | None],
    features: Mapping[str, np.ndarray] | None,
) -> np.ndarray:
    """The difficulty bin of every row (0 when not by difficulty or not answerable)."""
    bins = np.zeros(len(channels), dtype=np.intp)
    if thresholds is None or DIFFICULTY not in thresholds.kinds or features is None:
        return bins
    keys = np.array([_key(thresholds, group) or "" for group in row_groups], dtype=object)
    for channel in np.unique(channels):
        for key, fitted in thresholds.bins.get(int(channel), {}).items():
            rows = np.flatnonzero((channels == channel) & (keys == key))
            if rows.size:
                bins[rows] = fitted.assign({s: np.asarray(features[s])[rows] for s in fitted.signals})
    return bins


def _key(thresholds: StratifiedThresholds, group: str | None) -> str | None:
    return (group if group in thresholds.groups else None) if GROUP in thresholds.kinds else ALL_GROUPS


def _row_answer(
    thresholds: StratifiedThresholds | None, refusal: str | None, channel: int, group: str | None, index: int
) -> tuple[StratumAnswer | None, str]:
    if thresholds is None:
        return None, refusal or ""
    key = _key(thresholds, group)
    if key is None:
        known = ", ".join(repr(g) for g in thresholds.groups)
        named = "names no group" if group is None else f"group {group!r} is unknown to this version"
        return None, f"{named} (known groups: {known})"
    if channel not in thresholds.answers:
        return None, f"calibration version has no scores for keypoint channel {channel}"
    answer = thresholds.answers[channel][key][index]
    guarantee, stratum = answer.guarantee, answer.stratum
    if not guarantee.unbounded:
        return answer, ""
    where = "" if stratum.group is None else f" of group {stratum.group!r}"
    where += "" if stratum.bin is None else f" (difficulty bin {stratum.bin})"
    if guarantee.delta is None:
        # the smallest n with t = floor((n + 1) eps) >= 1 (a bounded threshold)
        least = max(0, math.ceil(1 / guarantee.epsilon) - 2)
        while coverage_guarantee(least, guarantee.epsilon).t == 0:
            least += 1
        asked = f"epsilon {guarantee.epsilon:g} (needs n >= {least})"
    else:
        asked = f"epsilon {guarantee.epsilon:g} with delta {guarantee.delta:g}"
    return None, (
        f"the stratum{where} has n = {guarantee.n} calibration scores for keypoint channel {channel}:"
        f" too few for {asked}"
    )
