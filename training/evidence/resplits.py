"""Random re-splits: the conditional coverage law (the paper's Fig. 2) observed directly.

The calibration and test rows are pooled and re-split at random by image, keeping the
real number of calibration images. For exchangeable scores without ties the covered
count of a keypoint on its m test rows is exactly BetaBinomial(m, n+1-t, t) for every
re-split, whatever the pool, so the randomized PIT of each count is Uniform(0, 1) and a
Kolmogorov-Smirnov distance measures the agreement (per keypoint over the re-splits,
whose PITs are independent; and pooled over keypoints, which are not independent
within a re-split, so only the distance is given there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from calibration_store import ScoreTable
from service.detector.manifest import Manifest
from training.evidence.distributions import betabinomial_pmf, ks_pvalue, ks_uniform, randomized_pit
from training.evidence.inference import SplitData
from training.evidence.sets import covered_by_score, score_table, thresholds


@dataclass(frozen=True)
class ResplitResult:
    """(splits, K) arrays for one function and epsilon."""

    kind: str
    epsilon: float
    n: np.ndarray
    t: np.ndarray
    m: np.ndarray
    covered: np.ndarray
    pit: np.ndarray

    @property
    def coverage(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.covered / self.m

    def keypoint_ks(self) -> tuple[np.ndarray, np.ndarray]:
        """Per keypoint: KS distance of its PITs to Uniform(0, 1), and the p-value."""
        columns = [column[~np.isnan(column)] for column in self.pit.T]
        distances = np.array([ks_uniform(c) if c.size else np.nan for c in columns])
        pvalues = [
            ks_pvalue(d, c.size) if c.size else np.nan for d, c in zip(distances, columns, strict=True)
        ]
        return distances, np.array(pvalues)

    def pooled_ks(self) -> float:
        pits = self.pit[~np.isnan(self.pit)]
        return ks_uniform(pits) if pits.size else float("nan")

    def expected_coverage(self) -> np.ndarray:
        """1 - t/(n+1), the mean of Beta(n+1-t, t), per split and keypoint."""
        return 1 - self.t / (self.n + 1)


def resplit(
    pooled: SplitData,
    calibration_images: int,
    manifest: Manifest,
    kinds: tuple[str, ...],
    epsilons: tuple[float, ...],
    splits: int,
    seed: int,
) -> dict[tuple[str, float], ResplitResult]:
    """Coverage per keypoint over ``splits`` random image-level re-splits of the pooled rows."""
    rng = np.random.default_rng(seed)
    image_ids, image_index = np.unique(pooled.image_id, return_inverse=True)
    images = len(image_ids)
    collected: dict[tuple[str, float], list[tuple[np.ndarray, ...]]] = {
        (k, e): [] for k in kinds for e in epsilons
    }
    for _ in tqdm(range(splits), desc="re-splits", mininterval=5):
        chosen = np.zeros(images, dtype=bool)
        chosen[rng.choice(images, calibration_images, replace=False)] = True
        in_calibration = chosen[image_index]
        calibration, test = pooled.rows(in_calibration), pooled.rows(~in_calibration)
        table = score_table(calibration, manifest, kinds)
        for kind in kinds:
            for epsilon in epsilons:
                collected[(kind, epsilon)].append(_one(table, test, manifest, kind, epsilon, rng))
    return {
        key: ResplitResult(key[0], key[1], *map(np.array, zip(*rows, strict=True)))
        for key, rows in collected.items()
    }


def _one(
    table: ScoreTable,
    test: SplitData,
    manifest: Manifest,
    kind: str,
    epsilon: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, ...]:
    result = thresholds(table, manifest, kind, epsilon)
    covered = covered_by_score(test, kind, result.values)
    labeled = test.labeled
    k = manifest.num_keypoints
    m = np.bincount(test.channel[labeled], minlength=k)
    count = np.bincount(test.channel[labeled], weights=covered[labeled], minlength=k).astype(np.int64)
    n = np.array([g.n for g in result.guarantees])
    t = np.array([g.t for g in result.guarantees])
    pit = np.array(
        [
            randomized_pit(int(count[j]), betabinomial_pmf(int(m[j]), n[j] + 1 - t[j], t[j]), rng)
            if t[j] > 0 and m[j] > 0
            else np.nan
            for j in range(k)
        ]
    )
    return n, t, m, count, pit
