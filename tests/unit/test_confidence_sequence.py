"""The live coverage alarm and its confidence sequence: valid under continuous monitoring (simulated):
each rung's betting e-process at its floor, the ladder of rungs over the calibration's coverage law."""

from __future__ import annotations

import numpy as np

from service.feedback.confidence_sequence import (
    BettingEProcess,
    CoverageAlarm,
    alarm_rungs,
    coverage_bounds,
    promised_floor,
    rung_floors,
)

LEVEL = 0.05  # two-sided; one rung's e-process is one side: level / 2
RUNS, VOTES = 400, 2000


def alarms(votes: np.ndarray, floor: float) -> np.ndarray:
    """Per run: whether one e-process at level / 2 crossed at any of its votes (read after every vote)."""
    raised = []
    for run in votes:
        alarm = BettingEProcess(LEVEL / 2)
        raised.append(any(alarm.observe(float(vote), floor) for vote in run))
    return np.array(raised)


def test_false_alarms_under_the_null_are_at_most_the_stated_level_watched_after_every_vote() -> None:
    rng = np.random.default_rng(1)
    floor = 0.9
    bernoulli = (rng.random((RUNS, VOTES)) < floor).astype(float)
    look_means = rng.beta(9 * 4, 1 * 4, size=(RUNS, VOTES))  # a look's share covered, mean 0.9
    for votes in (bernoulli, look_means):
        rate = alarms(votes, floor).mean()
        assert rate <= LEVEL / 2, rate


