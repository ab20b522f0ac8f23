"""The one command-line entry point: serve, calibrate, predict, check-model, export the schemas."""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
from pathlib import Path

from service.errors import InvalidInput, ServiceError
from service.settings import Settings


def _serve(args: argparse.Namespace, settings: Settings) -> int:
    from calibration_store import open_store
    from service.calibration.bundle import bootstrap_default_calibration
    from service.detector.runtime import Detector
    from service.metrics import enable_multiprocess
    from service.operators import load_operators
    from service.processes import remove_dead_process_folders
    from service.server import serve

    # Check the model and store the bundled calibration once, before workers start racing.
    load_operators(settings.admin_token, settings.admin_tokens_file)
    detector = Detector(settings.model_dir, settings.inference_threads)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    for shared in ("uploads", "metrics"):  # of stopped processes: uploads were never stored
        remove_dead_process_folders(settings.data_dir / shared)
    with open_store(settings.resolved_store_url) as store:
        if settings.bootstrap_calibration:
            bootstrap_default_calibration(store, detector, settings.model_dir)
    del detector  # the serving process loads its own
    metrics = enable_multiprocess(settings.data_dir / "metrics") if settings.workers > 1 else None
    try:
        return serve(settings, args.host, args.port)
    finally:
        if metrics is not None:
            shutil.rmtree(metrics, ignore_errors=True)


def _calibrate(args: argparse.Namespace, settings: Settings) -> int:
    from calibration_store import open_store
    from service.audit import AuditTrail, Operator
    from service.calibration.bundle import save_bundle
    from service.calibration.calibrate import CalibrationOptions, check_parent, create_calibration
    from service.calibration.coco import NamedBatch, load_coco_batch
    from service.calibration.intake import prepare_batch
    from service.detector.runtime import Detector

    if args.force and not (args.activate and args.reason.strip()):
        raise InvalidInput("--force needs --activate and a --reason (why the guardrails may be overridden)")
    share = settings.max_rejected_share if args.max_rejected_share is None else args.max_rejected_share
    detector = Detector(settings.model_dir, settings.inference_threads)
    with open_store(settings.resolved_store_url) as store:
        parent = parent_table = None
        if args.append_to is not None:
            parent = check_parent(store, detector, args.append_to)
            parent_table = store.load_scores(detector.model_hash, args.append_to)
        batches = []
        for folder in args.folders:
            batch = load_coco_batch(Path(folder), detector.manifest)
            named = NamedBatch(name=args.name or Path(folder).name, sha256=batch.sha256, batch=batch)
            batches.append(
                prepare_batch(named, parent, parent_table, dedupe=args.dedupe, max_rejected_share=share)
            )
        total = sum(b.named.batch.count for b in batches)
        done = 0

        def progress(count: int) -> None:
            nonlocal done
            done += count
            print(f"\rscored {done}/{total} instances", end="", file=sys.stderr, flush=True)

        options = CalibrationOptions(
            operator=Operator(args.author, "cli"),
            note=args.note,
            append_to=args.append_to,
            activate=args.activate,
            force=args.force,
            reason=args.reason,
            max_rejected_share=share,
            min_instances=settings.min_calibration_instances,
        )
        audit = AuditTrail(store, detector.model_hash)
        pixels = settings.max_image_pixels
        outcome = create_calibration(store, detector, batches, options, pixels, audit, progress)
        print(file=sys.stderr)
        if args.bundle:
            table = store.load_scores(detector.model_hash, outcome.info.number)
            save_bundle(Path(args.bundle), outcome.info, table)
    for problem in outcome.summary.get("activation_problems", []):
        print(f"guardrail: {problem}", file=sys.stderr)
    if args.activate and not outcome.activated:
        print("not activated: the guardrails refused it (see above); add --force --reason to override",
              file=sys.stderr)
    print(json.dumps(outcome.summary))
    return 0


def _predict(args: argparse.Namespace, settings: Settings) -> int:
    from service.api.schemas import PredictParameters
    from service.image_decoding import decode_image
    from service.prediction import predict
    from service.render import render_prediction
    from service.state import build_state

    instances = [{"object": obj, "bbox": [float(v) for v in bbox.split(",")]} for obj, bbox in args.instance]
    parameters = PredictParameters(
        instances=instances,
        epsilon=args.epsilon,
        nonconformity=args.nonconformity,
        coverage=args.coverage,
        delta=args.delta,
        calibration_version=args.calibration_version,
    )
    image = decode_image(Path(args.image).read_bytes(), settings.max_image_pixels)
    state = build_state(settings)
    try:
        response = predict(state, image, parameters)
    finally:
        state.close()
    if args.png:
        Path(args.png).write_bytes(render_prediction(image, response))
    print(response.model_dump_json(indent=2))
    return 0


