"""The composition root: build every long-lived part of the service once, from Settings."""

from __future__ import annotations

import logging
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2

from calibration_store import CalibrationStore, ScoreTable, open_store, store_location
from service.admission import Admission
from service.audit import AuditTrail
from service.calibration.archive import ArchiveLimits, DiskBudget
from service.calibration.bundle import bootstrap_default_calibration
from service.calibration.intake import IntakeRules
from service.calibration.jobs import CalibrationJobs, JobRunner, JobSettings
from service.calibration.registry import CalibrationRegistry
from service.calibration.stratification import difficulty_spec
from service.calibration.uploads import process_uploads_dir, remove_spent_job_folders
from service.calibration.versions import VersionRules
from service.conformal.kernel import native_kernel_available
from service.detector.activity import worker_activity
from service.detector.runtime import Detector
from service.logs import ensure_logging
from service.metrics import forget_drift_source, set_drift_source
from service.monitoring.audits import CoverageAudits
from service.monitoring.drift import DriftMonitor, DriftSettings
from service.operators import load_operators
from service.settings import Settings

log = logging.getLogger(__name__)


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

    @property
    def uploads_dir(self) -> Path:
        return self.settings.uploads_dir

    def close(self) -> None:
        """Stop: the store's poller ends, calibration jobs are interrupted, not waited for (see
        JobRunner.shutdown); uploads still being received are removed; then the store and the
        model are released."""
        started = time.monotonic()
        log.info("shutdown: interrupting calibration jobs, then closing the store and the model")
        self.registry.stop()
        if self.drift is not None:
            self.drift.stop()
            forget_drift_source(self.drift.report)
        self.jobs.shutdown()
        shutil.rmtree(process_uploads_dir(self.uploads_dir), ignore_errors=True)  # cancelled jobs' uploads
        self.cpu_pool.shutdown(wait=True, cancel_futures=True)
        self.store.close()
        self.detector.close()
        log.info("shutdown: done in %.2f s", time.monotonic() - started)


def build_state(settings: Settings) -> ServiceState:
    """Load the model (refusing a manifest that does not fit it), open the store, bootstrap.

    Also turns OpenCV's internal threading off for the process (``cv2.setNumThreads(1)``).
    """
    ensure_logging(settings)
    operators = load_operators(settings.admin_token, settings.admin_tokens_file)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    # Process-wide: requests already run in parallel on cpu_pool, and OpenCV's own pool would
    # split each small crop across helper threads that spin while they wait.
    cv2.setNumThreads(1)
    detector = Detector(
        settings.model_dir,
        settings.inference_threads,
        settings.max_inference_batch,
        settings.inference_streams,
        **detector_providers(settings),
        batch_window_s=settings.batch_window_ms / 1000,
        solo_threads=settings.solo_threads,
        activity=worker_activity(),
    )
    log.info("onnxruntime execution providers in use: %s", ", ".join(detector.execution_providers))
    kind, location = store_location(settings.resolved_store_url)
    # SQLite keeps its busy timeout: a write waiting on another writer is no outage
    options = {"timeout_s": settings.store_timeout_seconds} if kind == "postgresql" else {}
    store = open_store(settings.resolved_store_url, **options)
    if settings.bootstrap_calibration:
        bootstrap_default_calibration(store, detector, settings.model_dir, difficulty_spec(settings))
    registry = CalibrationRegistry(store, detector.model_hash, detector.manifest, settings.store_poll_seconds,
                                   settings.store_timeout_seconds)  # fmt: skip
    names = ", ".join(sorted(operators.values())) or "none (admin API disabled)"
    log.info("serving model %s (sha256 %s) from %s; calibration store: %s at %s; data directory %s;"
             " active calibration version %s; admin operators: %s", detector.manifest.name,
             detector.model_hash, settings.model_dir, kind, location, settings.data_dir,
             registry.start(), names)  # fmt: skip
    if not native_kernel_available():
        log.warning("the native kernel (service/conformal/kernel.py) is not built: 'peak' runs on the "
                    "slower numpy path; install a C compiler and reinstall the package")  # fmt: skip
    remove_spent_job_folders(settings.jobs_dir, store)
    jobs = JobRunner(store, settings.calibration_workers)
    audit = AuditTrail(store, detector.model_hash)
    job_settings = _job_settings(settings)
    audits = CoverageAudits(store, detector, registry, jobs, audit, job_settings)
    audits.publish_latest()
    drift = _drift_monitor(settings, detector, registry)
    return ServiceState(
        settings=settings,
        detector=detector,
        store=store,
        registry=registry,
        jobs=jobs,
        calibrations=CalibrationJobs(store, detector, registry, jobs, audit, job_settings),
        audit=audit,
        operators=operators,
        cpu_pool=ThreadPoolExecutor(settings.cpu_workers, thread_name_prefix="cpu"),
        admission=Admission(
            settings.max_concurrent_inferences,
            settings.max_queued_requests,
            settings.queue_timeout_seconds,
            settings.max_receiving_bytes,
        ),  # fmt: skip
        audits=audits,
        drift=drift,
    )


def _drift_monitor(
    settings: Settings, detector: Detector, registry: CalibrationRegistry
) -> DriftMonitor | None:
    """The drift monitor, its history ticker started and its report the source of cks_drift_*."""
    if not settings.drift_enabled:
        return None

    def active_calibration() -> tuple[int | None, ScoreTable | None]:
        version = registry.active_version()
        if version is None or registry.incompatibility(version) is not None:
            return version, None
        return version, registry.scores(version)

    drift_settings = DriftSettings(
        window=settings.drift_window,
        test=settings.drift_test,
        alarm_level=settings.drift_alarm_level,
        psi_threshold=settings.drift_psi_threshold,
        full_statistics_share=settings.drift_full_statistics_share,
        history_seconds=settings.drift_history_seconds,
    )
    monitor = DriftMonitor(detector.manifest, active_calibration, drift_settings)
    monitor.start()
    set_drift_source(monitor.report)
    return monitor


def _job_settings(settings: Settings) -> JobSettings:
    return JobSettings(
        jobs_dir=settings.jobs_dir,
        intake=IntakeRules(
            limits=ArchiveLimits.from_settings(settings),
            disk=DiskBudget.from_settings(settings),
            max_rejected_share=settings.max_rejected_share,
        ),
        versions=VersionRules(
            max_image_pixels=settings.max_image_pixels,
            min_instances=settings.min_calibration_instances,
            max_rejected_share=settings.max_rejected_share,
            difficulty=difficulty_spec(settings),
        ),
    )


def detector_providers(settings: Settings) -> dict[str, Any]:
    """The execution provider arguments of ``Detector``, from CKS_EXECUTION_PROVIDERS(_OPTIONS)."""
    return {
        "providers": settings.execution_providers,
        "provider_options": settings.execution_provider_options,
    }
