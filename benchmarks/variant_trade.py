"""What a compressed variant trades, on labelled images nobody tuned on: each model folder served with
its own bundled calibration (held-out coverage in keypoint and object scope, each object against its
own predictive interval), PCK, the median set area at the same epsilon with calibrations of equal
size (the same instances, scored by each model), and the model's own run.

    python -m training.generate --split test --out data/lmo_synth/fresh --images 1000 --seed $RANDOM$RANDOM
    python -m benchmarks.variant_trade data/lmo_synth/fresh models/lmo-synth-unet models/lmo-synth-unet-int8

writes the ``variant_trade`` section of docs/performance.md.

Sets are built by the steps predict takes (``service.evaluation``); the test interval of a coverage is
the 2.5-97.5 % range of 2,000 bootstrap resamples of whole images (keypoints of one image are not
independent), and a calibration's spread is the Beta(n + 1 - t, t) central 95 % of the median n.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from benchmarks.harness import PERFORMANCE_PAGE, load_average, this_machine, write_section
from benchmarks.quantization_choices import run_times
from calibration_store import ObjectScores, ScoreTable, open_store
from service.calibration.bundle import bootstrap_default_calibration
from service.calibration.coco import ANNOTATIONS_FILENAME, load_coco_batch
from service.calibration.registry import channel_thresholds
from service.calibration.variants import range_crops
from service.conformal import contains, get_nonconformity_score, map_sets_to_image
from service.conformal.laws import beta_interval
from service.detector.manifest import MODEL_FILENAME
from service.detector.session import CPU, Detector, create_session
from service.evaluation.coverage import unit_groups
from service.evaluation.rows import Rows, collect_rows
from service.evaluation.run import resolve_version
from service.evaluation.sizes import set_sizes

EPSILON = 0.1
KINDS = ("peak", "var", "cov")
SCOPES = ("keypoint", "object")
MAX_PIXELS = 50_000_000
RESAMPLES = 2_000


@dataclass(frozen=True)
class Served:
    name: str
    directory: Path
    detector: Detector
    table: ScoreTable
    rows: Rows


def serve(model_dir: Path, test: Path) -> Served:
    """The model, the calibration it serves out of the box, and its rows on the test folder."""
    detector = Detector(model_dir, 1)
    with tempfile.TemporaryDirectory() as scratch, open_store(f"sqlite:///{scratch}/store.db") as store:
        bootstrap_default_calibration(store, detector, model_dir)
        _, table = resolve_version(store, detector, None)
    rows = collect_rows(load_coco_batch(test, detector.manifest), detector, MAX_PIXELS)
    return Served(detector.manifest.variant_name, model_dir, detector, table, rows)


def covered(served: Served, table: ScoreTable, kind: str, scope: str) -> tuple[np.ndarray, np.ndarray, list]:
    """Per row: whether its set holds the label, the set's shape matrix, and the guarantees."""
    rows, manifest = served.rows, served.detector.manifest
    result = channel_thresholds(table, manifest.num_keypoints, kind, scope, EPSILON, None)
    centers, shapes = get_nonconformity_score(kind).region(rows.statistics, result.values[rows.channel])
    centers, shapes = map_sets_to_image(centers, shapes, rows.affine)
    inside = np.zeros(len(centers), dtype=bool)
    inside[rows.labeled] = contains(rows.label[rows.labeled], centers[rows.labeled], shapes[rows.labeled])
    return inside, shapes, result.guarantees


def units(served: Served, scope: str) -> list[tuple[str, tuple[int, ...]]]:
    manifest = served.detector.manifest
    if scope == "object":
        return [(o.name, tuple(o.keypoints)) for o in manifest.objects]
    return [(k.name, (k.index,)) for k in manifest.keypoints]


def pooled(served: Served, inside: np.ndarray, scope: str) -> tuple[float, float, float]:
    """Coverage over rows (keypoint) or instances (object), and its image-clustered 95 % interval."""
    rows = served.rows
    if scope == "object":  # an instance is covered when all its keypoints are
        hits = np.bincount(rows.instance, weights=~inside & rows.labeled) == 0
        image = np.bincount(rows.instance, weights=rows.image_id) / np.bincount(rows.instance)
    else:
        hits, image = inside[rows.labeled], rows.image_id[rows.labeled]
    ids, index = np.unique(image, return_inverse=True)
    per_image, count = np.bincount(index, weights=hits), np.bincount(index)
    draws = np.random.default_rng().integers(0, len(ids), (RESAMPLES, len(ids)))
    spread = per_image[draws].sum(axis=1) / count[draws].sum(axis=1)
    return float(hits.mean()), *np.percentile(spread, [2.5, 97.5])


def same_instances(table: ScoreTable, other: ScoreTable) -> ScoreTable:
    """``table``'s scores of the instances ``other`` holds too (a calibration of equal size)."""
    blocks = []
    for block in table.objects:
        keep = np.isin(block.instance_refs, other.object(block.object_name).instance_refs)
        refs = tuple(np.asarray(block.instance_refs)[keep])
        scores = {kind: matrix[keep] for kind, matrix in block.scores.items()}
        blocks.append(ObjectScores(block.object_name, block.keypoint_ids, refs, scores))
    return ScoreTable(tuple(blocks))


