"""Adaptive conformal inference: the long-run miscoverage bound of Gibbs & Candes holds at every T on
a stream whose scores shift, where the static threshold's miscoverage does not return to epsilon."""

from __future__ import annotations

import numpy as np

from service.conformal import conformal_threshold
from service.feedback.adaptive import AdaptiveView, aci_step, long_run_bound

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
    assert view.as_dict()["miscoverage"] == 52 / 500
    assert AdaptiveView("k", EPSILON, -0.3, GAMMA, 1, 1).served_epsilon == 1e-9
    assert AdaptiveView("k", EPSILON, 1.2, GAMMA, 1, 1).served_epsilon == 0.999
    assert long_run_bound(EPSILON, GAMMA, 0) is None
