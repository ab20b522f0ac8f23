"""``keypoint-service evaluate``: the paper's evaluation of a calibration version on any
labeled COCO folder, written as Markdown with PNG figures."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from calibration_store import CalibrationStore, ScoreTable, VersionInfo, VersionNotFound
from service.calibration.coco import load_coco_batch
from service.calibration.compatibility import version_incompatibility
from service.detector.session import Detector
from service.errors import Conflict, InvalidInput, NotFound, ServiceError
from service.evaluation.rows import collect_rows
from service.evaluation.summary import Evaluation, evaluate

DEFAULT_EPSILONS = (0.1,)
DEFAULT_TITLE = "Conformal keypoint sets: evaluation"
EVALUATE_EXTRA = "pip install 'conformal-keypoint-service[evaluate]'"


class MissingDependency(ServiceError):
    title = "Missing dependency"


def require_matplotlib() -> None:
    """Refuse before any work when the figures cannot be drawn."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise MissingDependency(
            f"evaluate draws its figures with matplotlib, which is not installed: {EVALUATE_EXTRA}"
        ) from None


@dataclass(frozen=True)
class EvaluationRequest:
    folder: Path
    out: Path
    version: int | None  # None: the active one
    epsilons: tuple[float, ...] = DEFAULT_EPSILONS
    delta: float | None = None
    title: str = DEFAULT_TITLE
    command: str = "keypoint-service evaluate"


def check_request(request: EvaluationRequest) -> None:
    """Refuse a mistake in the command before the model is loaded."""
    if not request.folder.is_dir():
        raise InvalidInput(f"{request.folder} is not a folder (one holding annotations.json and the images)")
    for epsilon in request.epsilons:
        if not 0 < epsilon < 1:
            raise InvalidInput(f"--epsilon {epsilon}: a miscoverage must lie strictly between 0 and 1")
    if request.delta is not None and not 0 < request.delta < 1:
        raise InvalidInput(f"--delta {request.delta}: must lie strictly between 0 and 1")


def resolve_version(
    store: CalibrationStore, detector: Detector, version: int | None
) -> tuple[VersionInfo, ScoreTable]:
    """The version asked for (or the active one) and its scores, refused when it is missing or
    was scored under other manifest settings."""
    if version is None:
        active = store.active_version(detector.model_hash)
        if active is None:
            raise NotFound("no calibration version is active for this model: name one with --version")
        version = active.version
    try:
        info = store.get_version(detector.model_hash, version)
    except VersionNotFound:
        known = [v.number for v in store.list_versions(detector.model_hash)]
        raise NotFound(
            f"calibration version {version} does not exist for this model "
            f"(versions: {', '.join(map(str, known)) or 'none'})"
        ) from None
    reason = version_incompatibility(info, detector.manifest)
    if reason is not None:
        raise Conflict(f"cannot evaluate: {reason}")
    return info, store.load_scores(detector.model_hash, version)


def run_evaluation(
    request: EvaluationRequest,
    store: CalibrationStore,
    detector: Detector,
    max_image_pixels: int,
    progress: Callable[[int], None] = lambda count: None,
) -> tuple[Evaluation, Path]:
    """Evaluate the version on the folder; write ``out/evaluation.md`` and ``out/figures/*.png``."""
    from service.evaluation.figures import draw_figures
    from service.evaluation.report import write_report

    check_request(request)
    info, table = resolve_version(store, detector, request.version)
    batch = load_coco_batch(request.folder, detector.manifest)
    rows = collect_rows(batch, detector, max_image_pixels, progress)
    evaluation = evaluate(rows, table, detector, info, request.epsilons, request.delta)
    draw_figures(evaluation, request.out / "figures")
    return evaluation, write_report(evaluation, request)
