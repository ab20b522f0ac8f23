"""Adaptive conformal inference (Gibbs & Candes 2021) per camera stream, driven by feedback labels.

A stream that asks for adaptive sets is served the calibration's threshold at level alpha_t
instead of epsilon; each labelled keypoint of its retained answers (or instance, object scope)
updates alpha_{t+1} = alpha_t + gamma (epsilon - err_t), err_t = 1 when the set served missed.
Whatever the shift, the miscoverage over the first T labels stays within

    | (1/T) sum err_t - epsilon | <= (max(alpha_1, 1 - alpha_1) + gamma) / (gamma T)

(Gibbs & Candes, Prop. 4.1; alpha_1 = epsilon here). The bound needs the empty set served at
alpha_t >= 1 and the whole plane at alpha_t <= 0; the service serves levels in [1e-9, 0.999] (the
whole plane below 1 / (n + 1)), and labels that arrive after later answers were served widen the
bound by gamma per label in flight. The state lives in the store (one row per stream and query,
compare-and-set), so it survives restarts and replicas share it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from calibration_store import AdaptiveState

#: levels served: the registry's thresholds need 0 < epsilon < 1
LOWEST_LEVEL, HIGHEST_LEVEL = 1e-9, 0.999
#: served levels are rounded to this grid: the threshold cache stays small
LEVEL_GRID = 1e-4
_CAS_ATTEMPTS = 20


@dataclass(frozen=True)
class AdaptiveView:
    """A stream's adaptive state as an answer reports it."""

    key: str
    epsilon: float
    alpha: float
    gamma: float
    steps: int
    errors: int

    @property
    def served_epsilon(self) -> float:
        level = round(self.alpha / LEVEL_GRID) * LEVEL_GRID
        return min(max(level, LOWEST_LEVEL), HIGHEST_LEVEL)

    @property
    def bound(self) -> float | None:
        return long_run_bound(self.epsilon, self.gamma, self.steps)

    def as_dict(self) -> dict[str, Any]:
        return {
            "guarantee": "adaptive",
            "epsilon": self.epsilon,
            "alpha": self.alpha,
            "served_epsilon": self.served_epsilon,
            "gamma": self.gamma,
            "steps": self.steps,
            "miscoverage": None if self.steps == 0 else self.errors / self.steps,
            "long_run_bound": self.bound,
        }


def aci_step(alpha: float, epsilon: float, gamma: float, missed: bool) -> float:
    """alpha_{t+1} = alpha_t + gamma (epsilon - err_t)."""
    return alpha + gamma * (epsilon - float(missed))


def long_run_bound(alpha_1: float, gamma: float, steps: int) -> float | None:
    """(max(alpha_1, 1 - alpha_1) + gamma) / (gamma T); None before the first label."""
    return None if steps == 0 else (max(alpha_1, 1 - alpha_1) + gamma) / (gamma * steps)


class AdaptiveSets:
    """Reads and advances each stream's alpha_t in the store."""

    def __init__(self, store: Any, model_hash: str, gamma: float) -> None:
        self._store, self._model_hash, self.gamma = store, model_hash, gamma

    def key(self, query: dict[str, Any], stream: str) -> str:
        """One level per model, stream and query, across calibration versions (a recalibration is
        one more shift to ACI)."""
        kind, scope, epsilon = query["nonconformity"], query["coverage"], query["epsilon"]
        return ":".join(str(part) for part in (self._model_hash[:16], kind, scope, epsilon, stream))

    def view(self, key: str, epsilon: float) -> AdaptiveView:
        stored = self._store.adaptive_state(key)
        if stored is None:
            return AdaptiveView(key, epsilon, epsilon, self.gamma, 0, 0)
        state = stored.state
        return AdaptiveView(
            key, state["epsilon"], state["alpha"], state["gamma"], stored.steps, state["errors"]
        )

    def learn(self, key: str, epsilon: float, misses: list[bool]) -> AdaptiveView:
        """Apply one update per label, in order (compare-and-set, retried when a replica wrote first)."""
        for _ in range(_CAS_ATTEMPTS):
            before = self.view(key, epsilon)
            alpha = before.alpha
            for missed in misses:
                alpha = aci_step(alpha, before.epsilon, before.gamma, missed)
            after = AdaptiveView(
                key,
                before.epsilon,
                alpha,
                before.gamma,
                before.steps + len(misses),
                before.errors + sum(misses),
            )
            state = {"epsilon": after.epsilon, "alpha": alpha, "gamma": after.gamma, "errors": after.errors}
            if self._store.save_adaptive_state(key, before.steps, AdaptiveState(key, after.steps, state)):
                return after
        raise RuntimeError(f"adaptive state {key}: {_CAS_ATTEMPTS} writers in a row got there first")
