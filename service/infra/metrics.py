"""Prometheus metrics: requests, inference batches, admission, calibration jobs, coverage audits,
and the drift of live heatmap features (``cks_drift_*``, computed when scraped).

With several workers, prometheus_client's multiprocess mode sums them. Its files are memory-mapped:
a page the file system cannot give kills the process with SIGBUS, so pages are reserved
(``posix_fallocate``) first; on a full disk the worker keeps new series in its own memory.
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import struct
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
    multiprocess,
    values,
)
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector

from service.infra.processes import process_folder, process_running

MULTIPROCESS_ENV = "PROMETHEUS_MULTIPROC_DIR"
log = logging.getLogger(__name__)
#: prometheus_client's first size of a multiprocess file; it doubles it when full
FIRST_CAPACITY = 1 << 16
#: free room kept reserved past a file's used bytes (new series of one request: a few keys of < 1 kB)
HEADROOM = 1 << 14


class ReservedValues:
    """prometheus_client's ValueClass in multiprocess mode, with each file's pages reserved before
    a new value (a new label series) may touch them; on a full disk: in-process values."""

    def __init__(self, mapped: Any) -> None:
        self._mapped = mapped
        self.degraded: str | None = None  # why this process keeps new series in its own memory

    def __call__(self, typ: str, *args: Any, multiprocess_mode: str = "", **kwargs: Any) -> Any:
        if self.degraded is None:
            prefix = f"{typ}_{multiprocess_mode}" if typ == "gauge" else typ
            path = Path(os.environ[MULTIPROCESS_ENV], f"{prefix}_{os.getpid()}.db")
            try:
                reserve_pages(path)
                return self._mapped(typ, *args, multiprocess_mode=multiprocess_mode, **kwargs)
            except OSError as error:
                self.degraded = f"{path.name}: {error.strerror or error}"
                log.warning(
                    "metrics degraded in process %d: its multiprocess files could not be reserved (%s);"
                    " its new series are kept in its own memory and are missing from /metrics until it"
                    " restarts with room on %s",
                    os.getpid(),
                    self.degraded,
                    os.environ[MULTIPROCESS_ENV],
                )
        return values.MutexValue(typ, *args, multiprocess_mode=multiprocess_mode, **kwargs)


def reserve_pages(path: Path) -> None:
    """Make sure the file's pages past its used bytes (HEADROOM at least) are allocated, growing
    it as prometheus_client would (first FIRST_CAPACITY, then doubled); OSError if they cannot be."""
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    size = 0
    try:
        size = os.fstat(descriptor).st_size
        header = os.pread(descriptor, 4, 0)
        used = struct.unpack("i", header)[0] if len(header) == 4 else 0
        wanted = size or FIRST_CAPACITY
        while used + HEADROOM > wanted:
            wanted *= 2
        if wanted > size:
            os.posix_fallocate(descriptor, 0, wanted)
    except OSError:
        if not size:  # an empty file would break every scrape's read of the folder
            path.unlink(missing_ok=True)
        raise
    finally:
        os.close(descriptor)


if os.environ.get(MULTIPROCESS_ENV) and getattr(values.ValueClass, "_multiprocess", False):
    values.ValueClass = ReservedValues(values.ValueClass)  # in a multiprocess worker, before any metric


REGISTRY = CollectorRegistry(auto_describe=True)


def _counter(name: str, documentation: str, labels: Sequence[str] = ()) -> Counter:
    return Counter(name, documentation, labels, registry=REGISTRY)


def _histogram(
    name: str, documentation: str, buckets: Sequence[float], labels: Sequence[str] = ()
) -> Histogram:
    return Histogram(name, documentation, labels, buckets=buckets, registry=REGISTRY)


def _gauge(name: str, documentation: str, labels: Sequence[str] = (), mode: str = "livesum") -> Gauge:
    return Gauge(name, documentation, labels, registry=REGISTRY, multiprocess_mode=mode)


REQUESTS = _counter("cks_http_requests", "HTTP requests by route and status", ["method", "route", "status"])
_SECONDS = (0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10)
LATENCY = _histogram(
    "cks_http_request_seconds", "HTTP request latency by route", _SECONDS, ["method", "route"]
)
_SIZES = (1, 2, 4, 8, 16, 32, 64, 128)
BATCH_SIZE = _histogram("cks_inference_batch_size", "instances per onnxruntime batch", _SIZES)
_RUN_SECONDS = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1)
INFERENCE_SECONDS = _histogram("cks_inference_seconds", "onnxruntime run time per batch", _RUN_SECONDS)
PREDICT_IN_FLIGHT = _gauge(
    "cks_predict_in_flight", "predict places taken, one per request or batch image (computing or waiting)"
)
PREDICT_COMPUTING = _gauge("cks_predict_computing", "predict requests holding a compute slot")
PREDICT_WAITING = _gauge("cks_predict_waiting", "predict requests waiting for a compute slot")
_REJECTED = "predict requests refused by admission control (503; 429 for client_share)"
PREDICT_REJECTED = _counter("cks_predict_rejected", _REJECTED, ["reason"])
CALIBRATION_JOBS = _counter("cks_calibration_jobs", "calibration jobs by final state", ["state"])
CALIBRATION_INSTANCES = _counter("cks_calibration_instances_scored", "instances scored by calibration jobs")

# The latest coverage audit (service/monitoring/coverage_audits.py); replaced whole by each new audit
_AUDIT = (["object", "keypoint", "nonconformity", "epsilon", "scope"], "mostrecent")
_BAND = "end of the 95% band of the coverage a valid calibration gives"
AUDIT_COVERAGE = _gauge(
    "cks_audit_coverage", 'empirical coverage in the latest coverage audit (keypoint="": pooled)', *_AUDIT
)
AUDIT_BAND_LOW = _gauge("cks_audit_band_low", f"low {_BAND}", *_AUDIT)
AUDIT_BAND_HIGH = _gauge("cks_audit_band_high", f"high {_BAND}", *_AUDIT)
_FLAGGED = "1 where the latest audit found the coverage significantly low (Holm)"
AUDIT_FLAGGED = _gauge("cks_audit_flagged", _FLAGGED, *_AUDIT)
AUDIT_LATEST = _gauge(
    "cks_audit_latest_id", "id of the latest coverage audit, by audited version", ["version"], "mostrecent"
)


class ReportCollector(Collector):
    """Families made at scrape from ``source``'s report (None: none); a failing source skips a scrape."""

    def __init__(self, families: Callable[[Any], list[GaugeMetricFamily]], failed: str) -> None:
        self.source: Callable[[], Any] | None = None
        self._families, self._failed = families, failed

    def collect(self) -> Iterator[GaugeMetricFamily]:
        if self.source is None:
            return
        try:
            report = self.source()
        except Exception:
            log.exception(self._failed)
            return
        yield from self._families(report)


