"""Mondrian strata of a calibration version: what was asked (difficulty bins, caller groups),
the bins fitted on the version's own instances (stored with it), and per-request thresholds.

The math (quantile bins, one ICP threshold per stratum, its guarantee) is in
``service.conformal.strata``; here a ScoreTable's blocks and channels are walked, a
version's strata are stored as JSON, and a request's rows are matched to their strata.
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
from service.conformal.features import HEATMAP_FEATURES
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
FALLBACKS = ("refuse", "pooled")


def difficulty_spec(signals: Sequence[str], bins: int, min_instances: int) -> DifficultySpec:
    """The difficulty bins new versions get (CKS_STRATUM_SIGNALS, _BINS, CKS_MIN_STRATUM_INSTANCES)."""
    signals = tuple(signals)
    if unknown := [name for name in signals if name not in HEATMAP_FEATURES]:
        raise ValueError(
            f"CKS_STRATUM_SIGNALS: unknown heatmap feature {', '.join(unknown)};"
            f" give one or two of {', '.join(HEATMAP_FEATURES)}"
        )
    return DifficultySpec(signals, bins, min_instances)


def parse_stratify(value: str | Sequence[str]) -> frozenset[str]:
    """``none``, ``difficulty``, ``group``, ``difficulty+group`` or a list of them -> the kinds."""
    parts = [value] if isinstance(value, str) else list(value)
    kinds: set[str] = set()
    for part in parts:
        for kind in re.split(r"[+\s,]+", str(part).strip()):  # a "+" in a query string arrives as " "
            if kind not in (DIFFICULTY, GROUP, "none"):
                choices = ", ".join(STRATIFY_CHOICES)
                raise InvalidInput(f"stratify {part!r} is not one of {choices} (or a list of them)")
            if kind != "none":
                kinds.add(kind)
    return frozenset(kinds)


def stored_kinds(strata: Mapping[str, Any] | None) -> frozenset[str]:
    """The kinds of strata a stored version has (``VersionInfo.strata``)."""
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

    @classmethod
    def of(cls, kinds: frozenset[str], difficulty: DifficultySpec) -> StrataSpec:
        unknown = [s for s in difficulty.signals if s not in HEATMAP_FEATURES]
        if unknown:
            known = ", ".join(HEATMAP_FEATURES)
            raise InvalidInput(f"difficulty signals {unknown} are not heatmap features ({known})")
        return cls(difficulty if DIFFICULTY in kinds else None, GROUP in kinds)

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
    """A version's strata: its spec, the group labels it knows and, per keypoint channel and
    group (``ALL_GROUPS`` = every instance), the difficulty bins fitted on its instances."""

    spec: StrataSpec
    groups: tuple[str, ...] = ()
    bins: Mapping[int, Mapping[str, DifficultyBins]] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "spec": self.spec.as_dict(),
            "groups": list(self.groups),
            "bins": {str(c): {k: b.as_dict() for k, b in keyed.items()} for c, keyed in self.bins.items()},
        }

    @classmethod
    def from_dict(cls, value: Mapping[str, Any]) -> VersionStrata:
        bins = {
            int(c): {k: DifficultyBins.from_dict(b) for k, b in keyed.items()}
            for c, keyed in value.get("bins", {}).items()
        }
        return cls(StrataSpec.from_dict(value["spec"]), tuple(value.get("groups", ())), bins)


def fit_strata(table: ScoreTable, spec: StrataSpec) -> VersionStrata:
    """Fit ``spec`` on a version's instances: bins per keypoint over its labeled instances
    (and within each group when both are asked). Refused when the table cannot carry it."""
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
        keys = (ALL_GROUPS, *groups) if spec.group else (ALL_GROUPS,)
        for block in table.objects:
            bins.update(_block_bins(block, spec.difficulty, keys))
    return VersionStrata(spec, groups if spec.group else (), bins)


def version_strata(
    table: ScoreTable, stratify: frozenset[str] | None, difficulty: DifficultySpec
) -> VersionStrata | None:
    """The strata a new version stores: those asked, or (None) difficulty strata whenever
    every instance carries heatmap features; None when there are none."""
    if stratify is None:
        stratify = frozenset({DIFFICULTY} if all(b.has_features for b in table.objects) else ())
    return fit_strata(table, StrataSpec.of(stratify, difficulty)) if stratify else None


def _block_bins(
    block: ObjectScores, spec: DifficultySpec, keys: Sequence[str]
) -> dict[int, dict[str, DifficultyBins]]:
    labeled = ~np.isnan(next(iter(block.scores.values())))  # NaN marks the same keypoints in every function
    members = _members(block)
    out: dict[int, dict[str, DifficultyBins]] = {}
    for j, channel in enumerate(block.keypoint_ids):
        out[int(channel)] = {}
        for key in keys:
            rows = labeled[:, j] & members(key)
            signals = {s: block.features[s][rows, j] for s in spec.signals}
            out[int(channel)][key] = fit_difficulty_bins(signals, spec)
    return out


def _members(block: ObjectScores):
    groups = np.asarray(block.groups if block.has_groups else [""] * block.n_instances)

    def rows(key: str) -> np.ndarray:
        return np.ones(block.n_instances, dtype=bool) if key == ALL_GROUPS else groups == key

    return rows


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
    answers: dict[int, dict[str, tuple[StratumAnswer, ...]]] = {}
    for block in table.objects:
        members = _members(block)
        matrix = block.scores[kind]
        if scope == "object":  # one threshold per group covers all of an object's keypoints at once
            per_key = {key: _object_answer(matrix[members(key)], key, epsilon, delta) for key in keys}
            answers.update({int(channel): per_key for channel in block.keypoint_ids})
            continue
        for j, channel in enumerate(block.keypoint_ids):
            answers[int(channel)] = {}
            for key in keys:
                rows = members(key)
                group = None if key == ALL_GROUPS else key
                if DIFFICULTY in kinds:
                    bins = strata.bins[int(channel)][key]
                    assigned = bins.assign({s: block.features[s][rows, j] for s in bins.signals})
                    count = bins.n_bins
                else:
                    bins, assigned, count = None, np.zeros(int(rows.sum()), dtype=np.intp), 1
                calibrations = stratum_calibrations(matrix[rows, j], assigned, count, epsilon, delta)
                answers[int(channel)][key] = tuple(
                    StratumAnswer(c.threshold, c.guarantee, _stratum(kinds, group, bins, b))
                    for b, c in enumerate(calibrations)
                )
    return StratifiedThresholds(kinds, answers, strata.bins, strata.groups)


def _object_answer(matrix: np.ndarray, key: str, epsilon: float, delta: float | None) -> tuple[StratumAnswer]:
    calibration = calibrate(object_scores(matrix), epsilon, delta)
    group = None if key == ALL_GROUPS else key
    return (StratumAnswer(calibration.threshold, calibration.guarantee, Stratum(GROUP, group)),)


def _stratum(kinds: frozenset[str], group: str | None, bins: DifficultyBins | None, index: int) -> Stratum:
    if bins is None:
        return Stratum(describe_kinds(kinds), group)
    ranges = tuple((signal, low, high) for signal, (low, high) in bins.ranges(index).items())
    return Stratum(describe_kinds(kinds), group, index, ranges)


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
    """Each row's stratum threshold; where a row has no bounded stratum (``refusal``: the version
    lacks the strata asked; or an unknown group, or t = 0), the pooled threshold if
    ``fallback`` is ``pooled``, else a 422 listing every such row."""
    values, guarantees = pooled
    out_values = np.empty(len(channels))
    out_guarantees: list[CoverageGuarantee] = []
    out_strata: list[Stratum] = []
    problems: list[str] = []
    bins_of_row = _row_bins(thresholds, channels, row_groups, features)
    for row, channel in enumerate(channels):
        answer, problem = _row_answer(thresholds, refusal, int(channel), row_groups[row], bins_of_row[row])
        if problem is not None and refusal is None:
            problem = f"instances[{int(row_instances[row])}]: {problem}"
        if problem is None:
            out_values[row] = answer.threshold
            out_guarantees.append(answer.guarantee)
            out_strata.append(answer.stratum)
            continue
        problems.append(problem)
        out_values[row] = values[channel]
        out_guarantees.append(guarantees[channel])
        out_strata.append(Stratum("pooled", fallback=problem))
    if problems and fallback != "pooled":
        unique = list(dict.fromkeys(problems))
        raise InvalidInput(
            "; ".join(unique[:5]) + ' (or set group_fallback="pooled" to use the pooled threshold there)',
            errors=unique,
        )
    return RowAnswers(out_values, out_guarantees, out_strata)


def _row_bins(thresholds, channels, row_groups, features) -> np.ndarray:
    """The difficulty bin of every row (0 when not stratified by difficulty or not answerable),
    assigned at once for all rows of one keypoint and group."""
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


def _row_answer(thresholds, refusal, channel, group, bin_index) -> tuple[StratumAnswer | None, str | None]:
    if thresholds is None:
        return None, refusal
    key = _key(thresholds, group)
    if key is None:
        known = ", ".join(repr(g) for g in thresholds.groups)
        named = "names no group" if group is None else f"group {group!r} is unknown to this version"
        return None, f"{named} (known groups: {known})"
    if channel not in thresholds.answers:
        return None, f"calibration version has no scores for keypoint channel {channel}"
    answer = thresholds.answers[channel][key][bin_index]
    if answer.guarantee.unbounded:
        stratum = answer.stratum
        where = "" if stratum.group is None else f" of group {stratum.group!r}"
        where += "" if stratum.bin is None else f" (difficulty bin {stratum.bin})"
        guarantee = answer.guarantee
        if guarantee.delta is None:
            asked = f"epsilon {guarantee.epsilon:g} (needs n >= {_least_n(guarantee.epsilon)})"
        else:
            asked = f"epsilon {guarantee.epsilon:g} with delta {guarantee.delta:g}"
        return None, (
            f"the stratum{where} has n = {guarantee.n} calibration scores for keypoint channel {channel}:"
            f" too few for {asked}"
        )
    return answer, None


def _least_n(epsilon: float) -> int:
    """The smallest n with t = floor((n + 1) eps) >= 1 (a bounded threshold)."""
    n = max(0, math.ceil(1 / epsilon) - 2)
    while coverage_guarantee(n, epsilon).t == 0:
        n += 1
    return n
