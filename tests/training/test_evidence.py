"""The evidence report: exact laws and rank correlation against scipy, and a smoke run of the command."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from service.settings import Settings
from training.evidence.adaptiveness import average_ranks, spearman
from training.evidence.baseline import OUTSIDE_SCORE, label_pixels, mass_curves
from training.evidence.distributions import (
    beta_interval,
    beta_quantile,
    betabinomial_pmf,
    central_interval,
    ks_pvalue,
    ks_uniform,
    randomized_pit,
)
from training.evidence.validity import GroupCoverage


@pytest.mark.parametrize(("m", "a", "b"), [(1, 1, 1), (50, 30, 4), (400, 451, 50), (1000, 900, 100)])
def test_betabinomial_pmf_and_interval_match_scipy(m: int, a: int, b: int) -> None:
    pmf = betabinomial_pmf(m, a, b)
    np.testing.assert_allclose(pmf, stats.betabinom.pmf(np.arange(m + 1), m, a, b), atol=1e-12)
    low, high = central_interval(pmf)
    assert (low, high) == tuple(int(v) for v in stats.betabinom.ppf([0.025, 0.975], m, a, b))


@pytest.mark.parametrize(("q", "a", "b"), [(0.025, 451, 50), (0.5, 26, 2), (0.975, 3, 1)])
def test_beta_quantile_matches_scipy(q: float, a: int, b: int) -> None:
    assert beta_quantile(q, a, b) == pytest.approx(stats.beta.ppf(q, a, b), abs=1e-8)
    low, high = beta_interval(a, b)
    assert low < beta_quantile(0.5, a, b) < high


def test_spearman_with_ties_matches_scipy() -> None:
    rng = np.random.default_rng(0)
    x = rng.integers(0, 5, 200).astype(float)
    y = x + rng.integers(0, 3, 200)
    y[:10] = np.inf  # unbounded sets rank last
    np.testing.assert_allclose(average_ranks(x), stats.rankdata(x))
    assert spearman(x, y) == pytest.approx(stats.spearmanr(x, y).statistic, abs=1e-12)
    assert math.isnan(spearman(np.ones(10), np.arange(10.0)))


def test_randomized_pit_is_uniform_and_ks_matches_scipy() -> None:
    rng = np.random.default_rng(1)
    m, a, b = 60, 45, 5
    pmf = betabinomial_pmf(m, a, b)
    counts = stats.betabinom.rvs(m, a, b, size=3000, random_state=2)
    pits = np.array([randomized_pit(int(c), pmf, rng) for c in counts])
    distance = ks_uniform(pits)
    assert distance == pytest.approx(stats.kstest(pits, "uniform").statistic)
    assert ks_pvalue(distance, pits.size) > 0.001
    assert ks_pvalue(0.1, 100) == pytest.approx(stats.kstwo.sf(0.1, 100), abs=0.01)


def test_mass_curve_scores_share_ties_and_count_pixels() -> None:
    probabilities = np.array([[[0.4, 0.2], [0.2, 0.2]]])
    curves = mass_curves(probabilities)
    np.testing.assert_allclose(curves.sorted_scores, [[0.4, 1.0, 1.0, 1.0]])
    assert curves.label_scores(np.array([0]))[0] == pytest.approx(0.4)
    assert curves.label_scores(np.array([-1]))[0] == OUTSIDE_SCORE
    assert curves.areas(np.array([0.5]))[0] == 1 and curves.areas(np.array([1.0]))[0] == 4
    pixels = label_pixels(np.array([[0.5, 1.5], [2.0, 0.0], [np.nan, np.nan]]), 2, 2)
    assert pixels.tolist() == [2, -1, -1]


def test_group_coverage_predictive_interval() -> None:
    inside = GroupCoverage("k", n=500, t=50, m=400, covered=360)
    outside = GroupCoverage("k", n=500, t=50, m=400, covered=330)
    assert inside.inside_predictive() and not outside.inside_predictive()
    assert 0.4 < inside.chance_at_least(0.9) < 0.8


@pytest.fixture(scope="module")
def model_dir() -> Path:
    path = Settings().model_dir
    assert (path / "model.onnx").is_file(), f"no model at {path}: the bundled model is part of the repository"
    return path


def test_report_smoke(tmp_path: Path, model_dir: Path) -> None:
    from training.evaluate_conformal import run
    from training.generate import generate

    calibration, test = tmp_path / "calibration", tmp_path / "test"
    generate(calibration, 4, 11, "smoke-cal", progress=False)
    generate(test, 4, 12, "smoke-test", progress=False)
    out = tmp_path / "docs"
    path = run(model_dir, calibration, test, out, tmp_path / "cache", splits=5, command="smoke")
    text = path.read_text()
    for section in (
        "## Validity",
        "### Object scope",
        "### PAC",
        "## Random re-splits",
        "## Tightness",
        "## Adaptiveness",
        "## Baseline",
    ):
        assert section in text
    for name in ("validity", "resplits", "tightness", "adaptiveness", "overlays", "baseline"):
        figure = out / "figures" / f"{name}.png"
        assert figure.is_file() and 0 < figure.stat().st_size < 1_500_000
        assert f"figures/{name}.png" in text
    table_cells = re.findall(r"\| ([-0-9.e+]+|nan|inf) (?=\|)", text)
    assert table_cells and "nan" not in table_cells
    check = float(re.search(r"cached sets is ([0-9.e+-]+)\.", text).group(1))
    assert check < 1e-9  # the cached path gives the sets of service.prediction.calibrated_sets
    rerun = run(model_dir, calibration, test, out, tmp_path / "cache", splits=5, command="smoke")
    assert rerun.read_text() == text  # the cache and the seed make the report reproducible
