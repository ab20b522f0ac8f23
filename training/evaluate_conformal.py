"""Regenerate docs/evaluation.md and docs/figures/*.png: the paper's evidence for the served detector.

    python -m training.evaluate_conformal --model models/lmo-synth-unet \
        --calibration data/lmo_synth/calibration --test data/lmo_synth/test --out docs

Inference runs once per image and is cached under --cache (reruns take seconds).
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from service.detector.runtime import Detector
from training.evidence.analysis import collect_evidence
from training.evidence.figures import (
    adaptiveness_figure,
    baseline_figure,
    resplit_figure,
    tightness_figure,
    validity_figure,
)
from training.evidence.overlays import overlay_figure
from training.evidence.report import write_report


def run(
    model: Path,
    calibration: Path,
    test: Path,
    out: Path,
    cache: Path,
    splits: int = 100,
    seed: int = 0,
    threads: int = 2,
    command: str | None = None,
) -> Path:
    """Compute everything, draw the figures into ``out/figures`` and write ``out/evaluation.md``."""
    detector = Detector(model, threads)
    evidence = collect_evidence(detector, calibration, test, cache, splits, seed)
    figures = out / "figures"
    validity_figure(evidence, figures / "validity.png")
    resplit_figure(evidence, figures / "resplits.png")
    tightness_figure(evidence, figures / "tightness.png")
    adaptiveness_figure(evidence, figures / "adaptiveness.png")
    baseline_figure(evidence, figures / "baseline.png")
    _, check = overlay_figure(evidence, detector, test, figures / "overlays.png")
    command = command or "python -m training.evaluate_conformal"
    return write_report(evidence, command, check, out / "evaluation.md")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", type=Path, required=True, help="model directory (model.onnx + manifest)")
    parser.add_argument("--calibration", type=Path, required=True, help="COCO keypoints calibration split")
    parser.add_argument("--test", type=Path, required=True, help="COCO keypoints test split")
    parser.add_argument("--out", type=Path, default=Path("docs"), help="writes evaluation.md and figures/")
    parser.add_argument("--cache", type=Path, default=Path("data/evidence_cache"), help="inference cache")
    parser.add_argument("--splits", type=int, default=100, help="random calibration/test re-splits")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    args = parser.parse_args(argv)
    command = shlex.join(
        ["python", "-m", "training.evaluate_conformal", *(sys.argv[1:] if argv is None else argv)]
    )
    path = run(
        args.model,
        args.calibration,
        args.test,
        args.out,
        args.cache,
        args.splits,
        args.seed,
        args.threads,
        command,
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
