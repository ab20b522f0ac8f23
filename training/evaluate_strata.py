"""Pooled against Mondrian (per-stratum) calibration on held-out renders: prints a Markdown section.

    python -m training.evaluate_strata --model models/lmo-synth-unet \\
        --calibration data/lmo_synth/calibration \\
        --heldout data/lmo_synth/heldout_default --heldout data/lmo_synth/heldout_heavy \\
        > docs/strata-evaluation.md

For each held-out split and nonconformity function: coverage of occluded (COCO v = 1) and
visible (v = 2) keypoints, the median set area of each (image pixels^2; the ratio to pooled),
and each stratum's coverage against its band [1 - eps, 1 - eps + 1/(n_g + 1)]. Under
exchangeability the covered count of a stratum's m held-out keypoints follows
BetaBinomial(m, n_g + 1 - t, t) (eq. 5 then binomial sampling), so a stratum is also
tested against that law: one under-covered beyond chance is one whose count falls in its
lower 2.5% tail (about 2.5% of strata do so by chance alone).

The strata are the service's (``service.conformal.strata``: quantile bins per keypoint,
fitted on the calibration instances' label-free heatmap features, at least
``min_instances`` per bin); inference is cached as for ``training.evaluate_conformal``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

from service.conformal import calibrate
from service.conformal.features import heatmap_features
from service.conformal.strata import DifficultySpec, fit_difficulty_bins, stratum_calibrations
from service.detector.runtime import Detector
from training.evidence.inference import SplitData, load_split

OCCLUDED, VISIBLE = 1, 2
KINDS = ("cov", "var")


@dataclass(frozen=True)
class Grouping:
    """How rows are stratified: a name and, per keypoint, (calibration rows, test rows) -> strata."""

    name: str
    strata: (
        Callable[[SplitData, np.ndarray, SplitData, np.ndarray], tuple[np.ndarray, np.ndarray, int]] | None
    )


def difficulty(spec: DifficultySpec) -> Callable:
    def strata(cal: SplitData, cal_rows: np.ndarray, test: SplitData, test_rows: np.ndarray):
        fitted = fit_difficulty_bins(_features(cal, cal_rows), spec)
        return (
            fitted.assign(_features(cal, cal_rows)),
            fitted.assign(_features(test, test_rows)),
            fitted.n_bins,
        )

    return strata


def _oracle(cal: SplitData, cal_rows: np.ndarray, test: SplitData, test_rows: np.ndarray):
    return (
        (cal.visibility[cal_rows] == OCCLUDED).astype(int),
        (test.visibility[test_rows] == OCCLUDED).astype(int),
        2,
    )


_FEATURE_CACHE: dict[int, dict[str, np.ndarray]] = {}


def _features(data: SplitData, rows: np.ndarray) -> dict[str, np.ndarray]:
    if id(data) not in _FEATURE_CACHE:
        _FEATURE_CACHE[id(data)] = heatmap_features(data.statistics())
    return {name: values[rows] for name, values in _FEATURE_CACHE[id(data)].items()}


def groupings(spec: DifficultySpec) -> list[Grouping]:
    signals = " x ".join("p*" if s == "peak_probability" else s for s in spec.signals)
    return [
        Grouping("pooled (today)", None),
        Grouping(
            "per keypoint, 4 quantile bins of p*", difficulty(DifficultySpec(("peak_probability",), 4, 30))
        ),
        Grouping("per keypoint, 4 quantile bins of gamma", difficulty(DifficultySpec(("gamma",), 4, 30))),
        Grouping(
            f"**per keypoint, joint {signals}, {spec.bins} bins each, n >= {spec.min_instances} per bin"
            " (the service's default)**",
            difficulty(spec),
        ),  # fmt: skip
        Grouping("oracle: true visibility (not available at prediction)", _oracle),
    ]


@dataclass
class Outcome:
    covered: np.ndarray  # (R,) bool over labeled test rows
    area: np.ndarray  # (R,) set area, image pixels^2
    strata: list[tuple[int, int, int, int]]  # (n, t, m, covered) per stratum with test rows


def evaluate(cal: SplitData, test: SplitData, kind: str, grouping: Grouping, epsilon: float) -> Outcome:
    thresholds = np.full(test.channel.size, np.nan)
    strata: list[tuple[int, int, int, int]] = []
    scores = test.scores[kind]
    for channel in np.unique(cal.channel):
        cal_rows = np.flatnonzero((cal.channel == channel) & cal.labeled)
        test_rows = np.flatnonzero(test.channel == channel)
        if grouping.strata is None:
            calibrations, test_strata = (
                [calibrate(cal.scores[kind][cal_rows], epsilon)],
                np.zeros(test_rows.size, int),
            )
        else:
            cal_strata, test_strata, count = grouping.strata(cal, cal_rows, test, test_rows)
            calibrations = stratum_calibrations(cal.scores[kind][cal_rows], cal_strata, count, epsilon)
        values = np.array([c.threshold for c in calibrations])
        thresholds[test_rows] = values[test_strata]
        for s, calibration in enumerate(calibrations):
            rows = test_rows[(test_strata == s) & test.labeled[test_rows]]
            if rows.size:
                guarantee = calibration.guarantee
                strata.append((guarantee.n, guarantee.t, rows.size, int(np.sum(scores[rows] <= values[s]))))
    labeled = test.labeled
    return Outcome(scores[labeled] <= thresholds[labeled], _areas(test, kind, thresholds)[labeled], strata)


def _areas(data: SplitData, kind: str, thresholds: np.ndarray) -> np.ndarray:
    """Area of each row's set in image pixels^2 (heatmap area over |det| of the crop affine)."""
    statistics = data.statistics()
    if kind == "cov":
        heatmap_area = np.pi * thresholds * np.sqrt(np.linalg.det(statistics.regularized_covariance))
    else:  # var: a ball of radius gamma * thr
        heatmap_area = np.pi * statistics.regularized_variance * thresholds**2
    return heatmap_area / np.abs(np.linalg.det(data.affine[:, :, :2]))


