"""The composition root: build every long-lived part of the service once, from Settings."""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import timedelta
from functools import cached_property
from typing import Any

import cv2

from calibration_store import CalibrationStore, ScoreTable, open_store, store_location
from service.api.http.admission import QUEUE_TIMEOUT_SECONDS, Admission
from service.calibration import jobs as calibration_jobs
from service.calibration.archive import MIN_FREE_DISK_BYTES, DiskBudget
from service.calibration.bundle import bootstrap_default_calibration
from service.calibration.intake import IntakeRules
from service.calibration.jobs import CalibrationJobs, JobSettings
from service.calibration.registry import POLL_SECONDS, STORE_TIMEOUT_SECONDS, CalibrationRegistry
from service.calibration.uploads import remove_spent_job_folders
from service.calibration.versions import VersionRules
from service.detector.session import Detector, usable_cores
from service.feedback import adaptive
from service.feedback.adaptive import AdaptiveSets
from service.feedback.live_coverage import LiveCoverageReader
from service.feedback.retention import Retention, RetentionRules
from service.infra.audit_trail import AuditTrail
from service.infra.job_engine import JobRunner
from service.infra.logs import ensure_logging
from service.infra.metrics import (
    forget_drift_process_values,
    forget_drift_source,
    set_drift_source,
    set_feedback_source,
)
from service.infra.operators import load_feedback_senders, load_operators, load_predict_callers
from service.infra.processes import process_folder
from service.infra.settings import Settings, refuse_removed_settings
from service.monitoring import coverage_audits, drift_monitor
from service.monitoring.coverage_audits import CoverageAudits
from service.monitoring.drift_monitor import DriftMonitor, DriftSettings
from service.monitoring.drift_shares import DriftShares
from service.prediction import Predictor

log = logging.getLogger(__name__)
#: how old the live coverage /metrics serves may be (each scrape would otherwise read every label)
FEEDBACK_METRICS_AGE_S = 10.0
# Fixed values (service.infra.settings.REMOVED_SETTINGS says which were settings once): the
# container's own, and those of other modules it passes on, are its globals, which tests change
# (tests/api/in_process.py, tests/live/fixed_serve.py).
FREE_SPACE_SHARE = 1 / 20  # of the data directory's file system, where that is less than 1 GiB
MAX_DECODED_BYTES = 256 * 2**20  # an image's decoded pixels (16-bit and alpha take more per pixel)
DRIFT_HISTORY_SECONDS = drift_monitor.HISTORY_SECONDS
DRIFT_FULL_STATISTICS_SHARE = drift_monitor.FULL_STATISTICS_SHARE
MAX_INSTANCES = 64  # per image
ACI_GAMMA = adaptive.ACI_GAMMA


@dataclass
class ServiceState:
    """Everything a request handler may need, created at start-up and closed at shutdown."""

    settings: Settings
    detector: Detector
    store: CalibrationStore
    registry: CalibrationRegistry
    jobs: JobRunner
    calibrations: CalibrationJobs
    audit: AuditTrail
    operators: dict[str, str]  # admin token -> operator name
    cpu_pool: ThreadPoolExecutor
    admission: Admission
    audits: CoverageAudits
    drift: DriftMonitor | None = None  # None when CKS_DRIFT_ENABLED is false
    stopping: threading.Event = field(default_factory=threading.Event)  # set at close
    feedback_senders: dict[str, str] = field(default_factory=dict)  # admin and feedback tokens -> name
    predict_callers: dict[str, str] = field(default_factory=dict)  # empty: predict needs no token
    retention: Retention | None = None
    live_coverage: LiveCoverageReader | None = None
    adaptive: AdaptiveSets | None = None
    version_rules: VersionRules | None = None  # what every new version is held to (field calibrations)

    @cached_property
    def predictor(self) -> Predictor:
        """The predict use case over this state's model, calibrations and drift monitor."""
        settings = self.settings
        return Predictor(
            self.detector,
            self.registry,
            self.drift,
            settings.predict.max_image_pixels,
            MAX_DECODED_BYTES,
            MAX_INSTANCES,
        )

    def close(self) -> None:
        """Stop: the store's poller ends, calibration jobs are interrupted, not waited for (see
        JobRunner.shutdown); uploads still being received are removed; then the store and the
        model are released."""
        started = time.monotonic()
        log.info("shutdown: interrupting calibration jobs, then closing the store and the model")
        self.registry.stop()
        self.stopping.set()
        if self.drift is not None:
            self.drift.stop()
            forget_drift_source(self.drift.report)
            forget_drift_process_values()
        self.jobs.shutdown()
        # cancelled jobs' uploads
        shutil.rmtree(process_folder(self.settings.storage.uploads_dir), ignore_errors=True)
        self.cpu_pool.shutdown(wait=True, cancel_futures=True)
        if self.retention is not None:
            self.retention.close()  # the answers retained so far reach the store
        self.store.close()
        log.info("shutdown: done in %.2f s", time.monotonic() - started)


