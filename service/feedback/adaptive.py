"""Adaptive conformal inference (Gibbs & Candes 2021) per camera stream, driven by feedback labels:
a stream is served the threshold at level alpha_t, each labelled unit updating
alpha_{t+1} = alpha_t + gamma (epsilon - err_t). With labels up to L updates late (docs/feedback.md):

    | (1/T) sum err_t - epsilon | <= (max(alpha_1, 1 - alpha_1) + gamma (L + 1)) / (gamma T)

Served levels lie in [1e-9, 0.999] (never the empty set). The state lives in the store
(compare-and-set): it survives restarts and replicas share it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from calibration_store import AdaptiveState

#: the ACI step size gamma
ACI_GAMMA = 0.005
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
    lag: int = 0  # the largest label lag seen (see the module's doc)

    @property
    def served_epsilon(self) -> float:
        level = round(self.alpha / LEVEL_GRID) * LEVEL_GRID
        return min(max(level, LOWEST_LEVEL), HIGHEST_LEVEL)

    @property
    def bound(self) -> float | None:
        return long_run_bound(self.epsilon, self.gamma, self.steps, self.lag)

    def as_dict(self) -> dict[str, Any]:
        return {
            "guarantee": "adaptive",
            "epsilon": self.epsilon,
            "alpha": self.alpha,
            "served_epsilon": self.served_epsilon,
            "gamma": self.gamma,
            "steps": self.steps,
            "miscoverage": None if self.steps == 0 else self.errors / self.steps,
            "label_lag": self.lag,
            "long_run_bound": self.bound,
        }


def aci_step(alpha: float, epsilon: float, gamma: float, missed: bool) -> float:
    """alpha_{t+1} = alpha_t + gamma (epsilon - err_t)."""
    return alpha + gamma * (epsilon - float(missed))


def long_run_bound(alpha_1: float, gamma: float, steps: int, lag: int = 0) -> float | None:
    """(max(alpha_1, 1 - alpha_1) + gamma (L + 1)) / (gamma T); None before the first label."""
    return None if steps == 0 else (max(alpha_1, 1 - alpha_1) + gamma * (lag + 1)) / (gamma * steps)


class AdaptiveSets:
    """Reads and advances each stream's alpha_t in the store."""

    def __init__(self, store: Any, model_hash: str, gamma: float = ACI_GAMMA) -> None:
        self._store, self._model_hash, self.gamma = store, model_hash, gamma

    def key(self, query: dict[str, Any], stream: str) -> str:
        """One level per model, stream and query, across calibration versions."""
        kind, scope, epsilon = query["nonconformity"], query["coverage"], query["epsilon"]
        return ":".join(str(part) for part in (self._model_hash[:16], kind, scope, epsilon, stream))

    def view(self, key: str, epsilon: float) -> AdaptiveView:
        stored = self._store.adaptive_state(key)
        if stored is None:
            return AdaptiveView(key, epsilon, epsilon, self.gamma, 0, 0)
        state = stored.state
        values = (state["epsilon"], state["alpha"], state["gamma"], stored.steps, state["errors"])
        return AdaptiveView(key, *values, state.get("lag", 0))

    def learn(
        self, key: str, epsilon: float, misses: list[bool], served_steps: int | None = None
    ) -> AdaptiveView:
        """Apply one update per label of one answer (compare-and-set, retried when a replica wrote first)."""
        for _ in range(_CAS_ATTEMPTS):
            before = self.view(key, epsilon)
            alpha = before.alpha
            for missed in misses:
                alpha = aci_step(alpha, before.epsilon, before.gamma, missed)
            first_lag = 0 if served_steps is None else max(before.steps - served_steps, 0)
            lag = max(before.lag, first_lag + len(misses) - 1) if misses else before.lag
            steps, errors = before.steps + len(misses), before.errors + sum(misses)
            new = AdaptiveView(key, before.epsilon, alpha, before.gamma, steps, errors, lag)
            state = {"epsilon": new.epsilon, "alpha": alpha, "gamma": new.gamma, "errors": errors, "lag": lag}
            if self._store.save_adaptive_state(key, before.steps, AdaptiveState(key, steps, state)):
                return new
        raise RuntimeError(f"adaptive state {key}: {_CAS_ATTEMPTS} writers in a row got there first")
