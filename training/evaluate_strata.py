"""Pooled against Mondrian (per-stratum) calibration on held-out renders: prints a Markdown section.

    python -m training.evaluate_strata --model models/lmo-synth-unet \\
        --calibration data/lmo_synth/calibration_2027 \\
        --heldout data/lmo_synth/heldout_default --heldout data/lmo_synth/heldout_heavy \\
        --conditional-sample 1500 >> docs/evaluation.md

For each held-out split and nonconformity function: coverage of occluded (COCO v = 1) and
visible (v = 2) keypoints, the median set area of each (image pixels^2; the ratio to pooled),
and each stratum's coverage against its band [1 - eps, 1 - eps + 1/(n_g + 1)]. Under
exchangeability the covered count of a stratum's m held-out keypoints follows
BetaBinomial(m, n_g + 1 - t, t) (eq. 5 then binomial sampling; ``service.conformal.laws``),
so a stratum is also tested against that law: one under-covered beyond chance is one whose
count falls below its central 95% interval (about 2.5% of strata do so by chance alone).

The strata are the service's (``service.conformal.strata``: quantile bins per keypoint,
fitted on the calibration instances' label-free heatmap features, at least
``min_instances`` per bin); rows come from ``keypoint-service evaluate``'s inference pass.
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

from service.calibration.coco import load_coco_batch
from service.conformal import calibrate
from service.conformal.features import heatmap_features
from service.conformal.laws import betabinomial_pmf, central_interval
from service.conformal.strata import DifficultySpec, fit_difficulty_bins, stratum_calibrations
from service.detector.session import Detector
from service.evaluation.rows import Rows, collect_rows

OCCLUDED, VISIBLE = 1, 2
MAX_IMAGE_PIXELS = 40_000_000
KINDS = ("cov", "var")


@dataclass(frozen=True)
class Grouping:
    """How rows are stratified: a name and, per keypoint, (calibration rows, test rows) -> strata."""

    name: str
    strata: Callable[[Rows, np.ndarray, Rows, np.ndarray], tuple[np.ndarray, np.ndarray, int]] | None


def difficulty(spec: DifficultySpec) -> Callable:
    def strata(cal: Rows, cal_rows: np.ndarray, test: Rows, test_rows: np.ndarray):
        fitted = fit_difficulty_bins(_features(cal, cal_rows), spec)
        return (
            fitted.assign(_features(cal, cal_rows)),
            fitted.assign(_features(test, test_rows)),
            fitted.n_bins,
        )

    return strata


def _oracle(cal: Rows, cal_rows: np.ndarray, test: Rows, test_rows: np.ndarray):
    return (
        (cal.visibility[cal_rows] == OCCLUDED).astype(int),
        (test.visibility[test_rows] == OCCLUDED).astype(int),
        2,
    )


_FEATURE_CACHE: dict[int, dict[str, np.ndarray]] = {}


def _features(data: Rows, rows: np.ndarray) -> dict[str, np.ndarray]:
    if id(data) not in _FEATURE_CACHE:
        _FEATURE_CACHE[id(data)] = heatmap_features(data.statistics)
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
        ),
        Grouping("oracle: true visibility (not available at prediction)", _oracle),
    ]


def conditional_threshold(
    features: np.ndarray, scores: np.ndarray, test: np.ndarray, epsilon: float
) -> float:
    """Conditional calibration over the linear functions of ``features`` (Gibbs, Cherian & Candès,
    "Conformal prediction with conditional guarantees", 2023), its conservative form: the fitted
    (1 - eps)-quantile at the test point of a quantile regression over the calibration scores and
    the test point with an infinite score. Their set {S <= g_S(x)} is contained in {S <= g_inf(x)},
    so coverage >= 1 - eps holds under every covariate shift f(x) >= 0 in the class."""
    from scipy.optimize import linprog  # only this evaluation needs scipy

    n, d = features.shape
    tau = 1 - epsilon
    # min sum tau u_i + (1 - tau) v_i - tau test.beta  s.t.  scores - features beta = u - v, u, v >= 0
    cost = np.concatenate([-tau * test, np.full(n, tau), np.full(n, 1 - tau)])
    equalities = np.hstack([features, np.eye(n), -np.eye(n)])
    bounds = [(None, None)] * d + [(0, None)] * (2 * n)
    fit = linprog(cost, A_eq=equalities, b_eq=scores, bounds=bounds, method="highs")
    return float(test @ fit.x[:d]) if fit.status == 0 else np.inf


def _basis(data: Rows, rows: np.ndarray) -> np.ndarray:
    features = _features(data, rows)
    return np.column_stack(
        [np.ones(rows.size), np.log(features["gamma"]), np.log(features["peak_probability"])]
    )


def conditional_lines(cal: Rows, test: Rows, kind: str, epsilon: float, sample: int) -> list[str]:
    """One table row: conditional calibration on ``sample`` random labeled held-out keypoints."""
    rows = np.random.default_rng(0).choice(np.flatnonzero(test.labeled), sample, replace=False)
    thresholds, pooled = np.empty(rows.size), np.empty(rows.size)
    for channel in np.unique(test.channel[rows]):
        cal_rows = np.flatnonzero((cal.channel == channel) & cal.labeled)
        mine = np.flatnonzero(test.channel[rows] == channel)
        basis, scores = _basis(cal, cal_rows), cal.scores[kind][cal_rows]
        pooled[mine] = calibrate(scores, epsilon).threshold
        for i, point in zip(mine, _basis(test, rows[mine]), strict=True):
            thresholds[i] = conditional_threshold(basis, scores, point, epsilon)
    covered = test.scores[kind][rows] <= thresholds
    area, pooled_area = (_areas(test, kind, _on_rows(test, rows, t))[rows] for t in (thresholds, pooled))
    occluded, visible = test.visibility[rows] == OCCLUDED, test.visibility[rows] == VISIBLE
    shares = " | ".join(
        f"{c:.3f}" for c in (covered[occluded].mean(), covered[visible].mean(), covered.mean())
    )
    ratios = [np.median(area[m]) / np.median(pooled_area[m]) for m in (visible, occluded)]
    return [
        f"| conditional calibration over a + b log gamma + c log p* (Gibbs, Cherian & Candès 2023;"
        f" conservative form; {sample} random keypoints) | {shares} | {np.median(area[visible]):.0f}"
        f" ({ratios[0]:.2f}) | {ratios[1]:.2f} | | | |"
    ]


def _on_rows(data: Rows, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
    full = np.full(data.channel.size, np.nan)
    full[rows] = values
    return full


@dataclass
class Outcome:
    covered: np.ndarray  # (R,) bool over labeled test rows
    area: np.ndarray  # (R,) set area, image pixels^2
    strata: list[tuple[int, int, int, int]]  # (n, t, m, covered) per stratum with test rows


def evaluate(cal: Rows, test: Rows, kind: str, grouping: Grouping, epsilon: float) -> Outcome:
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


def _areas(data: Rows, kind: str, thresholds: np.ndarray) -> np.ndarray:
    """Area of each row's set in image pixels^2 (heatmap area over |det| of the crop affine)."""
    statistics = data.statistics
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
            under += covered < central_interval(betabinomial_pmf(m, n + 1 - t, t), 0.95)[0]
    return len(strata), within, under


