"""Every guarantee field says what it is: the formula in its schema description gives its value.

Each field of ``Guarantee`` (and of its Beta law) either is an input of the calibration (n,
epsilon, scope, ...) or carries a formula between backticks in its description; the formula,
evaluated on the answer's own n, t, epsilon, delta, a and b (epsilon exact, as the rank reads
it), must equal the value, or hold when it is a comparison. A formula followed by "without
delta" is checked on the answers without delta.
"""

from __future__ import annotations

import math
import re
from fractions import Fraction

import pytest

from service.api.predict.predict_schemas import BetaLaw, Guarantee
from service.conformal import beta_cdf
from tests.api.in_process import InProcess
from tests.predict_client import predict_ok

INPUTS = {"scope", "model_variant", "n", "epsilon", "conditional_coverage", "stratum"}
FORMULA = re.compile(r"`([^`]+)`( without delta)?")


class Beta:
    """``Beta(a, b) < x`` reads as P(Beta(a, b) < x), as the descriptions write it."""

    def __init__(self, a: int, b: int) -> None:
        self.a, self.b = a, b

    def __lt__(self, x: float) -> float:
        return beta_cdf(float(x), self.a, self.b) if self.b > 0 else 0.0


def _fields() -> list[tuple[str, str, str]]:
    """(field, where to read its value, description) for every field with a description."""
    fields = [(name, name, info.description or "") for name, info in Guarantee.model_fields.items()]
    fields += [
        (name, f"conditional_coverage.{name}", info.description or "")
        for name, info in BetaLaw.model_fields.items()
    ]
    return fields


def test_every_guarantee_field_is_an_input_or_has_a_formula() -> None:
    missing = [
        name for name, _, description in _fields() if name not in INPUTS and not FORMULA.search(description)
    ]
    assert not missing, f"fields whose description gives no formula: {missing}"


@pytest.mark.parametrize("delta", [None, 0.1, 0.01])
@pytest.mark.parametrize("coverage", ["keypoint", "object"])
def test_every_formula_gives_the_value(
    api: InProcess, sample: tuple[bytes, list[dict]], coverage, delta
) -> None:
    image, instances = sample
    checked = 0
    for epsilon in (0.05, 0.1, 0.2):
        parameters = {"instances": instances, "epsilon": epsilon, "coverage": coverage, "delta": delta}
        for instance in predict_ok(api.client, image, parameters)["instances"]:
            for keypoint in instance["keypoints"]:
                checked += _check(keypoint["guarantee"])
    assert checked > 0


def _check(guarantee: dict) -> int:
    law = guarantee["conditional_coverage"]
    names = {
        "n": guarantee["n"],
        "t": guarantee["t"],
        "epsilon": Fraction(repr(guarantee["epsilon"])),
        "delta": guarantee["delta"],
        "a": law["a"],
        "b": law["b"],
        "pac_failure_probability": guarantee["pac_failure_probability"],
        "floor": math.floor,
        "P": lambda probability: probability,
        "Beta": Beta,
    }
    checked = 0
    for name, where, description in _fields():
        if name in INPUTS:
            continue
        value = guarantee if "." not in where else guarantee[where.split(".")[0]]
        value = value[where.split(".")[-1]]
        for formula, without_delta in FORMULA.findall(description):
            if without_delta and guarantee["delta"] is not None:
                continue
            if value is None or any(
                names[v] is None for v in ("delta", "pac_failure_probability") if v in formula
            ):
                assert guarantee["delta"] is None, f"{name} is null with delta {guarantee['delta']}"
                continue
            result = eval(formula, {"__builtins__": {"min": min, "max": max}}, names)  # noqa: S307
            if isinstance(result, bool):
                assert result, f"{name}: `{formula}` does not hold for {guarantee}"
            else:
                assert value == pytest.approx(float(result), rel=1e-12, abs=1e-15), (
                    f"{name}: `{formula}` for {guarantee}"
                )
            checked += 1
    return checked
