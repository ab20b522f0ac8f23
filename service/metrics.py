"""Prometheus metrics of the service: requests, inference batches, admission, calibration jobs,
coverage audits.

With several worker processes (``CKS_WORKERS > 1``) ``serve`` points prometheus_client's
multiprocess mode at a folder (``PROMETHEUS_MULTIPROC_DIR``) before the workers start:
each worker writes its values there and ``/metrics``, whichever worker answers, reports
the sum over all of them (gauges of live workers only).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
    multiprocess,
)

from service.processes import process_folder, process_running

MULTIPROCESS_ENV = "PROMETHEUS_MULTIPROC_DIR"

REGISTRY = CollectorRegistry(auto_describe=True)

REQUESTS = Counter(
    "cks_http_requests", "HTTP requests by route and status", ["method", "route", "status"], registry=REGISTRY
)
LATENCY = Histogram(
    "cks_http_request_seconds",
    "HTTP request latency by route",
    ["method", "route"],
    buckets=(0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10),
    registry=REGISTRY,
)
BATCH_SIZE = Histogram(
    "cks_inference_batch_size",
    "instances per onnxruntime batch",
    buckets=(1, 2, 4, 8, 16, 32, 64, 128),
    registry=REGISTRY,
)
INFERENCE_SECONDS = Histogram(
    "cks_inference_seconds",
    "onnxruntime run time per batch",
    buckets=(0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1),
    registry=REGISTRY,
)
PREDICT_IN_FLIGHT = Gauge(
    "cks_predict_in_flight", "predict places taken, one per request or batch image (computing or waiting)",
    registry=REGISTRY, multiprocess_mode="livesum",
)
PREDICT_COMPUTING = Gauge(
    "cks_predict_computing", "predict requests holding a compute slot",
    registry=REGISTRY, multiprocess_mode="livesum",
)
PREDICT_WAITING = Gauge(
    "cks_predict_waiting", "predict requests waiting for a compute slot",
    registry=REGISTRY, multiprocess_mode="livesum",
)
PREDICT_RECEIVING = Gauge(
    "cks_predict_receiving_bytes", "bytes of predict bodies still arriving (CKS_MAX_RECEIVING_BYTES)",
    registry=REGISTRY, multiprocess_mode="livesum",
)
PREDICT_REJECTED = Counter(
    "cks_predict_rejected", "predict requests refused with 503 by admission control", ["reason"],
    registry=REGISTRY,
)
CALIBRATION_JOBS = Counter(
    "cks_calibration_jobs", "calibration jobs by final state", ["state"], registry=REGISTRY
)
CALIBRATION_INSTANCES = Counter(
    "cks_calibration_instances_scored", "instances scored by calibration jobs", registry=REGISTRY
)

# The latest coverage audit (service/monitoring/audits.py); replaced whole by each new audit
_AUDIT_LABELS = ["object", "keypoint", "nonconformity", "epsilon", "scope"]
AUDIT_COVERAGE = Gauge(
    "cks_audit_coverage", "empirical coverage in the latest coverage audit (keypoint=\"\": pooled)",
    _AUDIT_LABELS, registry=REGISTRY, multiprocess_mode="mostrecent",
)
AUDIT_BAND_LOW = Gauge(
    "cks_audit_band_low", "low end of the 95% band of the coverage a valid calibration gives",
    _AUDIT_LABELS, registry=REGISTRY, multiprocess_mode="mostrecent",
)
AUDIT_BAND_HIGH = Gauge(
    "cks_audit_band_high", "high end of the 95% band of the coverage a valid calibration gives",
    _AUDIT_LABELS, registry=REGISTRY, multiprocess_mode="mostrecent",
)
AUDIT_FLAGGED = Gauge(
    "cks_audit_flagged", "1 where the latest audit found the coverage significantly low (Holm)",
    _AUDIT_LABELS, registry=REGISTRY, multiprocess_mode="mostrecent",
)
AUDIT_LATEST = Gauge(
    "cks_audit_latest_id", "id of the latest coverage audit, by audited version", ["version"],
    registry=REGISTRY, multiprocess_mode="mostrecent",
)


def metrics_payload() -> tuple[bytes, str]:
    """The exposition text: this process's metrics, or all workers' in multiprocess mode."""
    if folder := os.environ.get(MULTIPROCESS_ENV):
        _forget_dead_workers(Path(folder))
        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry)
        return generate_latest(registry), CONTENT_TYPE_LATEST
    return generate_latest(REGISTRY), CONTENT_TYPE_LATEST


def enable_multiprocess(parent: Path) -> Path:
    """Call in the parent before worker processes start (and before they import this module).

    The files go to a folder of this parent process (``<parent>/<host>--<pid>``), so another
    server on the same data directory keeps its own sums; returns it (remove it at exit).
    """
    folder = process_folder(parent)
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
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
