"""The report of a coverage audit: the empirical coverage of a calibration version's sets on
a labeled batch, figure by figure against what Theorem 1 predicts, with the keypoints that
are significantly low flagged and what to do about it.

An instance is covered when its nonconformity score is at most the version's threshold
(the true keypoint lies in its set: the score and the set are the same inequality).
- ``keypoint`` scope (each keypoint calibrated alone, the paper): a keypoint's figure is
  exact (Beta-Binomial band, ``coverage_law.coverage_test``); an object's and the overall
  figures pool its keypoints (``coverage_law.pooled_test``: the calibration's spread with the
  units perfectly correlated, the images' spread cluster-robust, one image one cluster).
- ``object`` scope (one threshold on the max score of an object, simultaneous coverage):
  an instance counts when all its keypoints are labeled (as in calibration) and is covered
  when all of them are in their sets; an object's figure is exact, the overall one pooled.
The flags come from Holm's step-down over every figure of the audit, exact and pooled (all
scores, epsilons and scopes), in two families at half of ``FAMILY_ALPHA`` each (the overall
figures; all others), so the chance that a valid calibration gets any flag is at most
``FAMILY_ALPHA`` (up to the pooled figures' normal approximation).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from calibration_store import ScoreTable
from service.conformal import object_scores
from service.detector.manifest import Manifest
from service.monitoring.coverage_law import (
    BAND_LEVEL,
    FAMILY_ALPHA,
    RECALIBRATION_TOLERANCE,
    CoverageTest,
    PooledTest,
    coverage_test,
    pooled_test,
    recalibration_size,
)
from service.monitoring.multiple_testing import holm_adjusted

SCOPES = ("keypoint", "object")
#: the flags' two families, each Holm-corrected at FAMILY_ALPHA / 2 (Bonferroni between them): the
#: overall figures (one per score, epsilon and scope), and every other figure, so that the headline
#: figure is not drowned among the hundreds of keypoint figures
FAMILIES = ("overall", "others")
DEFAULT_EPSILONS = (0.05, 0.1, 0.2)

#: (kind, scope, epsilon) -> (threshold per channel, calibration n per channel)
ThresholdLookup = Callable[[str, str, float], tuple[np.ndarray, Sequence[int]]]


@dataclass
class _Unit:
    """One exact figure (a keypoint, or an object in object scope), where it goes, and its labeled
    and covered counts per audited image."""

    test: CoverageTest
    figure: dict[str, Any]
    labeled: np.ndarray
    covered: np.ndarray


@dataclass
class _Flaggable:
    """A figure of the flag families: its p-value, where its flag goes, whether it is overall."""

    p_value: float
    figure: dict[str, Any]
    overall: bool = False


def audit_report(
    table: ScoreTable,
    manifest: Manifest,
    thresholds: ThresholdLookup,
    kinds: Sequence[str],
    epsilons: Sequence[float],
    version: int,
) -> dict[str, Any]:
    """The audit report (plain JSON) of the audited instances' scores ``table``."""
    sections, family = [], []
    audited = _Audited(table, _image_rows(table), {spec.index: spec.name for spec in manifest.keypoints})
    for kind in kinds:
        for epsilon in epsilons:
            for scope in SCOPES:
                values, counts = thresholds(kind, scope, epsilon)
                build = _keypoint_section if scope == "keypoint" else _object_section
                section, tested = build(audited, kind, values, counts, epsilon)
                sections.append({"nonconformity": kind, "epsilon": epsilon, "scope": scope, **section})
                family.extend(tested)
    for overall in (True, False):
        members = [f for f in family if f.overall == overall]
        adjusted = np.minimum(1.0, len(FAMILIES) * holm_adjusted([f.p_value for f in members]))
        for member, value in zip(members, adjusted.tolist(), strict=True):
            member.figure["adjusted_p_value"] = value
            member.figure["flagged"] = value <= FAMILY_ALPHA
    tested = family
    flagged = flagged_figures(sections)
    return {
        "version": version,
        "band_level": BAND_LEVEL,
        "correction": "holm",
        "family_alpha": FAMILY_ALPHA,
        "tests": len(tested),
        "instances": table.n_instances,
        "passed": not flagged,
        "flagged": flagged,
        "sections": sections,
        "advice": advice(version, flagged, epsilons, len(tested)),
    }


