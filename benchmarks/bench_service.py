"""The service against the cost of its model: throughput, latency, breakdown, memory, tuning.

    python -m benchmarks.bench_service            # ~10 min, writes its section of docs/performance.md
    python -m benchmarks.bench_service --quick    # a few seconds per point, for development
    python -m benchmarks.bench_service --seconds 6  # shorter headline points, same points

Needs wrk (``apt-get install -y wrk``). The model is ``CKS_MODEL_DIR`` (default: the bundled
model) and its ``samples/`` COCO folder; other ``CKS_*`` variables set the headline settings.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.service_bench import offline, page, report, runs
from benchmarks.service_bench.breakdown import service_state, stage_breakdown
from benchmarks.service_bench.inputs import Sample, load_sample
from benchmarks.service_bench.loadgen import require_wrk
from benchmarks.service_bench.machine import this_machine
from service.detector.manifest import load_manifest
from service.detector.session import file_sha256
from service.infra.settings import DEFAULT_MODEL_DIR, Settings

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUTPUT = ROOT / "docs" / "performance.md"


def log(message: str) -> None:
    print(message, flush=True)


def headline_settings() -> dict[str, int]:
    settings = Settings()
    return {name: settings.value(name) for name in runs.SETTING_NAMES}


def breakdowns(model_dir: Path, sample: Sample, threads: int, iterations: int) -> dict[int, dict[str, float]]:
    """In-process stage medians for 1 and 4 instances."""
    with service_state(model_dir, threads) as state:
        result = {
            n: stage_breakdown(state, sample.with_instances(n), iterations) for n in runs.INSTANCE_COUNTS
        }
    for count, stages in result.items():
        log(f"breakdown, {count} instance(s): " + ", ".join(f"{k} {v:.2f} ms" for k, v in stages.items()))
    return result


def model_description(model_dir: Path) -> str:
    manifest = load_manifest(model_dir)
    spec = manifest.input
    digest = file_sha256(model_dir / "model.onnx")[:12]
    bundled = model_dir == DEFAULT_MODEL_DIR.resolve()
    return (
        f"`{manifest.name}` from `{model_dir}` (model.onnx sha256 {digest}...), input "
        f"{spec.height}x{spec.width}, {manifest.num_keypoints} keypoints, heatmaps "
        f"{manifest.output.height}x{manifest.output.width}"
        + ("" if bundled else " (**not** the bundled model: CKS_MODEL_DIR points elsewhere)")
    )


def run(args: argparse.Namespace) -> report.Results:
    machine = this_machine()
    log(f"machine: {machine.describe()}")
    model_dir = Path(Settings().model.directory).resolve()
    samples = model_dir / "samples"
    sample = load_sample(samples)
    settings = headline_settings()
    plan = runs.Plan.for_mode(args.quick, args.seconds)
    with tempfile.TemporaryDirectory(prefix="cks-bench-") as directory:
        space = runs.prepare(Path(directory), model_dir, sample, settings)
        points, memory, extra = runs.headline(space, plan, log, with_memory=not args.skip_memory)
        variants = () if args.skip_tuning else runs.TUNING
        tuned = runs.tuning(space, plan, variants, log)
    stages = breakdowns(model_dir, sample, settings["inference_threads"], 10 if args.quick else 100)
    post = offline.post_processing(args.quick)
    log("post-processing: " + ", ".join(f"{p.kind} {p.speedup:.1f}x" for p in post))
    calibration = offline.calibration(samples, model_dir, settings["inference_threads"], args.quick)
    write = calibration.store_write_best_s
    log(f"calibration: {calibration.instances_per_s:.0f} instances/s, write 100k instances {write:.2f} s")
    return report.Results(
        command="python -m benchmarks.bench_service"
        + (" --quick" if args.quick else "")
        + (f" --seconds {args.seconds:g}" if args.seconds is not None else ""),
        quick=args.quick,
        machine=machine,
        load_at_end=os.getloadavg(),
        model=model_description(model_dir),
        settings=settings,
        points=points,
        memory=memory,
        extra=extra,
        breakdown=stages,
        post=post,
        calibration=calibration,
        tuning=tuned,
    )


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few seconds per point")
    parser.add_argument(
        "--seconds", type=float, help="seconds per headline point (default 10, quick 2; tuning at most 6)"
    )
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT, help="the Markdown report to write")
    parser.add_argument("--skip-memory", action="store_true", help="skip the 10 000-request memory run")
    parser.add_argument("--skip-tuning", action="store_true", help="skip the tuning variants")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    require_wrk()
    started = time.monotonic()
    results = run(args)
    text = report.render(results)
    page.write_section(args.output, "bench_service", page.demote(text))
    log(f"\n{text}\nwrote {args.output} in {time.monotonic() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