def coverage_table(models: list[Served]) -> list[str]:
    lines = [
        f"Held-out coverage at epsilon {EPSILON}, each model with its bundled calibration; *band*: one"
        " calibration's 95 % spread widened by the test's own interval; *units inside*: objects (keypoints"
        " in keypoint scope) whose covered count lies in their own BetaBinomial predictive interval.",
        "",
        "| model | function | scope | n (median) | coverage [test 95 %] | band | inside | units inside |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for served in models:
        for kind in KINDS:
            for scope in SCOPES:
                inside, _, guarantees = covered(served, served.table, kind, scope)
                value, low, high = pooled(served, inside, scope)
                groups = unit_groups(served.rows, inside, tuple(guarantees), units(served, scope))
                n, t = sorted((g.n, g.t) for g in groups)[(len(groups) - 1) // 2]
                band_low, band_high = beta_interval(n + 1 - t, t, 0.95)
                band = (band_low - (value - low), band_high + (high - value))
                within = "yes" if band[0] <= value <= band[1] else "**no**"
                inside_count = sum(g.inside_predictive() for g in groups)
                lines.append(
                    f"| {served.name} | {kind} | {scope} | {n} | {value:.3f} [{low:.3f}, {high:.3f}] |"
                    f" [{band[0]:.3f}, {band[1]:.3f}] | {within} | {inside_count}/{len(groups)} |"
                )
    return lines


def accuracy_table(models: list[Served]) -> list[str]:
    """PCK@0.05 of the peak point (error / max(w, h)), visible and occluded keypoints."""
    lines = [
        "| model | PCK@0.05 visible | PCK@0.05 occluded | median error visible (px) |",
        "|---|---|---|---|",
    ]
    for served in models:
        rows = served.rows
        centers, _ = get_nonconformity_score("peak").region(rows.statistics, np.ones(len(rows.channel)))
        centers, _ = map_sets_to_image(centers, np.tile(np.eye(2), (len(centers), 1, 1)), rows.affine)
        error = np.linalg.norm(centers - rows.label, axis=1)
        visible, occluded = rows.visibility == 2, rows.visibility == 1
        pck = [float((error[m] / rows.box_side[m] < 0.05).mean()) for m in (visible, occluded)]
        lines.append(f"| {served.name} | {pck[0]:.3f} | {pck[1]:.3f} | {np.median(error[visible]):.2f} |")
    return lines


def area_table(base: Served, variant: Served) -> list[str]:
    base_table = same_instances(base.table, variant.table)
    variant_table = same_instances(variant.table, base_table)
    lines = [
        f"Median set area (image pixels²) at epsilon {EPSILON}, both calibrated on the same"
        f" {variant_table.n_instances} instances:",
        "",
        f"| function | scope | {base.name} | {variant.name} | ratio |",
        "|---|---|---|---|---|",
    ]
    for kind in KINDS:
        for scope in SCOPES:
            areas = []
            for served, table in ((base, base_table), (variant, variant_table)):
                _, shapes, _ = covered(served, table, kind, scope)
                areas.append(float(np.median(set_sizes(kind, shapes[served.rows.labeled]).area)))
            lines.append(
                f"| {kind} | {scope} | {areas[0]:.1f} | {areas[1]:.1f} | {areas[1] / areas[0]:.3f} |"
            )
    return lines


def run_table(models: list[Served], test: Path) -> list[str]:
    """The model's own run on the test folder's first crops, one thread, the models taking turns."""
    sessions = {m.name: create_session(m.directory / MODEL_FILENAME, 1, CPU, spinning=False) for m in models}
    batch = load_coco_batch(test, models[0].detector.manifest)
    first = replace(batch, instances=batch.instances[:400])
    inputs = np.concatenate(list(range_crops(first, models[0].detector, MAX_PIXELS)))
    times = {size: run_times(sessions, inputs, size) for size in (1, 4)}
    lines = ["| model | run, batch 1 (ms) | run, batch 4 (ms) |", "|---|---|---|"]
    return lines + [f"| {name} | {times[1][name]:.2f} | {times[4][name]:.2f} |" for name in sessions]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("test", type=Path, help="labelled renders of a fresh seed")
    parser.add_argument("models", type=Path, nargs=2, help="the source model folder, then its variant's")
    parser.add_argument("--no-write", action="store_true", help="print the section, do not write the page")
    args = parser.parse_args()
    started = time.monotonic()
    models = [serve(directory, args.test) for directory in args.models]
    tables = [
        coverage_table(models),
        accuracy_table(models),
        area_table(*models),
        run_table(models, args.test),
    ]
    info = json.loads((args.test / ANNOTATIONS_FILENAME).read_text()).get("info", {})
    command = " ".join(["python -m benchmarks.variant_trade", *map(shlex.quote, sys.argv[1:])])
    lines = [
        "## What the int8 variant trades (variant_trade)",
        "",
        f"Generated by `{command}` in {(time.monotonic() - started) / 60:.0f} min on"
        f" {this_machine().describe()} (load average at the end {load_average()}). Test images:"
        f" {models[0].rows.images} renders of seed {info.get('seed', '?')} (`training.generate`; a seed no"
        f" calibration or tuning used), {models[0].rows.instances} instances.",
        "",
        *(line for table in tables for line in [*table, ""]),
    ]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        write_section(PERFORMANCE_PAGE, "variant_trade", text)


if __name__ == "__main__":
    main()
