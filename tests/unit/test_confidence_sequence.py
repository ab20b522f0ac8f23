"""The live coverage alarm's confidence sequence: valid under continuous monitoring (simulated)."""

from __future__ import annotations

import math

import numpy as np

from service.feedback.confidence_sequence import (
    coverage_bounds,
    evidence_path,
    promised_floor,
    proven_below,
)

LEVEL = 0.05  # two-sided; the alarm is one side: level / 2
RUNS, VOTES = 400, 2000


def alarms(votes: np.ndarray, floor: float) -> np.ndarray:
    """Per run: whether the alarm fired at any of its votes (watched after every vote)."""
    limit = math.log(2 / LEVEL)
    return np.array([(evidence_path(run, floor) >= limit).any() for run in votes])


def test_false_alarms_under_the_null_are_at_most_the_stated_level_watched_after_every_vote() -> None:
    rng = np.random.default_rng(1)
    floor = 0.9
    bernoulli = (rng.random((RUNS, VOTES)) < floor).astype(float)
    look_means = rng.beta(9 * 4, 1 * 4, size=(RUNS, VOTES))  # a look's share covered, mean 0.9
    for votes in (bernoulli, look_means):
        rate = alarms(votes, floor).mean()
        assert rate <= LEVEL / 2, rate


def test_the_alarm_fires_when_coverage_is_below_the_floor() -> None:
    rng = np.random.default_rng(2)
    votes = (rng.random((100, VOTES)) < 0.85).astype(float)
    assert alarms(votes, 0.9).mean() >= 0.9
    first = [int(np.argmax(evidence_path(run, 0.9) >= math.log(2 / LEVEL))) + 1 for run in votes[:20]]
    assert np.median(first) < 1000


def test_the_bounds_hold_the_true_mean_at_every_time() -> None:
    rng = np.random.default_rng(3)
    misses = 0
    for _ in range(100):
        votes = rng.random(400) < 0.8
        totals = np.cumsum(votes)
        checks = range(9, 400, 10)
        bounds = [coverage_bounds(float(totals[n]), n + 1, LEVEL) for n in checks]
        misses += any(not (b.lower <= 0.8 <= b.upper) for b in bounds)
    assert misses <= 100 * LEVEL


def test_the_promise_is_the_beta_band_or_one_minus_epsilon_with_pac() -> None:
    assert promised_floor(600, 60, 0.1, 0.05, 0.005) == 0.9
    assert promised_floor(10, 0, 0.05, None, 0.005) == 1.0
    floor = promised_floor(600, 60, 0.1, None, 0.005)
    assert 0.85 < floor < 0.9  # Beta(541, 60)'s 0.5 % quantile
    assert not proven_below(0.0, 0, floor, LEVEL)