@functools.cache
def drift_process_values() -> Gauge:
    """``cks_drift_process_values``, made when a drift monitor first shares (none: no ``cks_drift_*``)."""
    return Gauge(
        "cks_drift_process_values",
        "live values this process recorded into its drift windows, as of its last share (one series per"
        " worker: pid label; sum them over workers and replicas for the fleet)",
        registry=REGISTRY,
        multiprocess_mode="liveall",
    )


def forget_drift_process_values() -> None:
    """Stop exporting ``cks_drift_process_values`` (its drift monitor stopped)."""
    if drift_process_values.cache_info().currsize:
        REGISTRY.unregister(drift_process_values())
        drift_process_values.cache_clear()


def set_drift_source(source: Callable[[], Any] | None) -> None:
    """Serve ``cks_drift_*`` from this report (the process's drift monitor); None: none."""
    DRIFT.source = source


def forget_drift_source(source: Callable[[], Any]) -> None:
    """Stop serving ``cks_drift_*`` from ``source``, unless another monitor has taken its place."""
    if DRIFT.source == source:
        DRIFT.source = None


def drift_families(report: Any) -> list[GaugeMetricFamily]:
    """Per keypoint and feature: statistic, p-value (ks), alarm, live window size; and totals."""
    family = functools.partial(GaugeMetricFamily, labels=["object", "keypoint", "feature"])
    statistic = family(
        "cks_drift_statistic", f"drift statistic ({report.test}) of a keypoint's live feature window"
    )
    p_value = family("cks_drift_p_value", "Kolmogorov-Smirnov p-value (ks test)")
    alarm = family("cks_drift_alarm", "1 when the drift alarm is raised (Holm-corrected for ks)")
    window = family("cks_drift_window_size", "live values in the window")
    for keypoint in report.keypoints:
        for feature, test in keypoint.features.items():
            names = [keypoint.object, keypoint.keypoint, feature]
            window.add_metric(names, test.live_n)
            alarm.add_metric(names, float(test.alarm))
            if test.statistic is not None:
                statistic.add_metric(names, test.statistic)
            if test.p_value is not None:
                p_value.add_metric(names, test.p_value)
    objects = GaugeMetricFamily(
        "cks_drift_object_alarm", "1 when any keypoint of the object alarms", labels=["object"]
    )
    for obj in report.objects:
        objects.add_metric([obj.object], float(obj.alarm))
    reference = GaugeMetricFamily(
        "cks_drift_reference_version", "calibration version the live windows are compared with (0: none)"
    )
    reference.add_metric([], float(report.version or 0) if report.reference_available else 0.0)
    any_alarm = GaugeMetricFamily("cks_drift_alarm_any", "1 when any drift alarm is raised")
    any_alarm.add_metric([], float(report.alarm))
    replicas = GaugeMetricFamily(
        "cks_drift_replicas", "worker processes and replicas whose windows the cks_drift_* figures cover"
    )
    replicas.add_metric([], float(report.replicas))
    return [statistic, p_value, alarm, window, objects, reference, any_alarm, replicas]


