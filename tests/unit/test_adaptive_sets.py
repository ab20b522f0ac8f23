"""Adaptive conformal inference: the long-run miscoverage bound of Gibbs & Candes holds at every T on
a stream whose scores shift, where the static threshold's miscoverage does not return to epsilon;
with labels that arrive late, the bound widened for the label lag holds where the original does not;
the store keeps the lag the service saw."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration_store import open_store
from service.conformal import conformal_threshold
from service.feedback.adaptive import AdaptiveSets, AdaptiveView, aci_step, long_run_bound

EPSILON, GAMMA = 0.1, 0.01


def served_set_missed(scores: np.ndarray, alpha: float, score: float) -> bool:
    """ACI's set at level alpha: the whole plane at alpha <= 0, empty at alpha >= 1."""
    if alpha >= 1:
        return True
    if alpha <= 0:
        return False
    return bool(score > conformal_threshold(scores, alpha))


def test_the_long_run_bound_holds_at_every_step_of_a_shifted_stream() -> None:
    rng = np.random.default_rng(0)
    calibration = rng.chisquare(2, 600)
    stream = np.concatenate([rng.chisquare(2, 1000), 2.5 * rng.chisquare(2, 3000)])  # a shift at t = 1000
    alpha, errors, static = EPSILON, 0, 0
    static_threshold = conformal_threshold(calibration, EPSILON)
    for t, score in enumerate(stream, start=1):
        missed = served_set_missed(calibration, alpha, score)
        errors += missed
        static += bool(score > static_threshold)
        alpha = aci_step(alpha, EPSILON, GAMMA, missed)
        assert abs(errors / t - EPSILON) <= long_run_bound(EPSILON, GAMMA, t)
    assert abs(errors / len(stream) - EPSILON) < 0.01
    assert static / len(stream) > 0.25  # the static sets miss far more than promised after the shift


def test_the_answer_states_the_bound_it_has_reached() -> None:
    view = AdaptiveView("k", EPSILON, 0.07123456, GAMMA, 500, 52)
    assert view.served_epsilon == 0.0712
    assert view.as_dict()["long_run_bound"] == (0.9 + GAMMA) / (GAMMA * 500)
    assert view.as_dict()["label_lag"] == 0
    assert AdaptiveView("k", EPSILON, 0.07, GAMMA, 500, 52, 40).bound == (0.9 + GAMMA * 41) / (GAMMA * 500)
    assert view.as_dict()["miscoverage"] == 52 / 500
    assert AdaptiveView("k", EPSILON, -0.3, GAMMA, 1, 1).served_epsilon == 1e-9
    assert AdaptiveView("k", EPSILON, 1.2, GAMMA, 1, 1).served_epsilon == 0.999
    assert long_run_bound(EPSILON, GAMMA, 0) is None


def delayed_stream(scores: np.ndarray, calibration: np.ndarray, labels_per_frame: int, delay: int):  # noqa: ANN201
    """Frames of ``labels_per_frame`` scores served at one level, their labels learned ``delay``
    frames later: (T, miscoverage, alpha) after each label learned, and the largest label lag."""
    frames = scores.reshape(-1, labels_per_frame)
    alpha, learned, errors, served, path = EPSILON, 0, 0, [], []
    largest = 0
    for position, frame in enumerate(frames):
        served.append((learned, [served_set_missed(calibration, alpha, s) for s in frame]))
        if position >= delay:
            served_at, misses = served[position - delay]
            for missed in misses:
                largest = max(largest, learned - served_at)
                alpha = aci_step(alpha, EPSILON, GAMMA, missed)
                learned, errors = learned + 1, errors + missed
                path.append((learned, errors / learned, alpha))
    return path, largest


def test_with_late_labels_the_bound_widened_for_the_lag_holds_and_the_original_does_not() -> None:
    rng = np.random.default_rng(1)
    calibration = rng.chisquare(2, 600)
    # in distribution, then every point far out: every set misses until alpha reaches 0
    scores = np.concatenate([rng.chisquare(2, 2000), np.full(6000, 1e9)])
    path, lag = delayed_stream(scores, calibration, labels_per_frame=20, delay=10)
    assert lag == 10 * 20 + 19  # the frames in flight, and the labels of one answer before
    lowest, highest = -GAMMA * (1 - EPSILON) * (lag + 1), 1 + GAMMA * EPSILON * (lag + 1)
    assert all(lowest <= alpha <= highest for _, _, alpha in path)
    assert all(abs(m - EPSILON) <= long_run_bound(EPSILON, GAMMA, t, lag) for t, m, _ in path)
    assert any(abs(m - EPSILON) > long_run_bound(EPSILON, GAMMA, t) for t, m, _ in path)


def test_the_store_keeps_the_label_lag_the_service_saw(tmp_path: Path) -> None:
    store = open_store(f"sqlite://{tmp_path}/calibration.db")
    try:
        sets = AdaptiveSets(store, "f" * 64, GAMMA)
        first = sets.learn("cam", EPSILON, [True, False, False])  # served at steps 0 (not said)
        assert (first.steps, first.lag, first.errors) == (3, 2, 1)
        late = sets.learn("cam", EPSILON, [False, False], served_steps=0)  # served before the first
        assert (late.steps, late.lag) == (5, 4)
        assert late.alpha == EPSILON + GAMMA * (5 * EPSILON - 1)
        again = sets.view("cam", EPSILON)
        assert again == late and again.bound == long_run_bound(EPSILON, GAMMA, 5, 4)
        assert sets.learn("cam", EPSILON, [True], served_steps=5).lag == 4  # on time: the largest stays
    finally:
        store.close()
