"""The one command-line entry point: serve, calibrate, predict, check-model, export the schemas."""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
from pathlib import Path

from service.errors import ServiceError
from service.settings import Settings


def _serve(args: argparse.Namespace, settings: Settings) -> int:
    import uvicorn

    from calibration_store import open_store
    from service.calibration.bundle import bootstrap_default_calibration
    from service.detector.runtime import Detector
    from service.metrics import enable_multiprocess
    from service.operators import load_operators
    from service.processes import remove_dead_process_folders

    # Check the model and store the bundled calibration once, before workers start racing.
    load_operators(settings.admin_token, settings.admin_tokens_file)
    detector = Detector(settings.model_dir, settings.inference_threads)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    for shared in ("uploads", "metrics"):  # of stopped processes: uploads were never stored
        remove_dead_process_folders(settings.data_dir / shared)
    with open_store(settings.resolved_store_url) as store:
        if settings.bootstrap_calibration:
            bootstrap_default_calibration(store, detector, settings.model_dir)
    metrics = enable_multiprocess(settings.data_dir / "metrics") if settings.workers > 1 else None
    try:
        uvicorn.run(
            "service.api.main:app",
            host=args.host or settings.host,
            port=args.port or settings.port,
            workers=settings.workers,
            log_level="info",
            access_log=False,
        )
    finally:
        if metrics is not None:
            shutil.rmtree(metrics, ignore_errors=True)
    return 0


def _calibrate(args: argparse.Namespace, settings: Settings) -> int:
    from calibration_store import open_store
    from service.audit import AuditTrail, Operator
    from service.calibration.bundle import save_bundle
    from service.calibration.calibrate import check_parent, create_calibration
    from service.calibration.coco import NamedBatch, load_coco_batch
    from service.calibration.intake import prepare_batch
    from service.calibration.submission import UploadRequest
    from service.detector.runtime import Detector

    request = UploadRequest(args.name, args.note, args.append_to, args.activate, args.force, args.reason,
                            args.dedupe, args.max_rejected_share)  # fmt: skip
    share = request.rejected_share(settings.max_rejected_share)
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

        options = request.options(Operator(args.author, "cli"), settings.max_rejected_share,
                                  settings.min_calibration_instances)  # fmt: skip
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
    from contextlib import nullcontext

    from keypoint_client import ConnectionFailed, KeypointClient, ProblemError

    from service.inprocess import served

    image = Path(args.image).read_bytes()
    instances = [(obj, [float(v) for v in bbox.split(",")]) for obj, bbox in args.instance]
    options = {"epsilon": args.epsilon, "nonconformity": args.nonconformity, "coverage": args.coverage,
               "delta": args.delta, "calibration_version": args.calibration_version}  # fmt: skip
    # Without --url, this process serves the model on a loopback port: one path, the client's.
    with nullcontext(args.url) if args.url else served(settings) as url, KeypointClient(url) as client:
        try:
            response = client.predict(image, instances, **options)
            drawn = client.predict_png(image, instances, **options) if args.png else None
        except ProblemError as problem:
            raise ServiceError(problem.detail, errors=problem.errors) from None
        except ConnectionFailed as error:
            print(f"error: {error}", file=sys.stderr)
            return 1
    if drawn is not None:
        Path(args.png).write_bytes(drawn)
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
    predict.add_argument("--url", help="the service to ask (default: serve the model in this process)")
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
