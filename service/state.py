"""The composition root: build every long-lived part of the service once, from Settings."""

from __future__ import annotations

import logging
import shutil
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2

from calibration_store import CalibrationStore, open_store
from service.api.admission import Admission
from service.calibration.bundle import bootstrap_default_calibration
from service.calibration.jobs import JobRunner
from service.calibration.registry import CalibrationRegistry
from service.calibration.uploads import process_uploads_dir
from service.conformal.kernel import native_kernel_available
from service.detector.runtime import Detector
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
    cpu_pool: ThreadPoolExecutor
    admission: Admission

    @property
    def uploads_dir(self) -> Path:
        return self.settings.data_dir / "uploads"

    def close(self) -> None:
        self.jobs.shutdown()
        shutil.rmtree(process_uploads_dir(self.uploads_dir), ignore_errors=True)  # cancelled jobs' uploads
        self.cpu_pool.shutdown(wait=True, cancel_futures=True)
        self.store.close()
        self.detector.close()


def build_state(settings: Settings) -> ServiceState:
    """Load the model (refusing a manifest that does not fit it), open the store, bootstrap.

    Also turns OpenCV's internal threading off for the process (``cv2.setNumThreads(1)``).
    """
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    # Process-wide: requests already run in parallel on cpu_pool, and OpenCV's own pool would
    # split each small crop across helper threads that spin while they wait.
    cv2.setNumThreads(1)
    detector = Detector(
        settings.model_dir,
        settings.inference_threads,
        settings.max_inference_batch,
        settings.inference_streams,
    )
    store = open_store(settings.resolved_store_url)
    if settings.bootstrap_calibration:
        bootstrap_default_calibration(store, detector, settings.model_dir)
    registry = CalibrationRegistry(store, detector.model_hash, detector.manifest, settings.store_poll_seconds)
    log.info("serving model %s (%s), active calibration %s", detector.manifest.name,
             detector.model_hash[:12], registry.refresh_now())  # fmt: skip
    if not native_kernel_available():
        log.warning("the native kernel (service/conformal/kernel.py) is not built: 'peak' runs on the "
                    "slower numpy path; install a C compiler and reinstall the package")  # fmt: skip
    return ServiceState(
        settings=settings,
        detector=detector,
        store=store,
        registry=registry,
        jobs=JobRunner(store, settings.calibration_workers),
        cpu_pool=ThreadPoolExecutor(settings.cpu_workers, thread_name_prefix="cpu"),
        admission=Admission(
            settings.max_concurrent_inferences, settings.max_queued_requests, settings.queue_timeout_seconds
        ),
    )
