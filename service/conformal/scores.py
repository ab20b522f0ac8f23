"""The paper's three nonconformity functions, one class each (MAPIE conformity-score style): a
``score`` side r(y, f(x)) for labelled keypoints and a ``region`` side, the ICP set {y : r <= thr}
of eq. (3) as a centre c and shape L; thr = inf gives L = 0, thr = 0 gives L = diag(inf, inf).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from .statistics import HeatmapStatistics


class NonconformityScore(ABC):
    """A nonconformity function r(y, f(x)) and the ICP set it induces."""

    kind: ClassVar[str]
    needs_peak: ClassVar[bool] = False
    needs_spread: ClassVar[bool] = False

    @abstractmethod
    def score(self, statistics: HeatmapStatistics, keypoints: np.ndarray) -> np.ndarray:
        """Scores (N,) of keypoints (N, 2) in heatmap coordinates; NaN keypoint -> NaN."""

    @abstractmethod
    def region(self, statistics: HeatmapStatistics, threshold: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centres (N, 2) and shape matrices (N, 2, 2) of the sets for thresholds (N,)."""

    def point_estimate(self, statistics: HeatmapStatistics) -> np.ndarray:
        """The detector's point estimate (N, 2): the centre of the set (q* or q_bar)."""
        return (statistics.peak_location if self.needs_peak else statistics.mean).copy()


class PeakScore(NonconformityScore):
    """(Peak): r = p* ||y - q*||. Set (ICP-Peak): ball at q*, radius thr / p*."""

    kind = "peak"
    needs_peak = True

    def score(self, statistics: HeatmapStatistics, keypoints: np.ndarray) -> np.ndarray:
        offset = keypoints - statistics.peak_location
        return statistics.peak_probability * np.hypot(offset[:, 0], offset[:, 1])

    def region(self, statistics: HeatmapStatistics, threshold: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        base = _identity_times(statistics.peak_probability**2)
        return statistics.peak_location.copy(), _scaled_shapes(base, threshold**2)


class VarScore(NonconformityScore):
    """(Var): r = ||y - q_bar|| / gamma. Set (ICP-Var): ball at q_bar, radius gamma * thr."""

    kind = "var"
    needs_spread = True

    def score(self, statistics: HeatmapStatistics, keypoints: np.ndarray) -> np.ndarray:
        offset = keypoints - statistics.mean
        gamma = np.sqrt(statistics.regularized_variance)
        return np.hypot(offset[:, 0], offset[:, 1]) / gamma

    def region(self, statistics: HeatmapStatistics, threshold: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        base = _identity_times(1.0 / statistics.regularized_variance)
        return statistics.mean.copy(), _scaled_shapes(base, threshold**2)


class CovScore(NonconformityScore):
    """(Cov): r = (y - q_bar)^T Sigma^-1 (y - q_bar). Set (ICP-Cov): L = Sigma^-1 / thr."""

    kind = "cov"
    needs_spread = True

    def score(self, statistics: HeatmapStatistics, keypoints: np.ndarray) -> np.ndarray:
        offset = keypoints - statistics.mean
        return np.einsum("ni,nij,nj->n", offset, statistics.precision, offset)

    def region(self, statistics: HeatmapStatistics, threshold: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return statistics.mean.copy(), _scaled_shapes(statistics.precision, threshold)


NONCONFORMITY_SCORES: dict[str, type[NonconformityScore]] = {
    cls.kind: cls for cls in (PeakScore, VarScore, CovScore)
}


def get_nonconformity_score(kind: str) -> NonconformityScore:
    """The score object for "peak", "var" or "cov"."""
    try:
        return NONCONFORMITY_SCORES[kind]()
    except KeyError:
        raise ValueError(
            f"unknown nonconformity function {kind!r}; expected one of {sorted(NONCONFORMITY_SCORES)}"
        ) from None


def _identity_times(values: np.ndarray) -> np.ndarray:
    shapes = np.zeros((values.shape[0], 2, 2))
    shapes[:, 0, 0] = shapes[:, 1, 1] = values
    return shapes


def _scaled_shapes(base: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """base / scale, with scale = inf -> 0 (unbounded) and scale = 0 -> diag(inf) (a point)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        shapes = base / scale[:, None, None]
    shapes[scale == 0] = np.diag([np.inf, np.inf])
    return shapes