def build_state(settings: Settings) -> ServiceState:
    """Load the model (refusing a manifest that does not fit it), open the store, bootstrap.

    Also turns OpenCV's internal threading off for the process (``cv2.setNumThreads(1)``).
    """
    ensure_logging(settings)
    refuse_removed_settings(os.environ)
    operators = load_operators(settings.admin.token, settings.admin.tokens_file)
    settings.storage.data_dir.mkdir(parents=True, exist_ok=True)
    # Process-wide: requests already run in parallel on cpu_pool, and OpenCV's own pool would
    # split each small crop across helper threads that spin while they wait.
    cv2.setNumThreads(1)
    detector = Detector(
        settings.model.directory,
        settings.model.inference_threads,
        **detector_providers(settings),
    )
    log.info(
        "onnxruntime execution providers in use: %s; intra-op threads of a run: %d, of a request alone"
        " in this process: %d",
        ", ".join(detector.execution_providers),
        settings.model.inference_threads,
        detector.alone_threads,
    )
    kind, location = store_location(settings.storage.resolved_url)
    # Every lock wait is bounded alike: PostgreSQL's lock_timeout, SQLite's busy timeout
    timeout = STORE_TIMEOUT_SECONDS
    options = {"timeout_s": timeout} if kind == "postgresql" else {"busy_timeout_s": timeout}
    store = open_store(settings.storage.resolved_url, **options)
    if settings.storage.bootstrap_calibration:
        bootstrap_default_calibration(store, detector, settings.model.directory)
    registry = CalibrationRegistry(
        store, detector.model_hash, detector.manifest, POLL_SECONDS, STORE_TIMEOUT_SECONDS
    )
    names = ", ".join(sorted(operators.values())) or "none (admin API disabled)"
    log.info(
        "serving model %s, variant %s (sha256 %s) from %s; calibration store: %s at %s; data directory %s;"
        " active calibration version %s; admin operators: %s",
        detector.manifest.name,
        detector.manifest.variant_name,
        detector.model_hash,
        settings.model.directory,
        kind,
        location,
        settings.storage.data_dir,
        registry.start(),
        names,
    )
    remove_spent_job_folders(settings.storage.jobs_dir, store)
    jobs = JobRunner(store, settings.calibration.workers)
    audit = AuditTrail(store, detector.model_hash, settings.storage.data_dir / "audit-outbox")
    job_settings = _job_settings(settings)
    stopping = threading.Event()  # set at close: the audit gauges' follower stops
    audits = CoverageAudits(store, detector, registry, jobs, audit, job_settings)
    audits.publish_latest()
    calibrations = CalibrationJobs(store, detector, registry, jobs, audit, job_settings)
    jobs.on_stale(calibration_jobs.JOB_KIND, calibrations.take_over)
    jobs.on_stale(coverage_audits.JOB_KIND, None)  # its upload lives in its process's workspace
    audits.follow_latest(5 * POLL_SECONDS, stopping)
    drift = _drift_monitor(settings, detector, registry, store)
    predict = settings.predict
    return ServiceState(
        settings=settings,
        detector=detector,
        store=store,
        registry=registry,
        jobs=jobs,
        calibrations=calibrations,
        audit=audit,
        operators=operators,
        cpu_pool=ThreadPoolExecutor(
            _cpu_threads(predict.max_concurrent_inferences), thread_name_prefix="cpu"
        ),
        admission=Admission(
            predict.max_concurrent_inferences,
            predict.max_queued_requests,
            predict.client_share,
            min(predict.max_concurrent_inferences, usable_cores()),  # the threads that really run at once
            QUEUE_TIMEOUT_SECONDS,
        ),
        audits=audits,
        drift=drift,
        stopping=stopping,
        feedback_senders=load_feedback_senders(settings.admin.token, settings.admin.tokens_file),
        predict_callers=load_predict_callers(settings.admin.token, settings.admin.tokens_file),
        retention=Retention(store, detector.model_hash, _retention_rules(settings)),
        live_coverage=_live_coverage(settings, store, detector),
        adaptive=AdaptiveSets(store, detector.model_hash, ACI_GAMMA),
        version_rules=job_settings.versions,
    )