def pooled_looks(
    rng: np.random.Generator, mean: float, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Looks of 1-10 frames of 10-40 units: a scene's difficulty is shared by its frames (its
    coverage p drawn around ``mean``), each frame adds its own (p of a frame drawn around the
    scene's). Per look: the first frame's share covered, and the share over all its frames."""
    scene = rng.beta(mean * 20, (1 - mean) * 20, size=shape)
    frames = rng.integers(1, 11, size=shape)
    units = rng.integers(10, 41, size=shape)
    first = rng.binomial(units, rng.beta(scene * 30, (1 - scene) * 30)) / units
    pooled = np.zeros(shape)
    for count in range(1, 11):
        p = rng.beta(scene * 30, (1 - scene) * 30)
        pooled += np.where(frames >= count, rng.binomial(units, p) / units, 0.0)
    return first, pooled / frames


def test_votes_pooled_over_a_looks_frames_keep_the_false_alarm_rate() -> None:
    """Each frame's units are covered with the floor's probability (the null): the share over all
    of a look's frames has the floor as its mean, whatever the frames share, so the e-process
    keeps its level (docs/feedback.md: why pooling a look's frames is sound)."""
    rng = np.random.default_rng(6)
    _, pooled = pooled_looks(rng, 0.9, (RUNS, VOTES))
    assert alarms(pooled, 0.9).mean() <= LEVEL / 2


def test_pooled_votes_prove_a_shortfall_in_fewer_looks_than_a_looks_first_frame() -> None:
    rng = np.random.default_rng(7)
    first, pooled = pooled_looks(rng, 0.84, (40, VOTES))
    looks = {}
    for name, votes in (("first", first), ("pooled", pooled)):
        found = []
        for run in votes:
            alarm = BettingEProcess(LEVEL / 2)
            found.append(next((i for i, vote in enumerate(run, 1) if alarm.observe(float(vote), 0.9)), VOTES))
        looks[name] = np.median(found)
    assert looks["pooled"] < 0.9 * looks["first"], looks  # 40.5 against 51 looks


def test_the_alarm_fires_when_coverage_is_below_the_floor() -> None:
    rng = np.random.default_rng(2)
    votes = rng.beta(0.86 * 40, 0.14 * 40, size=(100, VOTES))  # looks' shares, mean 0.86 < 0.9
    assert alarms(votes, 0.9).mean() >= 0.95
    first = []
    for run in votes[:20]:
        alarm = BettingEProcess(LEVEL / 2)
        first.append(next(i for i, vote in enumerate(run, 1) if alarm.observe(float(vote), 0.9)))
    assert np.median(first) < 200


def test_a_long_run_of_good_looks_does_not_hold_back_the_alarm_after_a_shift() -> None:
    """The bet forgets: 1,000 looks well above the floor, then a shortfall, proved about as fast
    as from the start (a running mean over all looks would bet nothing for ~1,000 more looks)."""
    rng = np.random.default_rng(5)
    after = []
    for _ in range(20):
        good = rng.beta(0.95 * 40, 0.05 * 40, size=1000)
        shifted = rng.beta(0.86 * 40, 0.14 * 40, size=VOTES)
        alarm = BettingEProcess(LEVEL / 2)
        assert not any(alarm.observe(float(vote), 0.9) for vote in good)
        after.append(next(i for i, vote in enumerate(shifted, 1) if alarm.observe(float(vote), 0.9)))
    assert np.median(after) < 200


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
    assert not BettingEProcess(LEVEL / 2).observe(0.0, 0.0)  # an adaptive stream promises no floor
    assert not CoverageAlarm(LEVEL).observe(0.0, (0.0,) * len(alarm_rungs(LEVEL)))


def test_the_bounds_hold_the_mean_at_both_ends_of_the_unit_interval() -> None:
    for total, count in ((30.0, 30), (0.0, 30), (1.0, 1)):
        bounds = coverage_bounds(total, count, LEVEL)
        assert bounds.lower <= total / count <= bounds.upper
    assert coverage_bounds(30.0, 30, LEVEL).upper == 1.0 and coverage_bounds(0.0, 30, LEVEL).lower == 0.0


N, T = 400, 40  # a calibration of 400 keypoints, epsilon 0.1: coverage law Beta(361, 40)


def ladder_alarms(means: np.ndarray, votes: int, rng: np.random.Generator) -> np.ndarray:
    """Per run: whether the ladder alarm fired, its looks' shares drawn around the run's mean."""
    floors = rung_floors(N, T, 0.1, None, LEVEL)
    raised = []
    for mean in means:
        alarm = CoverageAlarm(LEVEL)
        shares = rng.beta(mean * 30, (1 - mean) * 30, size=votes)
        raised.append(any(alarm.observe(float(share), floors) for share in shares))
    return np.array(raised)


def test_the_rungs_spend_at_most_the_level() -> None:
    for level in (0.001, 0.01, 0.05, 0.2, 0.49):
        rungs = alarm_rungs(level)
        quantiles = [u for u, _ in rungs]
        assert quantiles == sorted(quantiles) and quantiles[0] > 0 and quantiles[-1] < 0.5
        assert all(0 < a <= 1 for _, a in rungs)
        uppers = [*quantiles[1:], 1.0]
        spent = quantiles[0] + sum((upper - u) * a for (u, a), upper in zip(rungs, uppers, strict=True))
        assert spent <= level + 1e-12, (level, spent)
    assert len(alarm_rungs(0.01)) == 3 and len(alarm_rungs(0.2)) == 2


def test_with_coverage_at_a_rungs_floor_the_alarm_is_as_rare_as_that_rungs_level() -> None:
    """The worst case of each stretch of the calibration's law: its coverage C exactly at rung i's
    floor (that rung's e-process at its null's edge, the rungs above it proving a true shortfall):
    at most a_i, so over the law at most u_0 + sum (u_(i+1) - u_i) a_i <= the level."""
    rng = np.random.default_rng(8)
    floors = rung_floors(N, T, 0.1, None, LEVEL)
    for floor, (_, a) in zip(floors, alarm_rungs(LEVEL), strict=True):
        rate = ladder_alarms(np.full(300, floor), 1000, rng).mean()
        assert rate <= a, (floor, rate, a)


def test_over_the_calibrations_law_false_alarms_stay_below_the_level() -> None:
    rng = np.random.default_rng(9)
    coverages = rng.beta(N + 1 - T, T, size=300)  # each run's calibration: its true coverage
    assert ladder_alarms(coverages, 1000, rng).mean() <= LEVEL


def test_the_ladder_proves_a_shortfall_in_fewer_looks_than_one_e_process_at_the_band() -> None:
    """The former alarm: one e-process at level / 2 against the level / 2 quantile."""
    rng = np.random.default_rng(10)
    band = promised_floor(N, T, 0.1, None, LEVEL / 2)
    floors = rung_floors(N, T, 0.1, None, LEVEL)
    looks = {"single": [], "ladder": []}
    for _ in range(30):
        shares = rng.beta(0.835 * 10, 0.165 * 10, size=VOTES)  # sd 0.11, mean 0.835
        single, ladder = BettingEProcess(LEVEL / 2), CoverageAlarm(LEVEL)
        looks["single"].append(next(i for i, x in enumerate(shares, 1) if single.observe(float(x), band)))
        looks["ladder"].append(next(i for i, x in enumerate(shares, 1) if ladder.observe(float(x), floors)))
    assert np.median(looks["ladder"]) < 0.8 * np.median(looks["single"]), looks