def feedback_families(groups: list[Any]) -> list[GaugeMetricFamily]:
    """``cks_feedback_coverage_*`` of each live_coverage.GroupCoverage (its reader caches)."""
    labels = ["version", "nonconformity", "coverage", "epsilon", "level", "name"]
    helps = {
        "lower": "anytime-valid lower bound",
        "upper": "anytime-valid upper bound",
        "looks": "independent labelled looks",
        "alarm": "1 when coverage is proven below the promise",
    }
    families = {
        k: GaugeMetricFamily(f"cks_feedback_coverage_{k}", h, labels=labels) for k, h in helps.items()
    }
    for group in groups:
        names = [str(group.version), group.nonconformity, group.coverage, f"{group.epsilon:g}"]
        names += [group.level, group.name]
        for attribute, family in families.items():
            family.add_metric(names, float(getattr(group, attribute)))
    return list(families.values())


DRIFT = ReportCollector(drift_families, "drift metrics: the evaluation failed")
FEEDBACK = ReportCollector(feedback_families, "feedback metrics: the live coverage could not be read")
REGISTRY.register(DRIFT)
REGISTRY.register(FEEDBACK)


def set_feedback_source(source: Callable[[], list[Any]] | None) -> None:
    """Serve ``cks_feedback_coverage_*`` from this reading; None: none."""
    FEEDBACK.source = source


def metrics_payload() -> tuple[bytes, str]:
    """The exposition text: this process's metrics, or all workers' in multiprocess mode."""
    if folder := os.environ.get(MULTIPROCESS_ENV):
        _forget_dead_workers(Path(folder))
        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry)
        registry.register(DRIFT)
        registry.register(FEEDBACK)
        return generate_latest(registry), CONTENT_TYPE_LATEST
    return generate_latest(REGISTRY), CONTENT_TYPE_LATEST


def enable_multiprocess(parent: Path) -> Path | None:
    """Call in the parent before workers start: the files go to (and it returns, to remove at exit)
    this process's folder under ``parent``, or None where it cannot be made (each worker its own)."""
    folder = process_folder(parent)
    shutil.rmtree(folder, ignore_errors=True)
    try:
        folder.mkdir(parents=True)
    except OSError as error:
        log.warning("metrics degraded: %s (%s); each worker reports only its own metrics", error, folder)
        return None
    os.environ[MULTIPROCESS_ENV] = str(folder)
    return folder


def _forget_dead_workers(folder: Path) -> None:
    """Drop live gauges of workers that died without a clean shutdown (killed, crashed)."""
    for path in folder.glob("gauge_live*_*.db"):
        pid = path.stem.rpartition("_")[2]
        if pid.isdigit() and not process_running(int(pid)):
            multiprocess.mark_process_dead(int(pid), str(folder))


def worker_stopped() -> None:
    """Drop this worker's live gauges from the multiprocess sums (no-op otherwise)."""
    if os.environ.get(MULTIPROCESS_ENV):
        multiprocess.mark_process_dead(os.getpid())
