"""The one command-line entry point: serve, calibrate, predict, check-model, export the schemas."""

from __future__ import annotations

import argparse
import json
import logging
import os
import shlex
import shutil
import socket
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from pydantic import ValidationError

from calibration_store import StoreError, store_location
from service import __version__
from service.errors import InvalidInput, ServiceError
from service.infra.logs import configure_logging
from service.infra.settings import RemovedSettings, Settings, refuse_removed_settings

DEFAULT_RANGE_IMAGES = 64  # int8 ranges: docs/variants.md says why this many

if TYPE_CHECKING:
    from calibration_store import CalibrationStore
    from service.calibration.intake import Parent, UploadOptions, ValidatedBatch
    from service.calibration.versions import CalibrationOutcome
    from service.detector.session import Detector


def _serve(args: argparse.Namespace, settings: Settings) -> int:
    from calibration_store import open_store
    from service.calibration.bundle import bootstrap_default_calibration
    from service.infra.metrics import enable_multiprocess
    from service.infra.operators import load_operators
    from service.infra.processes import remove_dead_process_folders
    from service.serving.server import serve

    host, port = args.host or settings.server.host, args.port or settings.server.port
    _check_port(host, port)
    # Check the model and store the bundled calibration once, before workers start racing.
    load_operators(settings.admin.token, settings.admin.tokens_file)
    detector = _detector(settings)
    settings.storage.data_dir.mkdir(parents=True, exist_ok=True)
    for shared in ("uploads", "metrics"):  # of stopped processes: uploads were never stored
        remove_dead_process_folders(settings.storage.data_dir / shared, starting=True)
    with open_store(settings.storage.resolved_url) as store:
        if settings.storage.bootstrap_calibration:
            bootstrap_default_calibration(store, detector, settings.model.directory)
    del detector  # the serving process loads its own
    metrics = (
        enable_multiprocess(settings.storage.data_dir / "metrics") if settings.server.workers > 1 else None
    )
    try:
        return serve(settings, host, port)
    finally:
        if metrics is not None:
            shutil.rmtree(metrics, ignore_errors=True)


def _detector(settings: Settings, model_dir: Path | None = None) -> Detector:
    from service.detector.session import Detector  # imported late: onnxruntime is slow to load
    from service.serving.container import detector_providers

    directory = model_dir or settings.model.directory
    return Detector(directory, settings.model.inference_threads, **detector_providers(settings))


def _check_port(host: str, port: int) -> None:
    """Refuse an address already in use now: uvicorn would load the model first, then fail."""
    try:
        family, kind, _, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
            probe.bind(address)
    except OSError as error:
        reason = error.strerror or str(error)
        raise InvalidInput(
            f"cannot listen on {host}:{port}: {reason} (choose another: --port or CKS_PORT)"
        ) from None


def _calibrate(args: argparse.Namespace, settings: Settings) -> int:
    from calibration_store import open_store
    from service.calibration.bundle import save_bundle
    from service.calibration.coco import NamedBatch, load_coco_batch
    from service.calibration.intake import UploadOptions, check_batch, read_parent
    from service.calibration.stratification import parse_stratify

    flags = ("activate", "force", "dedupe", "allow_duplicate")
    names = ("name", "note", "append_to", "reason", "max_rejected_share", *flags)
    stratify = None if args.stratify is None else parse_stratify(args.stratify)
    options = UploadOptions(**{n: getattr(args, n) for n in names}, stratify=stratify)
    detector = _detector(settings)
    with open_store(settings.storage.resolved_url) as store:
        parent = None if args.append_to is None else read_parent(store, detector, args.append_to)
        batches, checks = [], {"dedupe": args.dedupe, "max_rejected_share": options.rejected_share}
        for folder in args.folders:
            if not Path(folder).is_dir():
                raise InvalidInput(f"{folder} is not a folder (one holding annotations.json and the images)")
            batch = load_coco_batch(Path(folder), detector.manifest, bounded=True)
            named = NamedBatch(name=args.name or Path(folder).name, sha256=batch.sha256, batch=batch)
            batches.append(check_batch(named, parent, **checks))
        outcome = _new_version(store, detector, batches, parent, options, args.author, settings)
        print(file=sys.stderr)
        if args.bundle:
            table = store.load_scores(detector.model_hash, outcome.info.number)
            save_bundle(Path(args.bundle), outcome.info, table)
    for problem in outcome.summary.get("activation_problems", []):
        print(f"guardrail: {problem}", file=sys.stderr)
    if args.activate and not outcome.activated:
        refused = "not activated: the guardrails refused it (see above); add --force --reason to override"
        print(refused, file=sys.stderr)
    print(json.dumps(outcome.summary))
    return 0