def split_section(
    name: str, cal: Rows, test: Rows, spec: DifficultySpec, epsilon: float, sample: int = 0
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
        lines += [
            f"`{kind}`, epsilon {epsilon}:",
            "",
            "| grouping | occluded | visible | all | visible median area (px², vs pooled) |"
            " occluded median area vs pooled | strata | within band | under-covered beyond chance |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
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
        if sample:
            lines += conditional_lines(cal, test, kind, epsilon, sample)
        lines.append("")
    return lines


def _extra_occluders(folder: str) -> str:
    info = json.loads((Path(folder) / "annotations.json").read_text()).get("info", {})
    extra = int(info.get("extra_occluders", 0))
    seed = info.get("seed")
    return f"seed {seed}, " + (f"{extra} extra occluders per scene" if extra else "default occlusion")


def load_rows(folder: Path, detector: Detector) -> Rows:
    """One inference pass over a labeled COCO folder (``keypoint-service evaluate``'s rows)."""
    return collect_rows(load_coco_batch(folder, detector.manifest), detector, MAX_IMAGE_PIXELS)


def report(
    model: Path,
    calibration: Path,
    heldout: list[Path],
    epsilon: float,
    spec: DifficultySpec,
    command: str,
    sample: int = 0,
) -> str:
    detector = Detector(model, 2)
    cal = load_rows(calibration, detector)
    lines = [
        "## Mondrian strata on held-out renders",
        "",
        f"Made by `{command}`.",
        "",
        f"Calibration: {cal.images} images ({int(cal.labeled.sum())} labelled keypoints,"
        f" {np.mean(cal.visibility[cal.labeled] == OCCLUDED):.0%} occluded), the bundled calibration's"
        " renders. Thresholds per keypoint; a stratified row calibrates each stratum of each keypoint on"
        " its own calibration scores. *Within band*: held-out coverage of the stratum in"
        " [1 - eps, 1 - eps + 1/(n_g + 1)]; *under-covered beyond chance*: its covered count below the"
        " central 95% interval of BetaBinomial(m, n_g + 1 - t, t), the law it follows under exchangeability"
        " (so about 2.5% by chance alone). Areas are medians over keypoints, in image pixels².",
        "",
    ]
    for folder in heldout:
        lines += split_section(str(folder), cal, load_rows(folder, detector), spec, epsilon, sample)
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
    parser.add_argument("--epsilon", type=float, default=0.1)
    parser.add_argument("--signals", default=",".join(DifficultySpec().signals))
    parser.add_argument("--bins", type=int, default=DifficultySpec().bins)
    parser.add_argument("--min-instances", type=int, default=DifficultySpec().min_instances)
    parser.add_argument(
        "--conditional-sample",
        type=int,
        default=0,
        help="also conditional calibration (Gibbs et al. 2023) on this many random held-out"
        " keypoints (one linear program each; needs scipy)",
    )
    args = parser.parse_args(argv)
    spec = DifficultySpec(tuple(args.signals.split(",")), args.bins, args.min_instances)
    command = shlex.join(
        ["python", "-m", "training.evaluate_strata", *(sys.argv[1:] if argv is None else argv)]
    )
    print(
        report(
            args.model, args.calibration, args.heldout, args.epsilon, spec, command, args.conditional_sample
        )
    )


if __name__ == "__main__":
    main()