class _Audited(NamedTuple):
    """What every section reads: the audited scores, their image rows, the keypoints' names."""

    table: ScoreTable
    images: tuple[int, list[np.ndarray]]
    names: dict[int, str]


def _image_rows(table: ScoreTable) -> tuple[int, list[np.ndarray]]:
    """How many images the instances come from, and each block's rows' image (0..images-1).

    Instances are referenced "batch:image:annotation" (service/calibration/scoring.py)."""
    index: dict[str, int] = {}
    rows = [
        np.array(
            [index.setdefault(ref.rsplit(":", 1)[0], len(index)) for ref in block.instance_refs], dtype=int
        )
        for block in table.objects
    ]
    return len(index), rows


def _unit(
    test: CoverageTest,
    figure: dict[str, Any],
    image: np.ndarray,
    labeled: np.ndarray,
    covered: np.ndarray,
    images: int,
) -> _Unit:
    return _Unit(
        test,
        figure,
        np.bincount(image[labeled], minlength=images),
        np.bincount(image[covered], minlength=images),
    )


def _keypoint_section(
    audited: _Audited, kind: str, values: np.ndarray, counts: Sequence[int], epsilon: float
) -> tuple[dict[str, Any], list[_Flaggable]]:
    table, images, names = audited
    keypoints, objects, units = [], [], []
    for block, image in zip(table.objects, images[1], strict=True):
        own = []
        for column, channel in enumerate(int(c) for c in block.keypoint_ids):
            scores = block.scores[kind][:, column]
            labeled = ~np.isnan(scores)
            covered = labeled & (np.nan_to_num(scores, nan=np.inf) <= values[channel])
            test = coverage_test(int(covered.sum()), int(labeled.sum()), int(counts[channel]), epsilon)
            figure = {
                "object": block.object_name,
                "keypoint": names[channel],
                "index": channel,
                **figure_of(test),
            }
            keypoints.append(figure)
            own.append(_unit(test, figure, image, labeled, covered, images[0]))
        objects.append({"object": block.object_name, **pooled_figure(own)})
        units.extend(own)
    overall = pooled_figure(units)
    return {"overall": overall, "objects": objects, "keypoints": keypoints}, _family(units, objects, overall)


def _family(
    units: Sequence[_Unit], pooled: Sequence[dict[str, Any]], overall: dict[str, Any]
) -> list[_Flaggable]:
    """The figures a section adds to the flag families (those with instances): its exact
    figures, its pooled objects (keypoint scope) and its overall figure."""
    members = [_Flaggable(u.test.p_value, u.figure) for u in units if u.test.m > 0]
    members += [_Flaggable(f["p_value"], f) for f in pooled if f["m"] > 0]
    return members + ([_Flaggable(overall["p_value"], overall, overall=True)] if overall["m"] > 0 else [])


def _object_section(
    audited: _Audited, kind: str, values: np.ndarray, counts: Sequence[int], epsilon: float
) -> tuple[dict[str, Any], list[_Flaggable]]:
    table, images, _ = audited
    objects, units = [], []
    for block, image in zip(table.objects, images[1], strict=True):
        channel = int(block.keypoint_ids[0])  # one threshold and n for all of the object's channels
        worst = object_scores(block.scores[kind])
        complete = ~np.isnan(worst)  # instances with every keypoint labeled
        covered = complete & (np.nan_to_num(worst, nan=np.inf) <= values[channel])
        test = coverage_test(int(covered.sum()), int(complete.sum()), int(counts[channel]), epsilon)
        figure = {"object": block.object_name, **figure_of(test)}
        objects.append(figure)
        units.append(_unit(test, figure, image, complete, covered, images[0]))
    overall = pooled_figure(units)
    return {"overall": overall, "objects": objects, "keypoints": []}, _family(units, [], overall)


