"""The evaluation's figures (matplotlib, Agg, small PNGs). matplotlib is optional (the ``evaluate``
extra): import this module only once ``service.evaluation.run.require_matplotlib`` passed."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib
from PIL import Image

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from service.calibration.scoring import NONCONFORMITY_KINDS as KINDS  # noqa: E402
from service.conformal.laws import beta_pdf, betabinomial_pmf, central_interval  # noqa: E402
from service.evaluation.coverage import ValiditySummary  # noqa: E402
from service.evaluation.sizes import empirical_cdf  # noqa: E402
from service.evaluation.summary import Evaluation  # noqa: E402

DPI = 100
#: file names under figures/, stable: docs link them
VALIDITY, BANDS, TIGHTNESS, ADAPTIVENESS = "validity.png", "bands.png", "tightness.png", "adaptiveness.png"


def save(figure: plt.Figure, path: Path) -> Path:
    """PNG at ~100 dpi, laid out tight, quantized to a 256-colour palette to keep the repository small."""
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    figure.savefig(buffer, dpi=DPI, bbox_inches="tight", format="png")
    plt.close(figure)
    buffer.seek(0)
    with Image.open(buffer) as image:
        image.convert("RGB").quantize(256).save(path, optimize=True)
    return path


def draw_figures(evaluation: Evaluation, folder: Path) -> list[Path]:
    """Every figure of the report into ``folder``; adaptiveness only when the labels carry
    both visibility flags."""
    figures = [(validity_figure, VALIDITY), (band_figure, BANDS), (tightness_figure, TIGHTNESS)]
    if evaluation.has_occlusion_flags:
        figures.append((adaptiveness_figure, ADAPTIVENESS))
    return [draw(evaluation, folder / name) for draw, name in figures]


def validity_figure(evaluation: Evaluation, path: Path) -> Path:
    """Histogram of per-keypoint coverage with the Beta law and the predictive 95% band."""
    epsilons = evaluation.epsilons
    figure, axes = plt.subplots(3, len(epsilons), figsize=(3.7 * len(epsilons), 8.5), squeeze=False)
    for row, kind in enumerate(KINDS):
        for col, epsilon in enumerate(epsilons):
            scopes = (evaluation.validity[(kind, epsilon, scope)] for scope in ("keypoint", "object"))
            _validity_panel(axes[row, col], *scopes)
    figure.suptitle(
        "Empirical coverage of the batch: per keypoint (keypoint scope, histogram) and per "
        "object (object scope, triangles)"
    )
    return save(figure, path)


def _validity_panel(ax: plt.Axes, summary: ValiditySummary, objects: ValiditySummary) -> None:
    groups = [g for g in summary.groups if g.m and not g.unbounded]
    if not groups:
        ax.text(0.5, 0.5, "no bounded sets", ha="center", transform=ax.transAxes)
        return
    coverage = np.array([g.coverage for g in groups])
    n, m, t = (int(np.median([getattr(g, name) for g in groups])) for name in "nmt")
    low, high = central_interval(betabinomial_pmf(m, n + 1 - t, t))
    lowest = min(float(coverage.min()), float(np.min(objects.coverages(), initial=1.0)))
    grid = np.linspace(max(0.0, min(summary.target - 0.25, lowest)), 1.0, 400)
    ax.axvspan(low / m, high / m, color="tab:orange", alpha=0.2, label=f"95% predictive, m={m}")
    ax.hist(
        coverage, bins=20, range=(grid[0], 1.0), density=True, color="tab:blue", alpha=0.7, label="keypoints"
    )
    ax.plot(grid, beta_pdf(grid, n + 1 - t, t), color="tab:red", label=f"Beta({n + 1 - t}, {t})")
    simultaneous, marks = objects.coverages(), {"ms": 7, "clip_on": False, "label": "objects, object scope"}
    ax.plot(simultaneous, np.zeros_like(simultaneous), "^", color="tab:green", **marks)
    ax.axvline(summary.target, color="k", ls="--", lw=1)
    ax.set_title(f"{summary.kind}, eps={summary.epsilon}", fontsize=10)
    ax.set_xlabel("empirical coverage")
    ax.legend(fontsize=7, loc="upper left")


def band_figure(evaluation: Evaluation, path: Path) -> Path:
    """Each keypoint's (object's) coverage against the 95% band its n, t and m predict."""
    epsilon, scopes = evaluation.main_epsilon, evaluation.scopes
    figure, axes = plt.subplots(3, len(scopes), figsize=(5.5 * len(scopes), 8.5), squeeze=False)
    for row, kind in enumerate(KINDS):
        for col, scope in enumerate(scopes):
            _band_panel(axes[row, col], evaluation.validity[(kind, epsilon, scope)], row == col == 0)
    figure.suptitle(f"Coverage against the theoretical 95% band for the batch size, eps={epsilon}")
    return save(figure, path)


def _band_panel(ax: plt.Axes, summary: ValiditySummary, legend: bool) -> None:
    groups = [g for g in summary.groups if g.m]
    x = np.arange(len(groups))
    bands = np.array([g.band() for g in groups]).reshape(-1, 2)
    coverage = np.array([g.coverage for g in groups])
    inside = np.array([g.inside_predictive() for g in groups], dtype=bool)
    ax.vlines(x, bands[:, 0], bands[:, 1], color="tab:orange", lw=4, alpha=0.5, label="95% band")
    ax.scatter(x[inside], coverage[inside], s=12, color="tab:blue", zorder=3, label="inside")
    ax.scatter(x[~inside], coverage[~inside], s=16, color="tab:red", marker="x", zorder=3, label="outside")
    ax.axhline(summary.target, color="k", ls="--", lw=1)
    if summary.scope == "object":
        ax.set_xticks(x, [g.name for g in groups], fontsize=8)
    else:
        ax.set_xlabel("keypoint (manifest order)")
    ax.set_ylabel("empirical coverage")
    ax.set_title(f"{summary.kind}, {summary.label} scope", fontsize=10)
    if legend:
        ax.legend(fontsize=7, loc="best")


def tightness_figure(evaluation: Evaluation, path: Path) -> Path:
    """Per-keypoint CDFs of radii (peak, var) and semi-axes a (solid), b (dashed) (cov)."""
    epsilon, rows = evaluation.main_epsilon, evaluation.rows
    figure, axes = plt.subplots(1, 3, figsize=(13, 3.8), squeeze=False)
    channel = rows.channel[rows.labeled]
    colors = plt.cm.viridis(np.linspace(0, 1, evaluation.manifest.num_keypoints))
    for ax, kind in zip(axes[0], KINDS, strict=True):
        sizes = evaluation.sizes[(kind, epsilon)]
        finite = sizes.b[np.isfinite(sizes.b)]
        limit = float(np.quantile(finite, 0.98)) if finite.size else 1.0
        for k in np.unique(channel):
            ax.plot(*empirical_cdf(sizes.a[channel == k]), color=colors[k], lw=0.7)
            if kind == "cov":
                ax.plot(*empirical_cdf(sizes.b[channel == k]), color=colors[k], lw=0.7, ls="--")
        xlabel = "semi-axes a (solid), b (dashed), px" if kind == "cov" else "radius, px"
        ax.set(xlim=(0, limit), xlabel=xlabel, ylabel="CDF")
        ax.set_title(f"ICP-{kind.capitalize()}, eps={epsilon}", fontsize=10)
    return save(figure, path)


def adaptiveness_figure(evaluation: Evaluation, path: Path) -> Path:
    """Equivalent radius by visibility flag, and relative area against the visible fraction."""
    epsilon, rows = evaluation.main_epsilon, evaluation.rows
    labeled = rows.labeled
    visibility, fraction, side = rows.visibility[labeled], rows.visib_fract[labeled], rows.box_side[labeled]
    panels = 2 if np.isfinite(fraction).any() else 1
    figure, axes = plt.subplots(1, panels, figsize=(6 * panels, 4), squeeze=False)
    data, labels = [], []
    for kind in KINDS:
        radius = np.sqrt(evaluation.sizes[(kind, epsilon)].area / np.pi)
        for flag, name in ((2, "visible"), (1, "occluded")):
            data.append(radius[(visibility == flag) & np.isfinite(radius)])
            labels.append(f"{kind}\n{name}")
    axes[0, 0].boxplot(data, tick_labels=labels, showfliers=False)
    axes[0, 0].set_ylabel("sqrt(area / pi), px")
    axes[0, 0].set_title(f"Set size by COCO visibility, eps={epsilon}", fontsize=10)
    if panels == 2:
        _fraction_panel(axes[0, 1], evaluation, fraction, side)
    return save(figure, path)


def _fraction_panel(ax: plt.Axes, evaluation: Evaluation, fraction: np.ndarray, side: np.ndarray) -> None:
    bins = np.linspace(np.nanmin(fraction), np.nanmax(fraction) + 1e-9, 9)
    centers = (bins[:-1] + bins[1:]) / 2
    which = np.digitize(fraction, bins) - 1
    for kind in KINDS:
        relative = evaluation.sizes[(kind, evaluation.main_epsilon)].area / side**2
        medians = [
            np.median(relative[which == i]) if (which == i).any() else np.nan for i in range(len(centers))
        ]
        ax.plot(centers, medians, marker="o", label=kind)
    ax.set(xlabel="visib_fract of the object", ylabel="median area / box side^2", yscale="log")
    ax.legend()
    ax.set_title("Relative set area against the visible fraction", fontsize=10)