def band_summary(strata: list[tuple[int, int, int, int]], epsilon: float) -> tuple[int, int, int]:
    """(strata, within the literal band, under-covered beyond chance)."""
    within = under = 0
    for n, t, m, covered in strata:
        share = covered / m
        within += 1 - epsilon <= share <= 1 - epsilon + 1 / (n + 1)
        if t > 0:
            under += stats.betabinom(m, n + 1 - t, t).cdf(covered) < 0.025
    return len(strata), within, under


def split_section(
    name: str, cal: SplitData, test: SplitData, spec: DifficultySpec, epsilon: float
) -> list[str]:
    labeled = test.labeled
    visibility = test.visibility[labeled]
    extra = _extra_occluders(name)
    lines = [
        f"### {Path(name).name}: {test.images} images, {int(labeled.sum())} labelled keypoints,"
        f" {np.mean(visibility == OCCLUDED):.0%} occluded ({extra})",
        "",
    ]
    for kind in KINDS:
        lines += [f"`{kind}`, epsilon {epsilon}:", "",
                  "| grouping | occluded | visible | all | visible median area (px², vs pooled) |"
                  " occluded median area vs pooled | strata | within band | under-covered beyond chance |",
                  "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        pooled = None
        for grouping in groupings(spec):
            outcome = evaluate(cal, test, kind, grouping, epsilon)
            pooled = pooled or outcome
            occluded, visible = visibility == OCCLUDED, visibility == VISIBLE
            vis_area = np.median(outcome.area[visible])
            vis_ratio = vis_area / np.median(pooled.area[visible])
            occ_ratio = np.median(outcome.area[occluded]) / np.median(pooled.area[occluded])
            count, within, under = band_summary(outcome.strata, epsilon)
            covered = outcome.covered
            shares = (covered[occluded].mean(), covered[visible].mean(), covered.mean())
            coverages = " | ".join(f"{share:.3f}" for share in shares)
            lines.append(
                f"| {grouping.name} | {coverages} | {vis_area:.0f} ({vis_ratio:.2f}) | {occ_ratio:.2f}"
                f" | {count}"
                f" | {within} ({within / count:.0%}) | {under} ({under / count:.0%}) |"
            )
        lines.append("")
    return lines


def _extra_occluders(folder: str) -> str:
    info = json.loads((Path(folder) / "annotations.json").read_text()).get("info", {})
    extra = int(info.get("extra_occluders", 0))
    seed = info.get("seed")
    return f"seed {seed}, " + (f"{extra} extra occluders per scene" if extra else "default occlusion")


def report(model: Path, calibration: Path, heldout: list[Path], cache: Path, epsilon: float,
           spec: DifficultySpec, command: str) -> str:  # fmt: skip
    detector = Detector(model, 2)
    cal = load_split(calibration, detector, cache)
    lines = [
        "## Mondrian strata on held-out renders",
        "",
        f"Made by `{command}`.",
        "",
        f"Calibration: {cal.images} images ({int(cal.labeled.sum())} labelled keypoints,"
        f" {np.mean(cal.visibility[cal.labeled] == OCCLUDED):.0%} occluded), the bundled calibration's"
        " renders. Thresholds per keypoint; a stratified row calibrates each stratum of each keypoint on"
        " its own calibration scores. *Within band*: held-out coverage of the stratum in"
        " [1 - eps, 1 - eps + 1/(n_g + 1)]; *under-covered beyond chance*: its covered count in the lower"
        " 2.5% tail of BetaBinomial(m, n_g + 1 - t, t), the law it follows under exchangeability (so about"
        " 2.5% by chance alone). Areas are medians over keypoints, in image pixels².",
        "",
    ]
    for folder in heldout:
        lines += split_section(str(folder), cal, load_split(folder, detector, cache), spec, epsilon)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--calibration", type=Path, required=True, help="COCO keypoints calibration split")
    parser.add_argument(
        "--heldout", type=Path, action="append", required=True, help="held-out split (repeat)"
    )
    parser.add_argument("--cache", type=Path, default=Path("data/strata_cache"), help="inference cache")
    parser.add_argument("--epsilon", type=float, default=0.1)
    parser.add_argument("--signals", default=",".join(DifficultySpec().signals))
    parser.add_argument("--bins", type=int, default=DifficultySpec().bins)
    parser.add_argument("--min-instances", type=int, default=DifficultySpec().min_instances)
    args = parser.parse_args(argv)
    spec = DifficultySpec(tuple(args.signals.split(",")), args.bins, args.min_instances)
    command = shlex.join(
        ["python", "-m", "training.evaluate_strata", *(sys.argv[1:] if argv is None else argv)]
    )
    print(report(args.model, args.calibration, args.heldout, args.cache, args.epsilon, spec, command))


if __name__ == "__main__":
    main()
