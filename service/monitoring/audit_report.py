"""The report of a coverage audit: each figure's coverage against Theorem 1, flags and advice. Keypoint
scope: a keypoint's figure exact, an object's and the overall one pooled. Object scope: an instance counts
when all its keypoints are labeled, covered when all are in their sets. Flags: Holm over the overall
figures and over all others at ``FAMILY_ALPHA / 2`` each: any flag on a valid calibration <= ``FAMILY_ALPHA``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration_store import ScoreTable
from service.calibration.scoring import NONCONFORMITY_KINDS
from service.conformal import object_scores
from service.detector.manifest import Manifest
from service.monitoring.coverage_law import (
    BAND_LEVEL,
    FAMILY_ALPHA,
    RECALIBRATION_TOLERANCE,
    CoverageTest,
    coverage_test,
    pooled_test,
    recalibration_size,
)
from service.monitoring.multiple_testing import holm_adjusted

SCOPES = ("keypoint", "object")
#: the flags' two families, each Holm-corrected at FAMILY_ALPHA / 2: the overall figures, so that the
#: headline is not drowned among hundreds of keypoint figures, and every other figure
FAMILIES = ("overall", "others")
DEFAULT_EPSILONS = (0.05, 0.1, 0.2)

#: (kind, scope, epsilon) -> (threshold per channel, calibration n per channel)
ThresholdLookup = Callable[[str, str, float], tuple[np.ndarray, Sequence[int]]]


@dataclass
class _Unit:
    """One exact figure and its labeled and covered counts per audited image."""

    test: CoverageTest
    figure: dict[str, Any]
    labeled: np.ndarray
    covered: np.ndarray


def audit_report(
    table: ScoreTable,
    manifest: Manifest,
    thresholds: ThresholdLookup,
    epsilons: Sequence[float],
    version: int,
) -> dict[str, Any]:
    """The audit report (plain JSON) of the audited instances' scores ``table``."""
    sections, family = [], []  # family: (p-value, figure, overall) of every figure with instances
    images = _image_rows(table)
    names = {spec.index: spec.name for spec in manifest.keypoints}
    for kind in NONCONFORMITY_KINDS:
        for epsilon in epsilons:
            for scope in SCOPES:
                section = _section(table, images, names, thresholds, (kind, scope, epsilon))
                sections.append({"nonconformity": kind, "epsilon": epsilon, "scope": scope, **section})
                pooled = section["objects"] if scope == "keypoint" else []
                exact = section["keypoints"] if scope == "keypoint" else section["objects"]
                family += [(f, False) for f in (*exact, *pooled) if f["m"] > 0]
                family += [(section["overall"], True)] if section["overall"]["m"] > 0 else []
    for overall in (True, False):
        members = [figure for figure, is_overall in family if is_overall == overall]
        adjusted = np.minimum(1.0, len(FAMILIES) * holm_adjusted([f["p_value"] for f in members]))
        for figure, value in zip(members, adjusted.tolist(), strict=True):
            figure["adjusted_p_value"], figure["flagged"] = value, value <= FAMILY_ALPHA
    flagged = flagged_figures(sections)
    return {
        "version": version,
        "band_level": BAND_LEVEL,
        "correction": "holm",
        "family_alpha": FAMILY_ALPHA,
        "tests": len(family),
        "instances": table.n_instances,
        "passed": not flagged,
        "flagged": flagged,
        "sections": sections,
        "advice": advice(version, flagged, epsilons, len(family)),
    }


def _image_rows(table: ScoreTable) -> tuple[int, list[np.ndarray]]:
    """How many images, and each block's rows' image (refs are "batch:image:annotation")."""
    index: dict[str, int] = {}
    rows = [
        np.array([index.setdefault(ref.rsplit(":", 1)[0], len(index)) for ref in b.instance_refs], dtype=int)
        for b in table.objects
    ]
    return len(index), rows


def _section(
    table: ScoreTable,
    images: tuple[int, list[np.ndarray]],
    names: dict[int, str],
    thresholds: ThresholdLookup,
    query: tuple[str, str, float],
) -> dict[str, Any]:
    """One scope's figures: exact per keypoint or object, pooled per object and overall."""
    (kind, scope, epsilon), (values, counts) = query, thresholds(*query)
    keypoints, objects, units = [], [], []
    for block, image in zip(table.objects, images[1], strict=True):
        scores = block.scores[kind]
        if scope == "keypoint":
            channels = [int(c) for c in block.keypoint_ids]
            columns = [(scores[:, i], c, {"keypoint": names[c], "index": c}) for i, c in enumerate(channels)]
        else:  # one threshold and n for all of the object's channels
            columns = [(object_scores(scores), int(block.keypoint_ids[0]), {})]
        own = []
        for column, channel, where in columns:
            labeled = ~np.isnan(column)
            covered = labeled & (np.nan_to_num(column, nan=np.inf) <= values[channel])
            test = coverage_test(int(covered.sum()), int(labeled.sum()), int(counts[channel]), epsilon)
            figure = {"object": block.object_name, **where, **figure_of(test)}
            counted = [np.bincount(image[rows], minlength=images[0]) for rows in (labeled, covered)]
            own.append(_Unit(test, figure, *counted))
        units += own
        if scope == "keypoint":
            keypoints += [unit.figure for unit in own]
            objects.append({"object": block.object_name, **pooled_figure(own)})
        else:
            objects += [unit.figure for unit in own]
    return {"overall": pooled_figure(units), "objects": objects, "keypoints": keypoints}


def figure_of(test: CoverageTest) -> dict[str, Any]:
    """An exact figure: the coverage, its Beta-Binomial band and p-value (adjusted later)."""
    return {
        "m": test.m,
        "covered": test.covered,
        "coverage": test.coverage,
        "promised": 1.0 - test.epsilon,
        "band": None if test.m == 0 else [test.band[0] / test.m, test.band[1] / test.m],
        "in_band": test.in_band,
        "n": test.n,
        "rank": test.rank,
        "p_value": test.p_value,
        "adjusted_p_value": None,
        "flagged": False,
    }


def pooled_figure(units: Sequence[_Unit]) -> dict[str, Any]:
    """A pooled figure: its band and p-value under the dependence of an image's keypoints."""
    tested = [u for u in units if u.test.m > 0]
    counts = [
        np.stack([getattr(u, name) for u in tested], axis=1) if tested else np.zeros((0, 0))
        for name in ("labeled", "covered")
    ]
    pooled = pooled_test([u.test for u in tested], *counts)
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
    """Every flagged figure, most significant first, with where it is."""
    flagged = []
    for section in sections:
        where = {name: section[name] for name in ("nonconformity", "epsilon", "scope")}
        figures = [section["overall"], *section["objects"], *section["keypoints"]]
        flagged.extend({**where, **figure} for figure in figures if figure.get("flagged"))
    return sorted(flagged, key=lambda figure: figure["p_value"])


def advice(version: int, flagged: Sequence[dict[str, Any]], epsilons: Sequence[float], tests: int) -> str:
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
