"""Report figures (matplotlib, Agg, small PNGs): validity, re-splits, tightness, adaptiveness, baseline."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib
from PIL import Image

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from training.evidence.analysis import EPSILONS, MAIN_EPSILON, Evidence  # noqa: E402
from training.evidence.distributions import beta_pdf, betabinomial_pmf, central_interval  # noqa: E402
from training.evidence.tightness import empirical_cdf  # noqa: E402

DPI = 100
KINDS = ("peak", "var", "cov")


def save(figure: plt.Figure, path: Path) -> Path:
    """PNG at ~100 dpi, quantized to a 256-colour palette to keep the repository small."""
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    figure.savefig(buffer, dpi=DPI, bbox_inches="tight", format="png")
    plt.close(figure)
    buffer.seek(0)
    with Image.open(buffer) as image:
        image.convert("RGB").quantize(256).save(path, optimize=True)
    return path


def validity_figure(evidence: Evidence, path: Path) -> Path:
    """Histogram of per-keypoint test coverage with the Beta law and the predictive 95% band."""
    figure, axes = plt.subplots(3, 3, figsize=(11, 8.5), squeeze=False)
    for row, kind in enumerate(KINDS):
        for col, epsilon in enumerate(EPSILONS):
            _validity_panel(axes[row, col], evidence.validity[(kind, epsilon, "keypoint")])
    figure.suptitle("Per-keypoint empirical coverage on the test split (keypoint scope)")
    figure.tight_layout()
    return save(figure, path)


def _validity_panel(ax: plt.Axes, summary) -> None:
    groups = [g for g in summary.groups if g.m and not g.unbounded]
    coverage = summary.coverages()
    if not groups:
        ax.text(0.5, 0.5, "no bounded sets", ha="center", transform=ax.transAxes)
        return
    n = int(np.median([g.n for g in groups]))
    m = int(np.median([g.m for g in groups]))
    t = int(np.median([g.t for g in groups]))
    low, high = central_interval(betabinomial_pmf(m, n + 1 - t, t))
    grid = np.linspace(max(0.0, min(summary.target - 0.25, float(coverage.min()))), 1.0, 400)
    ax.axvspan(low / m, high / m, color="tab:orange", alpha=0.2, label=f"95% predictive, m={m}")
    ax.hist(
        coverage, bins=20, range=(grid[0], 1.0), density=True, color="tab:blue", alpha=0.7, label="keypoints"
    )
    ax.plot(grid, beta_pdf(grid, n + 1 - t, t), color="tab:red", label=f"Beta({n + 1 - t}, {t})")
    ax.axvline(summary.target, color="k", ls="--", lw=1)
    ax.set_title(f"{summary.kind}, eps={summary.epsilon}", fontsize=10)
    ax.set_xlabel("empirical coverage")
    ax.legend(fontsize=7, loc="upper left")


def resplit_figure(evidence: Evidence, path: Path) -> Path:
    """Fig. 2 made empirical: coverage of one keypoint over re-splits, and pooled PITs."""
    figure, axes = plt.subplots(3, 2, figsize=(10, 8.5), squeeze=False)
    for row, kind in enumerate(KINDS):
        result = evidence.resplits[(kind, MAIN_EPSILON)]
        keypoint = _median_keypoint(result.n)
        n, t = int(np.median(result.n[:, keypoint])), int(np.median(result.t[:, keypoint]))
        m = int(np.median(result.m[:, keypoint]))
        ax = axes[row, 0]
        coverage = result.coverage[:, keypoint]
        coverage = coverage[~np.isnan(coverage)]
        if coverage.size:
            ax.hist(coverage, bins=15, density=True, alpha=0.7, label=f"{result.coverage.shape[0]} re-splits")
        grid = np.linspace(max(0.0, (coverage.min() if coverage.size else 1.0) - 0.05), 1.0, 400)
        if t > 0 and m > 0:  # t = 0: unbounded sets, coverage 1, no Beta law to draw
            ax.plot(grid, beta_pdf(grid, n + 1 - t, t), color="tab:red", label=f"Beta({n + 1 - t}, {t})")
            pmf = betabinomial_pmf(m, n + 1 - t, t)
            ax.plot(np.arange(m + 1) / m, pmf * m, color="tab:orange", lw=1, label=f"BetaBinomial(m={m})/m")
        ax.set_xlim(grid[0], 1.0)
        ax.axvline(1 - MAIN_EPSILON, color="k", ls="--", lw=1)
        name = evidence.manifest.keypoints[keypoint].name
        ax.set_title(f"{kind}: keypoint {name}, eps={MAIN_EPSILON}", fontsize=10)
        ax.legend(fontsize=7, loc="upper left")
        ax = axes[row, 1]
        pits = result.pit[~np.isnan(result.pit)]
        pooled = f"KS {result.pooled_ks():.3f}" if pits.size else "no bounded sets"
        if pits.size:
            ax.hist(pits, bins=20, range=(0, 1), density=True, alpha=0.7)
        ax.axhline(1.0, color="tab:red")
        ax.set_title(f"{kind}: PIT of every keypoint and re-split ({pooled})", fontsize=10)
    figure.tight_layout()
    return save(figure, path)


def _median_keypoint(n: np.ndarray) -> int:
    means = n.mean(axis=0)
    return int(np.argmin(np.abs(means - np.median(means))))


def tightness_figure(evidence: Evidence, path: Path) -> Path:
    """Per-keypoint CDFs of radii (peak, var) and semi-axes a (solid), b (dashed) (cov)."""
    figure, axes = plt.subplots(1, 3, figsize=(13, 3.8), squeeze=False)
    channel = evidence.test.channel[evidence.test.labeled]
    colors = plt.cm.viridis(np.linspace(0, 1, evidence.manifest.num_keypoints))
    for ax, kind in zip(axes[0], KINDS, strict=True):
        sizes = evidence.sizes[(kind, MAIN_EPSILON)]
        finite = sizes.b[np.isfinite(sizes.b)]
        limit = float(np.quantile(finite, 0.98)) if finite.size else 1.0
        for k in np.unique(channel):
            ax.plot(*empirical_cdf(sizes.a[channel == k]), color=colors[k], lw=0.7)
            if kind == "cov":
                ax.plot(*empirical_cdf(sizes.b[channel == k]), color=colors[k], lw=0.7, ls="--")
        ax.set_xlim(0, limit)
        ax.set_xlabel("semi-axes a (solid), b (dashed), px" if kind == "cov" else "radius, px")
        ax.set_title(f"ICP-{kind.capitalize()}, eps={MAIN_EPSILON}", fontsize=10)
        ax.set_ylabel("CDF")
    figure.tight_layout()
    return save(figure, path)


def adaptiveness_figure(evidence: Evidence, path: Path) -> Path:
    """Equivalent radius by visibility flag, and relative area against the visible fraction."""
    test = evidence.test
    labeled = test.labeled
    visibility, fraction = test.visibility[labeled], test.visib_fract[labeled]
    relative_side = test.box_side[labeled]
    figure, axes = plt.subplots(1, 2, figsize=(12, 4))
    data, labels = [], []
    for kind in KINDS:
        radius = np.sqrt(evidence.sizes[(kind, MAIN_EPSILON)].area / np.pi)
        for flag, name in ((2, "visible"), (1, "occluded")):
            data.append(radius[(visibility == flag) & np.isfinite(radius)])
            labels.append(f"{kind}\n{name}")
    axes[0].boxplot(data, tick_labels=labels, showfliers=False)
    axes[0].set_ylabel("sqrt(area / pi), px")
    axes[0].set_title(f"Set size by COCO visibility, eps={MAIN_EPSILON}", fontsize=10)
    bins = np.linspace(np.nanmin(fraction), np.nanmax(fraction) + 1e-9, 9)
    centers = (bins[:-1] + bins[1:]) / 2
    which = np.digitize(fraction, bins) - 1
    for kind in KINDS:
        relative = evidence.sizes[(kind, MAIN_EPSILON)].area / relative_side**2
        medians = [
            np.median(relative[which == i]) if (which == i).any() else np.nan for i in range(len(centers))
        ]
        axes[1].plot(centers, medians, marker="o", label=kind)
    axes[1].set_xlabel("visib_fract of the object")
    axes[1].set_ylabel("median area / box side^2")
    axes[1].set_yscale("log")
    axes[1].legend()
    axes[1].set_title("Relative set area against the visible fraction", fontsize=10)
    figure.tight_layout()
    return save(figure, path)


def baseline_figure(evidence: Evidence, path: Path) -> Path:
    """CDF of set areas: the three ICP sets against the classification-style pixel set."""
    figure, ax = plt.subplots(figsize=(6.5, 4))
    for kind in KINDS:
        area = evidence.sizes[(kind, MAIN_EPSILON)].area
        ax.plot(*empirical_cdf(area[np.isfinite(area)]), label=f"ICP-{kind.capitalize()}")
    ax.plot(
        *empirical_cdf(evidence.baseline[MAIN_EPSILON].area), label="highest-probability pixels", color="k"
    )
    ax.set_xscale("log")
    ax.set_xlabel("set area, image px^2")
    ax.set_ylabel("CDF over test keypoints")
    ax.set_title(f"Set area, eps={MAIN_EPSILON}", fontsize=10)
    ax.legend(fontsize=8)
    figure.tight_layout()
    return save(figure, path)
