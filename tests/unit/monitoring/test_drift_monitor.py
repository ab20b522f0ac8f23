"""The drift monitor on crafted heatmap statistics: its tests, alarms, windows, set sizes and history.

Live rows go through the hot path (``DriftMonitor.record`` with HeatmapStatistics); the
reference is a score table whose features were made by the same ``heatmap_features``.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from prometheus_client import CollectorRegistry, generate_latest
from scipy import stats

from calibration_store import ObjectScores, ScoreTable
from service.conformal import HeatmapStatistics, ball_shapes
from service.conformal.features import HEATMAP_FEATURES, heatmap_features
from service.detector.manifest import load_manifest
from service.infra.metrics import ReportCollector, drift_families
from service.infra.settings import DEFAULT_MODEL_DIR
from service.monitoring.drift_monitor import PSI_MIN_LIVE, DriftMonitor, DriftSettings

MANIFEST = load_manifest(DEFAULT_MODEL_DIR)
K = MANIFEST.num_keypoints
REFERENCE_N = 400
SETTINGS = DriftSettings(
    window=200, test="ks", alarm_level=0.01, full_statistics_share=1.0, history_seconds=60
)


def _statistics(rng: np.random.Generator, rows: int, blur: float = 1.0) -> HeatmapStatistics:
    """Statistics of ``rows`` heatmaps: ``blur`` > 1 spreads the maps and lowers their peaks."""
    variances = rng.lognormal(np.log(4.0 * blur**2), 0.3, size=(rows, 2))
    covariance = np.zeros((rows, 2, 2))
    covariance[:, 0, 0], covariance[:, 1, 1] = variances[:, 0], variances[:, 1]
    return HeatmapStatistics(
        heatmap_shape=(64, 64),
        uninformative=np.zeros(rows, dtype=bool),
        peak_location=np.full((rows, 2), 32.0),
        peak_probability=rng.beta(8, 40, size=rows) / blur,
        mean=np.full((rows, 2), 32.0),
        covariance=covariance,
    )


def _table(rng: np.random.Generator, with_features: bool = True) -> ScoreTable:
    blocks = []
    for obj in MANIFEST.objects:
        k = len(obj.keypoints)
        columns = [heatmap_features(_statistics(rng, REFERENCE_N)) for _ in range(k)]
        features = {name: np.stack([c[name] for c in columns], axis=1) for name in HEATMAP_FEATURES}
        blocks.append(
            ObjectScores(
                object_name=obj.name,
                keypoint_ids=np.asarray(obj.keypoints),
                instance_refs=tuple(f"i{i}" for i in range(REFERENCE_N)),
                scores={kind: rng.uniform(size=(REFERENCE_N, k)) for kind in ("peak", "var", "cov")},
                features=features if with_features else {},
            )
        )
    return ScoreTable(tuple(blocks))


def _monitor(
    table: ScoreTable | None, settings: DriftSettings = SETTINGS, version: int | None = 1
) -> DriftMonitor:
    return DriftMonitor(MANIFEST, lambda: (version, table), settings)


def _record(monitor: DriftMonitor, rng: np.random.Generator, instances: int, objects=None, blur=1.0) -> None:
    """``instances`` predictions of one instance each, cycling over ``objects`` (default: all)."""
    names = objects or MANIFEST.object_names
    for i in range(instances):
        channels = np.asarray(MANIFEST.object(names[i % len(names)]).keypoints)
        shapes = ball_shapes(np.full(channels.size, 10.0))
        monitor.record(channels, _statistics(rng, channels.size, blur), "cov", shapes)


def test_a_stream_like_the_reference_stays_quiet_and_its_tests_are_scipys():
    rng = np.random.default_rng(1)
    table = _table(rng)
    monitor = _monitor(table)
    _record(monitor, rng, 6 * 150)
    report = monitor.report()
    assert report.reference_available and report.version == 1 and not report.alarm
    first = report.keypoints[0]
    block = next(b for b in table.objects if b.object_name == first.object)
    column = list(block.keypoint_ids).index(first.index)
    live = monitor._windows.window(first.index)  # the window behind the figures
    for position, name in enumerate(HEATMAP_FEATURES):
        test = first.features[name]
        expected = stats.ks_2samp(live[:, position], block.features[name][:, column])
        assert (test.live_n, test.reference_n) == (150, REFERENCE_N)
        assert test.statistic == pytest.approx(expected.statistic, abs=1e-12)
        assert test.p_value == pytest.approx(expected.pvalue, rel=0.05, abs=1e-6)


def test_a_blurred_object_raises_the_alarm_of_its_keypoints_only():
    rng = np.random.default_rng(2)
    monitor = _monitor(_table(rng))
    _record(monitor, rng, 5 * 100, objects=[n for n in MANIFEST.object_names if n != "duck"])
    _record(monitor, rng, 100, objects=["duck"], blur=1.6)
    report = monitor.report()
    assert report.alarm
    by_object = {o.object: o for o in report.objects}
    duck_features = by_object["duck"].features
    assert by_object["duck"].alarm
    assert duck_features["peak_probability"].alarm and duck_features["gamma"].alarm
    assert not duck_features["anisotropy"].alarm  # the blur scales both axes: the shape is unchanged
    assert not any(o.alarm for name, o in by_object.items() if name != "duck")
    duck = [k for k in report.keypoints if k.object == "duck"]
    assert all(k.features["gamma"].alarm and k.features["gamma"].p_value < 1e-6 for k in duck)


def test_the_window_slides_and_the_report_is_cached_until_it_changes():
    rng = np.random.default_rng(3)
    monitor = _monitor(_table(rng), DriftSettings(**{**SETTINGS.__dict__, "window": 50}))
    _record(monitor, rng, 6 * 80)
    report = monitor.report()
    assert {t.live_n for k in report.keypoints for t in k.features.values()} == {50}
    assert monitor.report().evaluated_at == report.evaluated_at  # nothing recorded: the cached report
    _record(monitor, rng, 1)
    assert monitor.report().evaluated_at > report.evaluated_at


def test_statistics_without_the_peak_feed_the_spread_features_only():
    rng = np.random.default_rng(4)
    monitor = _monitor(_table(rng))
    channels = np.asarray(MANIFEST.object("mug").keypoints)
    spread_only = _statistics(rng, channels.size)
    spread_only = HeatmapStatistics(
        spread_only.heatmap_shape,
        spread_only.uninformative,
        None,
        None,
        spread_only.mean,
        spread_only.covariance,
    )
    monitor.record(channels, spread_only, "cov", ball_shapes(np.ones(channels.size)))
    mug = next(k for k in monitor.report().keypoints if k.object == "mug")
    assert mug.features["peak_probability"].live_n == 0 and mug.features["peak_probability"].statistic is None
    assert mug.features["gamma"].live_n == 1 and mug.features["anisotropy"].live_n == 1


@pytest.mark.parametrize(
    ("version", "table", "reason"),
    [
        (None, None, "no calibration version is active"),
        (3, None, "cannot serve"),
        (3, "old", "no heatmap features"),
    ],
)
def test_without_a_reference_the_report_says_why(version, table, reason):
    rng = np.random.default_rng(5)
    source = _table(rng, with_features=False) if table == "old" else None
    monitor = _monitor(source, version=version)
    _record(monitor, rng, 6)
    report = monitor.report()
    assert not report.reference_available and reason in report.reason and not report.alarm
    assert all(t.statistic is None and t.live_n == 1 for k in report.keypoints for t in k.features.values())


def test_psi_alarms_above_its_threshold_once_the_window_is_large_enough():
    rng = np.random.default_rng(6)
    settings = DriftSettings(**{**SETTINGS.__dict__, "test": "psi", "window": 500})
    quiet, shifted = _monitor(_table(rng), settings), _monitor(_table(rng), settings)
    _record(quiet, rng, 6 * PSI_MIN_LIVE)
    _record(shifted, rng, 6 * (PSI_MIN_LIVE - 1), blur=1.6)
    assert not quiet.report().alarm
    assert not shifted.report().alarm  # 399 values: PSI is not trusted yet
    _record(shifted, rng, 6, blur=1.6)
    report = shifted.report()
    assert report.alarm and report.alarm_threshold == 0.25
    assert all(t.p_value is None for k in report.keypoints for t in k.features.values())


def test_set_sizes_summarize_the_recent_sets_per_nonconformity():
    monitor = _monitor(None, version=None)
    rng = np.random.default_rng(7)
    channels = np.asarray(MANIFEST.object("duck").keypoints)
    radii = np.linspace(1.0, 8.0, channels.size)
    monitor.record(channels, _statistics(rng, channels.size), "peak", ball_shapes(radii))
    sizes = monitor.report().set_sizes
    assert sizes["peak"].n == channels.size and sizes["cov"].n == 0 and sizes["cov"].semi_major_px is None
    assert sizes["peak"].semi_major_px.quantiles["p50"] == pytest.approx(np.median(radii))
    assert sizes["peak"].area_px2.quantiles["p95"] == pytest.approx(np.quantile(np.pi * radii**2, 0.95))
    assert sum(sizes["peak"].semi_major_px.histogram_counts) == channels.size


def test_history_gets_a_point_per_period_while_values_arrive():
    rng = np.random.default_rng(8)
    monitor = _monitor(_table(rng), DriftSettings(**{**SETTINGS.__dict__, "history_seconds": 0.05}))
    monitor.start()
    try:
        _record(monitor, rng, 6)
        deadline = time.monotonic() + 10
        while not monitor.report().history and time.monotonic() < deadline:
            time.sleep(0.02)
        point = monitor.report().history[-1]
        assert point.recorded == 6 * 8 and len(point.keypoint_statistics) == K
        time.sleep(0.3)
        assert len(monitor.report().history) == 1  # nothing new recorded: no new point
    finally:
        monitor.stop()


def test_prometheus_families_carry_every_keypoint_and_feature():
    rng = np.random.default_rng(9)
    monitor = _monitor(_table(rng))
    _record(monitor, rng, 12)
    collector = ReportCollector(drift_families, "drift metrics failed")
    collector.source = monitor.report
    registry = CollectorRegistry()
    registry.register(collector)
    text = generate_latest(registry).decode()
    assert text.count("cks_drift_statistic{") == K * len(HEATMAP_FEATURES)
    assert 'cks_drift_window_size{feature="gamma",keypoint="duck_kp0",object="duck"} 2.0' in text
    assert "cks_drift_alarm_any 0.0" in text and "cks_drift_reference_version 1.0" in text


def test_a_failing_evaluation_leaves_the_other_metrics_served():
    def broken() -> None:
        raise RuntimeError("the store went away")

    collector = ReportCollector(drift_families, "drift metrics failed")
    collector.source = broken
    registry = CollectorRegistry()
    registry.register(collector)
    assert "cks_drift" not in generate_latest(registry).decode()
