"""Mondrian (group-conditional) conformal thresholds: one ICP threshold per stratum.

Eq. (3) on the n_g scores of one category known at prediction time gives, by Theorem 1 within it,
1 - eps <= P(cover | category) <= 1 - eps + 1/(n_g + 1) for every category at once (Vovk et al.,
"Algorithmic Learning in a Random World", sec. 4.5). A stratum is a caller group, a difficulty bin
of a label-free heatmap signal, or the bin within the group. Difficulty bins are quantile bins of
the signal over the labeled calibration instances, at least ``min_instances`` each; two signals make
joint bins. The edges use the features, never the labels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .guarantees import Calibration, calibrate

#: the stratum key of instances taken together, whatever their group
ALL_GROUPS = "*"
DEFAULT_SIGNALS = ("gamma", "peak_probability")  # measured best: docs/strata-evaluation.md
DEFAULT_BINS = 3


@dataclass(frozen=True)
class DifficultySpec:
    """How difficulty bins are chosen: the signal(s), bins per signal, the least n per bin."""

    signals: tuple[str, ...] = DEFAULT_SIGNALS
    bins: int = DEFAULT_BINS
    min_instances: int = 30

    def __post_init__(self) -> None:
        if not 1 <= len(self.signals) <= 2 or len(set(self.signals)) != len(self.signals):
            raise ValueError(f"difficulty needs one or two distinct signals, got {self.signals}")
        if self.bins < 1:
            raise ValueError(f"bins must be >= 1, got {self.bins}")
        if self.min_instances < 1:
            raise ValueError(f"min_instances must be >= 1, got {self.min_instances}")

    def as_dict(self) -> dict[str, object]:
        return {"signals": list(self.signals), "bins": self.bins, "min_instances": self.min_instances}

    @classmethod
    def from_dict(cls, value: Mapping[str, Any]) -> DifficultySpec:
        return cls(tuple(value["signals"]), int(value["bins"]), int(value["min_instances"]))


def quantile_edges(values: np.ndarray, bins: int, min_instances: int) -> np.ndarray:
    """Interior cut points splitting ``values`` into at most ``bins`` quantile bins [c_{k-1}, c_k)
    of at least ``min_instances`` values each (ties may merge bins); empty = one bin."""
    ordered = np.sort(np.asarray(values, dtype=np.float64).ravel())
    n = ordered.size
    count = max(1, min(bins, n // min_instances))
    positions = [round(k * n / count) for k in range(1, count)]
    edges = np.unique([(ordered[p - 1] + ordered[p]) / 2 for p in positions])
    return _merge_small_bins(ordered, edges, min_instances)


def _merge_small_bins(ordered: np.ndarray, edges: np.ndarray, min_instances: int) -> np.ndarray:
    """Drop cuts until every bin holds ``min_instances`` values: the smallest bin merges with
    its smaller neighbour (ties at a cut can leave a quantile bin short)."""
    edges = list(edges)
    while edges:
        counts = np.diff(np.searchsorted(ordered, edges, side="left"), prepend=0, append=ordered.size)
        smallest = int(np.argmin(counts))
        if counts[smallest] >= min_instances:
            break
        # the cut to drop: left of the smallest bin for the last bin or a smaller left neighbour
        last = smallest == len(counts) - 1
        left = last or (smallest > 0 and counts[smallest - 1] <= counts[smallest + 1])
        del edges[smallest - 1 if left else smallest]
    return np.asarray(edges, dtype=np.float64)


@dataclass(frozen=True)
class DifficultyBins:
    """Bins of one keypoint (within one group): edges on ``signals[0]`` and, for joint bins, on
    ``signals[1]`` within each of those; ``counts``: calibration instances per bin, outer-major."""

    signals: tuple[str, ...]
    edges: tuple[float, ...]
    inner_edges: tuple[tuple[float, ...], ...] = ()
    counts: tuple[int, ...] = ()

    @property
    def n_bins(self) -> int:
        return len(self.counts)

    def assign(self, features: Mapping[str, np.ndarray]) -> np.ndarray:
        """The bin of every row of ``features`` (name -> (m,) values)."""
        outer = np.searchsorted(self.edges, np.asarray(features[self.signals[0]]), side="right")
        if len(self.signals) == 1:
            return outer.astype(np.intp)
        inner = np.asarray(features[self.signals[1]])
        offsets = np.cumsum([0] + [len(e) + 1 for e in self.inner_edges])
        bins = np.empty(outer.shape, dtype=np.intp)
        for k, edges in enumerate(self.inner_edges):
            rows = outer == k
            bins[rows] = offsets[k] + np.searchsorted(edges, inner[rows], side="right")
        return bins

    def ranges(self, bin_index: int) -> dict[str, tuple[float | None, float | None]]:
        """signal -> [low, high) of one bin (None: unbounded on that side)."""
        if len(self.signals) == 1:
            return {self.signals[0]: _interval(self.edges, bin_index)}
        sizes = [len(e) + 1 for e in self.inner_edges]
        outer = int(np.searchsorted(np.cumsum(sizes), bin_index, side="right"))
        inner = bin_index - sum(sizes[:outer])
        return {
            self.signals[0]: _interval(self.edges, outer),
            self.signals[1]: _interval(self.inner_edges[outer], inner),
        }

    def as_dict(self) -> dict[str, object]:
        inner = {"inner_edges": [list(e) for e in self.inner_edges]} if self.inner_edges else {}
        return {"signals": list(self.signals), "edges": list(self.edges), "counts": list(self.counts)} | inner

    @classmethod
    def from_dict(cls, value: Mapping[str, Any]) -> DifficultyBins:
        inner = tuple(tuple(map(float, e)) for e in value.get("inner_edges", ()))
        edges, counts = tuple(map(float, value["edges"])), tuple(map(int, value["counts"]))
        return cls(tuple(value["signals"]), edges, inner, counts)


def _interval(edges: Sequence[float], index: int) -> tuple[float | None, float | None]:
    low = float(edges[index - 1]) if index > 0 else None
    high = float(edges[index]) if index < len(edges) else None
    return low, high


def fit_difficulty_bins(features: Mapping[str, np.ndarray], spec: DifficultySpec) -> DifficultyBins:
    """Quantile bins of the given rows (the labeled calibration instances of one keypoint)."""
    first = np.asarray(features[spec.signals[0]], dtype=np.float64)
    edges = quantile_edges(first, spec.bins, spec.min_instances)
    outer = np.searchsorted(edges, first, side="right")
    if len(spec.signals) == 1:
        counts = np.bincount(outer, minlength=edges.size + 1)
        return DifficultyBins(spec.signals, tuple(edges.tolist()), counts=tuple(counts.tolist()))
    second = np.asarray(features[spec.signals[1]], dtype=np.float64)
    inner_edges, counts = [], []
    for k in range(edges.size + 1):
        values = second[outer == k]
        inner = quantile_edges(values, spec.bins, spec.min_instances)
        inner_edges.append(tuple(inner.tolist()))
        counts.extend(np.bincount(np.searchsorted(inner, values, side="right"), minlength=inner.size + 1))
    return DifficultyBins(
        spec.signals, tuple(edges.tolist()), tuple(inner_edges), tuple(int(c) for c in counts)
    )


def stratum_calibrations(
    scores: np.ndarray, strata: np.ndarray, n_strata: int, epsilon: float, delta: float | None = None
) -> list[Calibration]:
    """One ICP threshold and guarantee per stratum, eq. (3) on its scores alone (NaN: unlabeled;
    ``strata`` in [0, n_strata)); a stratum with too few scores is unbounded (t = 0)."""
    scores, strata = np.asarray(scores, dtype=np.float64), np.asarray(strata)
    return [calibrate(scores[strata == s], epsilon, delta) for s in range(n_strata)]