def figure_of(test: CoverageTest) -> dict[str, Any]:
    """An exact figure: the coverage, its Beta-Binomial band and p-value (adjusted later)."""
    band = test.band_coverage
    return {
        "m": test.m,
        "covered": test.covered,
        "coverage": test.coverage,
        "promised": 1.0 - test.epsilon,
        "band": None if band is None else list(band),
        "in_band": test.in_band,
        "n": test.n,
        "rank": test.rank,
        "p_value": test.p_value,
        "adjusted_p_value": None,
        "flagged": False,
    }


def pooled_figure(units: Sequence[_Unit]) -> dict[str, Any]:
    """A pooled figure: its band and p-value under the dependence of an image's keypoints
    (``coverage_law.pooled_test``), its flag from Holm's family."""
    tested = [u for u in units if u.test.m > 0]
    pooled: PooledTest = pooled_test(
        [u.test for u in tested],
        np.stack([u.labeled for u in tested], axis=1) if tested else np.zeros((0, 0)),
        np.stack([u.covered for u in tested], axis=1) if tested else np.zeros((0, 0)),
    )
    epsilon = units[0].test.epsilon if units else None
    return {
        "m": pooled.m,
        "covered": pooled.covered,
        "coverage": pooled.coverage,
        "promised": None if epsilon is None else 1.0 - epsilon,
        "expected": pooled.expected,
        "band": None if pooled.m == 0 else list(pooled.band),
        "in_band": pooled.in_band,
        "p_value": pooled.p_value,
        "adjusted_p_value": None,
        "flagged": False,
    }


def flagged_figures(sections: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every flagged exact figure, most significant first, with where it is."""
    flagged = []
    for section in sections:
        where = {name: section[name] for name in ("nonconformity", "epsilon", "scope")}
        figures = [section["overall"], *section["objects"], *section["keypoints"]]
        flagged.extend({**where, **figure} for figure in figures if figure.get("flagged"))
    return sorted(flagged, key=lambda figure: figure["p_value"])


def advice(version: int, flagged: Sequence[dict[str, Any]], epsilons: Sequence[float], tests: int) -> str:
    """What the operator should do, in words."""
    if not flagged:
        return (
            f"Version {version} holds on this batch: no figure is significantly below its promised"
            f" coverage (Holm over {tests} tests, family-wise error {FAMILY_ALPHA:g}). About"
            f" {1 - BAND_LEVEL:.0%} of the figures may fall outside their {BAND_LEVEL:.0%} band by chance."
        )
    objects = sorted({figure["object"] for figure in flagged if "object" in figure})
    keypoints = sorted({figure["keypoint"] for figure in flagged if "keypoint" in figure})
    needed = ", ".join(f"{recalibration_size(e)} at epsilon {e:g}" for e in sorted(epsilons))
    where = (
        f"keypoints {', '.join(keypoints)}"
        if keypoints
        else f"objects {', '.join(objects)}"
        if objects
        else "the overall figures"
    )
    objects = objects or ["every object"]
    return (
        f"Version {version} does not hold on images like these: {len(flagged)} figures are"
        f" significantly below their promised coverage (Holm over {tests} tests, family-wise error"
        f" {FAMILY_ALPHA:g}), at {where}. Their sets are too small for such images, whatever"
        " coverage_lower_bound the responses state. Recalibrate with labeled images like the audited"
        " ones (same cameras, scenes, occlusion and object sizes): upload them with POST"
        f" /v1/admin/calibrations (append_to={version} keeps the present images if both kinds are served),"
        f" with at least this many labeled instances per keypoint of {', '.join(objects)}: {needed}"
        f" (the n whose conditional coverage stays above 1 - epsilon - {RECALIBRATION_TOLERANCE:g} with"
        f" {BAND_LEVEL:.0%} probability; 1/(n+1) <= epsilon is the bare minimum for bounded sets)."
        " Then audit the new version on other labeled images of that kind, never on the ones it was"
        " calibrated with, before activating it."
    )
