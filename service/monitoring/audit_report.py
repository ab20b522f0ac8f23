"""The report of a coverage audit: the empirical coverage of a calibration version's sets on
a labeled batch, figure by figure against what Theorem 1 predicts, with the keypoints that
are significantly low flagged and what to do about it.

An instance is covered when its nonconformity score is at most the version's threshold
(the true keypoint lies in its set: the score and the set are the same inequality).
- ``keypoint`` scope (each keypoint calibrated alone, the paper): a keypoint's figure is
  exact (Beta-Binomial band, ``coverage.coverage_test``); an object's and the overall
  figures pool its keypoints, with the union-bound band (``coverage.pooled_band``).
- ``object`` scope (one threshold on the max score of an object, simultaneous coverage):
  an instance counts when all its keypoints are labeled (as in calibration) and is covered
  when all of them are in their sets; an object's figure is exact, the overall one pooled.
The flags come from Holm's step-down over every exact figure of the audit (all scores,
epsilons and scopes), so the chance that a valid calibration gets any flag is at most
``FAMILY_ALPHA``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration_store import ScoreTable
from service.conformal import object_scores
from service.detector.manifest import Manifest
from service.monitoring.coverage_law import (
    BAND_LEVEL,
    FAMILY_ALPHA,
    RECALIBRATION_TOLERANCE,
    CoverageTest,
    bonferroni_p_value,
    coverage_test,
    pooled_band,
    recalibration_size,
)
from service.monitoring.multiple_testing import holm_adjusted

SCOPES = ("keypoint", "object")
DEFAULT_EPSILONS = (0.05, 0.1, 0.2)

#: (kind, scope, epsilon) -> (threshold per channel, calibration n per channel)
ThresholdLookup = Callable[[str, str, float], tuple[np.ndarray, Sequence[int]]]


@dataclass
class _Unit:
    """One exact figure (a keypoint, or an object in object scope) and where it goes."""

    test: CoverageTest
    figure: dict[str, Any]


def audit_report(
    table: ScoreTable,
    manifest: Manifest,
    thresholds: ThresholdLookup,
    kinds: Sequence[str],
    epsilons: Sequence[float],
    version: int,
) -> dict[str, Any]:
    """The audit report (plain JSON) of the audited instances' scores ``table``."""
    sections, units = [], []
    for kind in kinds:
        for epsilon in epsilons:
            for scope in SCOPES:
                values, counts = thresholds(kind, scope, epsilon)
                build = _keypoint_section if scope == "keypoint" else _object_section
                section, section_units = build(table, manifest, kind, values, counts, epsilon)
                sections.append({"nonconformity": kind, "epsilon": epsilon, "scope": scope, **section})
                units.extend(section_units)
    tested = [unit for unit in units if unit.test.m > 0]
    for unit, adjusted in zip(tested, holm_adjusted([u.test.p_value for u in tested]).tolist(), strict=True):
        unit.figure["adjusted_p_value"] = adjusted
        unit.figure["flagged"] = adjusted <= FAMILY_ALPHA
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


def _keypoint_section(
    table: ScoreTable,
    manifest: Manifest,
    kind: str,
    values: np.ndarray,
    counts: Sequence[int],
    epsilon: float,
) -> tuple[dict[str, Any], list[_Unit]]:
    names = {spec.index: spec.name for spec in manifest.keypoints}
    keypoints, objects, units = [], [], []
    for block in table.objects:
        own = []
        for column, channel in enumerate(int(c) for c in block.keypoint_ids):
            scores = block.scores[kind][:, column]
            labeled = scores[~np.isnan(scores)]
            covered = int(np.count_nonzero(labeled <= values[channel]))
            test = coverage_test(covered, int(labeled.size), int(counts[channel]), epsilon)
            figure = {
                "object": block.object_name,
                "keypoint": names[channel],
                "index": channel,
                **figure_of(test),
            }
            keypoints.append(figure)
            own.append(test)
            units.append(_Unit(test, figure))
        objects.append({"object": block.object_name, **pooled_figure(own)})
    overall = pooled_figure([unit.test for unit in units])
    return {"overall": overall, "objects": objects, "keypoints": keypoints}, units


def _object_section(
    table: ScoreTable,
    manifest: Manifest,
    kind: str,
    values: np.ndarray,
    counts: Sequence[int],
    epsilon: float,
) -> tuple[dict[str, Any], list[_Unit]]:
    objects, units = [], []
    for block in table.objects:
        channel = int(block.keypoint_ids[0])  # one threshold and n for all of the object's channels
        worst = object_scores(block.scores[kind])
        complete = worst[~np.isnan(worst)]  # instances with every keypoint labeled
        covered = int(np.count_nonzero(complete <= values[channel]))
        test = coverage_test(covered, int(complete.size), int(counts[channel]), epsilon)
        figure = {"object": block.object_name, **figure_of(test)}
        objects.append(figure)
        units.append(_Unit(test, figure))
    overall = pooled_figure([unit.test for unit in units])
    return {"overall": overall, "objects": objects, "keypoints": []}, units


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


def pooled_figure(tests: Sequence[CoverageTest]) -> dict[str, Any]:
    """A pooled figure: union-bound band and the Bonferroni global p-value of its units."""
    m = sum(t.m for t in tests)
    covered = sum(t.covered for t in tests)
    low, high = pooled_band([t for t in tests if t.m > 0])
    epsilon = tests[0].epsilon if tests else None
    return {
        "m": m,
        "covered": covered,
        "coverage": None if m == 0 else covered / m,
        "promised": None if epsilon is None else 1.0 - epsilon,
        "band": None if m == 0 else [low / m, high / m],
        "in_band": low <= covered <= high,
        "p_value": bonferroni_p_value([t for t in tests if t.m > 0]),
    }


def flagged_figures(sections: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every flagged exact figure, most significant first, with where it is."""
    flagged = []
    for section in sections:
        where = {name: section[name] for name in ("nonconformity", "epsilon", "scope")}
        units = section["keypoints"] if section["scope"] == "keypoint" else section["objects"]
        flagged.extend({**where, **unit} for unit in units if unit.get("flagged"))
    return sorted(flagged, key=lambda figure: figure["p_value"])


def advice(version: int, flagged: Sequence[dict[str, Any]], epsilons: Sequence[float], tests: int) -> str:
    """What the operator should do, in words."""
    if not flagged:
        return (
            f"Version {version} holds on this batch: no figure is significantly below its promised"
            f" coverage (Holm over {tests} tests, family-wise error {FAMILY_ALPHA:g}). About"
            f" {1 - BAND_LEVEL:.0%} of the figures may fall outside their {BAND_LEVEL:.0%} band by chance."
        )
    objects = sorted({figure["object"] for figure in flagged})
    keypoints = sorted({figure["keypoint"] for figure in flagged if "keypoint" in figure})
    needed = ", ".join(f"{recalibration_size(e)} at epsilon {e:g}" for e in sorted(epsilons))
    where = f"keypoints {', '.join(keypoints)}" if keypoints else f"objects {', '.join(objects)}"
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