def _new_version(
    store: CalibrationStore,
    detector: Detector,
    batches: list[ValidatedBatch],
    parent: Parent | None,
    options: UploadOptions,
    author: str,
    settings: Settings,
) -> CalibrationOutcome:
    from service.calibration.versions import VersionRules, create_version
    from service.infra.audit_trail import AuditTrail, Operator

    total = sum(b.named.batch.count for b in batches)
    progress = _progress(lambda done: f"scored {done}/{total} instances")
    rules = VersionRules(settings.predict.max_image_pixels, settings.calibration.min_instances)
    operator, audit = Operator(author, "cli"), AuditTrail(store, detector.model_hash)
    return create_version(store, detector, batches, parent, options, operator, rules, audit, progress)


def _optimize(args: argparse.Namespace, settings: Settings) -> int:
    import tempfile
    from dataclasses import replace

    from calibration_store import open_store
    from service.calibration.bundle import BUNDLE_FILENAME, save_bundle
    from service.calibration.coco import NamedBatch, load_coco_batch
    from service.calibration.intake import UploadOptions, check_batch
    from service.calibration.variants import split_for_ranges, write_variant

    source_dir, folder, out = Path(args.model_dir), Path(args.folder), Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise InvalidInput(f"{out} is not empty: optimize writes a whole model folder, name a new one")
    if args.precision == "float16" and settings.model.execution_providers == ("CPUExecutionProvider",):
        raise InvalidInput(
            "float16 is for GPUs, and its calibration is scored where it will run: set"
            " CKS_EXECUTION_PROVIDERS (e.g. CUDAExecutionProvider,CPUExecutionProvider); on CPUs use int8"
        )
    source = _detector(settings, source_dir)
    if source.manifest.variant is not None:
        raise InvalidInput(f"{source_dir} is already the {source.manifest.variant.name} variant of a model")
    batch = load_coco_batch(folder, source.manifest)
    ranges, rest = split_for_ranges(batch, args.range_images)
    name = args.name or folder.name
    options = UploadOptions(name=name)
    named = NamedBatch(name=name, sha256=batch.sha256, batch=rest)
    batches = [check_batch(named, None, dedupe=False, max_rejected_share=options.rejected_share)]
    out.parent.mkdir(parents=True, exist_ok=True)
    # built beside OUT and renamed to it once whole: a failed run leaves no half-written model folder
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as scratch:
        staged = Path(scratch) / "model"
        pixels = settings.predict.max_image_pixels
        variant = write_variant(source, source_dir, staged, args.precision, ranges, pixels)
        detector = _detector(settings, staged)
        note = f"scored with the {variant.name} variant"
        options = replace(options, note=note + (f"; ranges from {variant.ranges}" if variant.ranges else ""))
        with open_store(f"sqlite:///{scratch}/store.db") as store:
            outcome = _new_version(store, detector, batches, None, options, args.author, settings)
            print(file=sys.stderr)
            table = store.load_scores(detector.model_hash, outcome.info.number)
        save_bundle(staged / BUNDLE_FILENAME, outcome.info, table)
        if out.exists():
            out.rmdir()  # empty, checked above
        staged.rename(out)
    summary = {"model_dir": str(out), "variant": variant.model_dump(), "calibration": outcome.summary}
    print(json.dumps(summary))
    return 0