def _check_model(args: argparse.Namespace, settings: Settings) -> int:
    from service.detector.runtime import Detector

    model_dir = args.model_dir or settings.model_dir
    detector = Detector(model_dir, settings.inference_threads)
    print(f"{model_dir}: ok, model.onnx sha256 {detector.model_hash}\n{detector.manifest.summary()}")
    return 0


def _export_openapi(args: argparse.Namespace, settings: Settings) -> int:
    from service.api.openapi import openapi_document

    return _write_json(openapi_document(), args.output)


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


def _instance(text: str) -> tuple[str, str]:
    name, sep, bbox = text.partition(":")
    if not sep or len(bbox.split(",")) != 4:
        raise argparse.ArgumentTypeError("use OBJECT:x,y,w,h, e.g. duck:120,80,64,70")
    return name, bbox


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="keypoint-service", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)

    serve = commands.add_parser("serve", help="run the HTTP service (settings from CKS_* variables)")
    serve.add_argument("--host")
    serve.add_argument("--port", type=int)
    serve.set_defaults(run=_serve)

    calibrate = commands.add_parser("calibrate", help="score COCO-keypoints folders into a new version")
    calibrate.add_argument("folders", nargs="+", help="folders holding annotations.json and images")
    calibrate.add_argument("--name", help="batch name (default: the folder name)")
    calibrate.add_argument("--author", default="cli")
    calibrate.add_argument("--note", default="")
    calibrate.add_argument("--append-to", type=int)
    calibrate.add_argument("--activate", action="store_true")
    calibrate.add_argument("--force", action="store_true",
                           help="with --activate: activate although the guardrails refuse (needs --reason)")
    calibrate.add_argument("--reason", default="", help="why (recorded in the activation log and the audit)")
    calibrate.add_argument("--dedupe", action="store_true",
                           help="drop instances already counted instead of refusing the batch")
    calibrate.add_argument("--max-rejected-share", type=float,
                           help="share of instances the box rule may reject (default CKS_MAX_REJECTED_SHARE)")
    calibrate.add_argument("--bundle", help="also write the version to this .npz file")
    calibrate.set_defaults(run=_calibrate)

    predict = commands.add_parser("predict", help="prediction sets for one image, as JSON (and a PNG)")
    predict.add_argument("image")
    predict.add_argument("--instance", type=_instance, action="append", required=True, help="OBJECT:x,y,w,h")
    predict.add_argument("--epsilon", type=float, default=0.1)
    predict.add_argument("--nonconformity", choices=["peak", "var", "cov"], default="cov")
    predict.add_argument("--coverage", choices=["keypoint", "object"], default="keypoint")
    predict.add_argument("--delta", type=float)
    predict.add_argument("--calibration-version", type=int)
    predict.add_argument("--png", help="also draw the sets into this PNG file")
    predict.set_defaults(run=_predict)

    check = commands.add_parser("check-model", help="validate a model directory and summarize its manifest")
    check.add_argument("model_dir", nargs="?", type=Path, help="default: CKS_MODEL_DIR")
    check.set_defaults(run=_check_model)

    export = commands.add_parser("export-openapi", help="write the OpenAPI document")
    export.add_argument("--output", default="openapi/openapi.json", help="file, or - for stdout")
    export.set_defaults(run=_export_openapi)

    schema = commands.add_parser("manifest-schema", help="write the JSON Schema of manifest.json")
    schema.add_argument("--output", default="docs/manifest.schema.json", help="file, or - for stdout")
    schema.set_defaults(run=_manifest_schema)
    return parser


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    args = build_parser().parse_args(argv)
    from service.detector.runtime import ModelMismatch
    from service.operators import OperatorsError

    try:
        return args.run(args, Settings())
    except ServiceError as error:
        print(f"error: {error.detail}", *error.errors[:20], sep="\n  ", file=sys.stderr)
        return 2
    except ModelMismatch as error:
        print(f"error: the model cannot be served: {error}", file=sys.stderr)
        return 3
    except OperatorsError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