def _live_coverage(settings: Settings, store: CalibrationStore, detector: Detector) -> LiveCoverageReader:
    """The live coverage of the feedback labels, also the source of cks_feedback_*."""
    names = [keypoint.name for keypoint in detector.manifest.keypoints]
    feedback = settings.feedback
    reader = LiveCoverageReader(
        store, detector.model_hash, names, feedback.max_retained, feedback.alarm_level
    )
    set_feedback_source(lambda: reader.report(max_age_s=FEEDBACK_METRICS_AGE_S))
    return reader


def _retention_rules(settings: Settings) -> RetentionRules:
    feedback = settings.feedback
    return RetentionRules(
        share=feedback.retain_share,
        max_age=timedelta(seconds=feedback.max_age_seconds),
        max_rows=feedback.max_retained,
    )


def _drift_monitor(
    settings: Settings, detector: Detector, registry: CalibrationRegistry, store: CalibrationStore
) -> DriftMonitor | None:
    """The drift monitor, its history ticker started and its report the source of cks_drift_*."""
    if not settings.drift.enabled:
        return None

    def active_calibration() -> tuple[int | None, ScoreTable | None]:
        version = registry.active_version()
        if version is None or registry.incompatibility(version) is not None:
            return version, None
        return version, registry.scores(version)

    drift_settings = DriftSettings(
        window=settings.drift.window,
        test=settings.drift.test,
        alarm_level=settings.drift.alarm_level,
        full_statistics_share=DRIFT_FULL_STATISTICS_SHARE,
        history_seconds=DRIFT_HISTORY_SECONDS,
    )
    shares = DriftShares(store, detector.model_hash, settings.drift.share_seconds)
    monitor = DriftMonitor(detector.manifest, active_calibration, drift_settings, shares)
    monitor.start()
    set_drift_source(monitor.report)
    return monitor


def _cpu_threads(slots: int) -> int:
    """Threads that decode, crop and score: one per compute slot, at most two per usable core (more
    only contend for the cores and the interpreter lock)."""
    return min(slots, 2 * usable_cores())


def _free_space_to_leave(settings: Settings) -> int:
    """What unzipping an upload must leave free: 1 GiB, or a twentieth of a smaller file system."""
    return min(
        MIN_FREE_DISK_BYTES, int(shutil.disk_usage(settings.storage.data_dir).total * FREE_SPACE_SHARE)
    )


def _job_settings(settings: Settings) -> JobSettings:
    kept_uploads = (settings.storage.jobs_dir, settings.storage.uploads_dir)
    return JobSettings(
        jobs_dir=settings.storage.jobs_dir,
        intake=IntakeRules(
            DiskBudget(
                kept_uploads, settings.calibration.max_uploads_disk_bytes, _free_space_to_leave(settings)
            )
        ),
        versions=VersionRules(settings.predict.max_image_pixels, settings.calibration.min_instances),
    )


def detector_providers(settings: Settings) -> dict[str, Any]:
    """The execution provider arguments of ``Detector``, from CKS_EXECUTION_PROVIDERS(_OPTIONS)."""
    return {
        "providers": settings.model.execution_providers,
        "provider_options": settings.model.execution_provider_options,
    }