def _predict(args: argparse.Namespace, settings: Settings) -> int:
    from contextlib import nullcontext

    from keypoint_client import ConnectionFailed, KeypointClient, PoseRequest, ProblemError

    from service.api.predict.predict_schemas import PredictParameters
    from service.serving.loopback import served

    image = Path(args.image).read_bytes()
    names = ("epsilon", "nonconformity", "coverage", "delta", "calibration_version")
    options = {name: getattr(args, name) for name in names}
    pose = None if args.pose_k is None else {"K": args.pose_k}
    if pose is not None and args.coverage != "object":
        raise InvalidInput("--pose-k needs --coverage object: only object-scope sets carry a pose guarantee")
    try:  # refuse a mistake before a model is loaded for nothing
        instances = [{"object": o, "bbox": b} for o, b in args.instance]
        PredictParameters(instances=instances, pose=pose, **options)
    except ValidationError as error:
        raise InvalidInput(
            _problems(error, lambda loc: "--pose-k" if loc[:2] == ["pose", "K"] else ".".join(loc))
        ) from None
    if pose is not None:
        options["pose"] = PoseRequest.model_validate(pose)
    # Without --url, this process serves the model on a loopback port: one path, the client's.
    with nullcontext(args.url) if args.url else served(settings) as url, KeypointClient(url) as client:
        try:
            response = client.predict(image, args.instance, **options)
            drawn = client.predict_png(image, args.instance, **options) if args.png else None
        except ProblemError as problem:
            raise ServiceError(problem.detail, errors=problem.errors) from None
        except ConnectionFailed as error:
            return _failed(str(error), 1)
    if drawn is not None:
        Path(args.png).write_bytes(drawn)
    print(response.model_dump_json(indent=2))
    return 0


def _evaluate(args: argparse.Namespace, settings: Settings) -> int:
    from calibration_store import open_store
    from service.evaluation import run

    command = shlex.join(["keypoint-service", *args.argv])
    epsilons = tuple(sorted(set(args.epsilon or run.DEFAULT_EPSILONS)))
    title = args.title or run.DEFAULT_TITLE
    request = run.EvaluationRequest(
        Path(args.folder), Path(args.out), args.version, epsilons, args.delta, title, command
    )
    run.require_matplotlib()  # refuse a mistake before a model is loaded for nothing
    run.check_request(request)
    from service.calibration.bundle import bootstrap_default_calibration
    from service.detector.session import Detector

    detector = Detector(settings.model.directory, settings.model.inference_threads)
    settings.storage.data_dir.mkdir(parents=True, exist_ok=True)
    with open_store(settings.storage.resolved_url) as store:
        if settings.storage.bootstrap_calibration:  # as serve would on its first start
            bootstrap_default_calibration(store, detector, settings.model.directory)
        progress = _progress(lambda done: f"evaluated {done} instances")
        evaluation, path = run.run_evaluation(
            request, store, detector, settings.predict.max_image_pixels, progress
        )
    print(file=sys.stderr)
    print(f"wrote {path} (version {evaluation.version.number}, {evaluation.rows.instances} instances)")
    return 0


def _progress(line: Callable[[int], str]) -> Callable[[int], None]:
    """Counts instances done, rewriting one stderr line."""
    done = 0

    def advance(count: int) -> None:
        nonlocal done
        done += count
        print(f"\r{line(done)}", end="", file=sys.stderr, flush=True)

    return advance


def _check_model(args: argparse.Namespace, settings: Settings) -> int:
    from service.detector.session import Detector

    model_dir = args.model_dir or settings.model.directory
    detector = Detector(model_dir, settings.model.inference_threads)
    print(f"{model_dir}: ok, model.onnx sha256 {detector.model_hash}\n{detector.manifest.summary()}")
    return 0


def _export_openapi(args: argparse.Namespace, settings: Settings) -> int:
    from service.serving.app import create_app

    return _write_json(create_app().openapi(), args.output)  # the app's document, without starting it


def _manifest_schema(args: argparse.Namespace, settings: Settings) -> int:
    from service.detector.manifest import manifest_json_schema

    return _write_json(manifest_json_schema(), args.output)


def _write_json(document: dict, output: str) -> int:
    text = json.dumps(document, indent=2, sort_keys=True) + "\n"
    if output == "-":
        sys.stdout.write(text)
    else:
        Path(output).write_text(text, encoding="utf-8")
    return 0


