"""Smoke test of benchmarks.bench_drift: what it measures and prints, never its timings."""

from __future__ import annotations

import numpy as np

from benchmarks.bench_drift import KIND, parts, predict_rounds
from benchmarks.service_bench.breakdown import service_state
from benchmarks.service_bench.inputs import load_sample
from service.api.predict.predict_schemas import PredictParameters
from service.detector.images import decode_image
from service.infra.settings import Settings


def test_bench_drift_times_every_mode_and_part_and_leaves_the_monitor_in_place():
    settings = Settings()
    sample = load_sample(settings.model.directory / "samples").with_instances(1)
    image = decode_image(sample.jpeg, settings.predict.max_image_pixels)
    parameters = PredictParameters.model_validate({"instances": sample.instances, "nonconformity": KIND})
    with service_state(settings.model.directory, 1) as state:
        monitor = state.drift
        medians = predict_rounds(state, sample.jpeg, parameters, rounds=3)
        assert list(medians) == ["off", "on (share 0.25)", "on, share 1"]
        assert medians["off"][1] == 0.0 and all(np.isfinite(m) and m > 0 for m, _ in medians.values())
        assert state.drift is monitor
        timed = parts(state, image, parameters, repeats=3)
        assert all(value > 0 for value in timed.values()) and len(timed) == 5
        assert monitor.report().recorded > 0  # the rounds went through the hot path