def _camera_matrix(text: str) -> list[list[float]]:
    """``fx,fy,cx,cy`` as the pinhole matrix, or a JSON matrix (checked later, as the API checks it)."""
    try:
        if text.lstrip().startswith("["):
            matrix = json.loads(text)
            if isinstance(matrix, list) and all(isinstance(row, list) for row in matrix):
                return [[float(v) for v in row] for row in matrix]
        else:
            fx, fy, cx, cy = (float(v) for v in text.split(","))
            return [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
    except (ValueError, TypeError):
        pass
    raise argparse.ArgumentTypeError(
        f"{text!r}: use fx,fy,cx,cy (e.g. 572,572,320,240) or a 3x3 JSON matrix [[fx,0,cx],[0,fy,cy],[0,0,1]]"
    )


def _instance(text: str) -> tuple[str, list[float]]:
    name, sep, bbox = text.partition(":")
    try:
        values = [float(v) for v in bbox.split(",")]
    except ValueError:
        values = []
    if not sep or len(values) != 4:
        raise argparse.ArgumentTypeError(f"{text!r}: use OBJECT:x,y,w,h with numbers, e.g. duck:120,80,64,70")
    return name, values


EXAMPLES = {
    "serve": """\
  keypoint-service serve
  keypoint-service serve --host 0.0.0.0 --port 8080
  CKS_ADMIN_TOKEN=change-me-to-a-secret CKS_LOG_FORMAT=json keypoint-service serve
""",
    "calibrate": """\
  keypoint-service calibrate data/site_a
  keypoint-service calibrate data/site_a data/site_b --activate --note "two sites"
  keypoint-service calibrate data/more --append-to 2 --dedupe --activate
  keypoint-service calibrate data/small --activate --force --reason "pilot, n below the floor"
  keypoint-service calibrate data/site_a --bundle models/my-model/default_calibration.npz
""",
    "predict": """\
  keypoint-service predict models/lmo-synth-unet/samples/images/000000.jpg --instance duck:235,217,67,64
  keypoint-service predict scene.png --instance duck:235,217,67,64 --instance teddy:383,191,81,73 \\
      --epsilon 0.05 --nonconformity var --png sets.png
  keypoint-service predict models/lmo-synth-unet/samples/images/000000.jpg --instance duck:235,217,67,64 \\
      --coverage object --pose-k 572,572,320,240 --png pose.png

A box is x,y,width,height in pixels, origin at the image's top-left corner.
""",
    "evaluate": """\
  keypoint-service evaluate data/site_b
  keypoint-service evaluate data/site_b --version 3 --epsilon 0.05 --epsilon 0.1 --out reports/site_b
  CKS_DATA_DIR=/tmp/scratch keypoint-service evaluate data/lmo_synth/test --delta 0.1 --out docs

Writes OUT/evaluation.md and OUT/figures/*.png (needs the `evaluate` extra: matplotlib).
""",
    "optimize": """\
  keypoint-service optimize models/lmo-synth-unet data/renders --out models/lmo-synth-unet-int8
  CKS_EXECUTION_PROVIDERS=CUDAExecutionProvider,CPUExecutionProvider \\
      keypoint-service optimize models/my-hrnet data/site_a --precision float16 --out models/my-hrnet-fp16

Writes OUT/manifest.json (naming the variant and its source), OUT/model.onnx and
OUT/default_calibration.npz, scored with the new model on the images not used for its ranges.
Serve it with CKS_MODEL_DIR=OUT (docs/variants.md). Needs the `optimize` extra (onnx).
""",
    "check-model": """\
  keypoint-service check-model
  keypoint-service check-model models/my-hrnet
""",
    "export-openapi": """\
  keypoint-service export-openapi
  keypoint-service export-openapi --output - | jq '.paths | keys'
""",
    "manifest-schema": """\
  keypoint-service manifest-schema
  keypoint-service manifest-schema --output - > manifest.schema.json
""",
}


_RAW = argparse.RawDescriptionHelpFormatter


class _Parser(argparse.ArgumentParser):
    """Reports a usage mistake in one line (and exit status 2) rather than the whole usage."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _command(
    commands: argparse._SubParsersAction, name: str, summary: str, run: Callable[..., int]
) -> argparse.ArgumentParser:
    epilog = "examples:\n" + EXAMPLES[name]
    command = commands.add_parser(
        name, help=summary, description=summary, epilog=epilog, formatter_class=_RAW
    )
    command.set_defaults(run=run)
    return command


EXIT_STATUS = """\
Settings come from CKS_* environment variables (README, Configuration).

exit status: 0 done; 1 a file, the calibration store or the system failed; 2 a mistake in
the command, its input or the settings; 3 the model cannot be served.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="keypoint-service", description=__doc__, epilog=EXIT_STATUS, formatter_class=_RAW)
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    serve = _command(commands, "serve", "run the HTTP service (settings from CKS_* variables)", _serve)
    serve.add_argument("--host", help="address to listen on (default CKS_HOST, 127.0.0.1)")
    serve.add_argument("--port", type=int, help="port to listen on (default CKS_PORT, 8000)")

    calibrate = _command(commands, "calibrate", "score COCO-keypoints folders into a new version", _calibrate)
    add = calibrate.add_argument
    add("folders", nargs="+", help="folders holding annotations.json and images")
    add("--name", help="batch name (default: the folder name)")
    add("--author", default="cli", help="operator name in the audit trail (default cli)")
    add("--note", default="", help="free text stored with the version")
    add("--append-to", type=int, metavar="VERSION", help="new version = its instances + the batches")
    add("--activate", action="store_true", help="activate the new version (if the guardrails allow it)")
    add(
        "--force",
        action="store_true",
        help="with --activate: although the guardrails refuse (needs --reason)",
    )
    add("--reason", default="", help="why (recorded in the activation log and the audit)")
    add("--dedupe", action="store_true", help="drop instances already counted instead of refusing the batch")
    add("--allow-duplicate", action="store_true", help="store a copy of a stored version (needs --reason)")
    add("--max-rejected-share", type=float, help="share of instances the box rule may reject (default 0)")
    add(
        "--stratify",
        help="Mondrian strata to store: none, difficulty, group or difficulty+group (default: difficulty"
        " when the scores carry heatmap features)",
    )
    add("--bundle", help="also write the version to this .npz file")

    predict = _command(commands, "predict", "prediction sets for one image, as JSON (and a PNG)", _predict)
    add = predict.add_argument
    add("image", help="a JPEG or PNG file")
    add(
        "--instance",
        type=_instance,
        action="append",
        required=True,
        metavar="OBJECT:x,y,w,h",
        help="an object of the model and its box; repeat for several",
    )
    add("--epsilon", type=float, default=0.1, help="miscoverage: sets hold the keypoint w.p. >= 1 - epsilon")
    add(
        "--nonconformity", choices=["peak", "var", "cov"], default="cov", help="balls (peak, var) or ellipses"
    )
    add(
        "--coverage",
        choices=["keypoint", "object"],
        default="keypoint",
        help="a guarantee per keypoint, or per object",
    )
    add("--delta", type=float, help="PAC: the guarantee holds with probability >= 1 - delta")
    add("--calibration-version", type=int, metavar="VERSION", help="this version (default: the active one)")
    add(
        "--pose-k",
        type=_camera_matrix,
        metavar="fx,fy,cx,cy",
        help="also each instance's pose set (PURSE) for this camera (or a 3x3 JSON matrix), in the"
        " image's pixels with pixel centres at +0.5; needs --coverage object (docs/pose.md)",
    )
    add("--png", help="also draw the sets (and the poses) into this PNG file")
    add("--url", help="the service to ask (default: serve the model in this process)")

    evaluate = _command(
        commands, "evaluate", "the paper's evaluation of a version on a COCO folder", _evaluate
    )
    add = evaluate.add_argument
    add("folder", help="a folder holding annotations.json and images (as for calibrate)")
    add(
        "--version",
        "--calibration-version",
        dest="version",
        type=int,
        metavar="VERSION",
        help="the calibration version to evaluate (default: the active one)",
    )
    add("--epsilon", type=float, action="append", help="miscoverage to evaluate at; repeat (default 0.1)")
    add("--delta", type=float, help="also evaluate the PAC guarantee at this delta")
    add("--out", default="evaluation", help="writes OUT/evaluation.md and OUT/figures/")
    add("--title", help="the report's title (default: Conformal keypoint sets: evaluation)")

    optimize = _command(
        commands, "optimize", "a faster variant of a model folder, with its own calibration", _optimize
    )
    add = optimize.add_argument
    add("model_dir", type=Path, help="the model folder to compress (manifest.json and model.onnx)")
    add("folder", help="a labelled COCO-keypoints folder (as for calibrate), as served images")
    add("--out", required=True, help="the new model folder (new or empty)")
    add("--precision", choices=["int8", "float16"], default="int8", help="int8 for CPUs, float16 for GPUs")
    add(
        "--range-images",
        type=int,
        default=DEFAULT_RANGE_IMAGES,
        help=f"int8: images whose crops set the activation ranges, left out of the calibration"
        f" (default {DEFAULT_RANGE_IMAGES})",
    )
    add("--name", help="batch name in the calibration (default: the folder name)")
    add("--author", default="optimize", help="recorded with the calibration (default optimize)")

    check = _command(
        commands, "check-model", "validate a model directory, summarize its manifest", _check_model
    )
    check.add_argument("model_dir", nargs="?", type=Path, help="default: CKS_MODEL_DIR")
    export = _command(commands, "export-openapi", "write the OpenAPI document", _export_openapi)
    export.add_argument("--output", default="openapi/openapi.json", help="file, or - for stdout")
    schema = _command(commands, "manifest-schema", "write the JSON Schema of manifest.json", _manifest_schema)
    schema.add_argument("--output", default="docs/manifest.schema.json", help="file, or - for stdout")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = sys.argv[1:] if argv is None else list(argv)  # as typed: the report states its command
    try:
        settings = Settings()
        refuse_removed_settings(os.environ)
    except ValidationError as error:
        return _failed(f"invalid settings: {_problems(error, lambda loc: 'CKS_' + '_'.join(loc).upper())}", 2)
    except RemovedSettings as error:
        return _failed(str(error), 2)
    # serve logs at CKS_LOG_LEVEL; the one-shot commands say only what went wrong unless it is set
    quiet = args.run is not _serve and "level" not in settings.logs.model_fields_set
    configure_logging(settings, "WARNING" if quiet else None)
    if quiet:  # the pool's warning at each retry to reach PostgreSQL, before the error line says so
        logging.getLogger("psycopg.pool").setLevel(logging.ERROR)
    from service.detector.session import ModelMismatch
    from service.infra.operators import OperatorsError

    try:
        return args.run(args, settings)
    except ServiceError as error:
        return _failed(error.detail, 2, [line for line in error.errors[:20] if line not in error.detail])
    except ModelMismatch as error:
        return _failed(f"the model cannot be served: {error}", 3)
    except OperatorsError as error:
        return _failed(str(error), 2)
    except StoreError as error:
        _, location = store_location(settings.storage.resolved_url)
        return _failed(f"the calibration store {location} (CKS_STORE_URL): {error}", 1)
    except OSError as error:  # a file or folder that is missing, not writable, not a folder
        return _failed(f"{error.filename}: {error.strerror}" if error.filename else str(error), 1)
    except KeyboardInterrupt:
        return _failed("interrupted", 130)


def _failed(message: str, status: int, details: list[str] | None = None) -> int:
    print(f"error: {message}", *(details or []), sep="\n  ", file=sys.stderr)
    return status


def _problems(error: ValidationError, name: Callable[[list[str]], str]) -> str:
    """``name: what is wrong; ...``, without the values: a mistyped store URL may hold a password."""
    return "; ".join(
        f"{name([str(part) for part in problem['loc']])}: {problem['msg'].removeprefix('Value error, ')}"
        for problem in error.errors()
    )


if __name__ == "__main__":
    sys.exit(main())
