"""Cost and tightness of pose sets (service/pose) on the bundled samples, per instance.

Run: python -m benchmarks.bench_pose [--samples 100] [--epsilon 0.1 --epsilon 0.3] [--images N]
                                    [--programs 150] [--splits 6]
                                    [--sequences 3 --frames 10 --seed 0]

Object-scope sets come from the bundled model and calibration (in process, a temporary data
directory); the camera matrix and true poses from the samples' annotations. For each instance it
times the steps the predict API runs, in milliseconds per instance:
    estimate  PnP on the set centres (+ refinement into PURSE when outside)
    inner     --samples draws of keypoints inside the sets (PnP, membership) and the boundary search
              (poses pushed to PURSE's edge by local optimisation): poses known to be in PURSE
    outer     the certified bounds, side by side:
              whole     the whole-space relaxation (7 conic programs), as outer_programs 0
              splits    --splits rounds of the older branch-and-bound, as pose.outer_splits
              search    the search over rotation cubes, --programs conic programs at most, as
                        pose.outer_programs (the default)
Per method: certified bounds, their median and 90th percentile, outer / inner per quantity (the
inner bound is the same for all three: the farthest poses found in PURSE), the time, and how many
certified bounds contained the true pose's error when the true pose was in PURSE.

Then the whole pose answer per instance as the predict API computes it (``instance_pose_sets``
with the request's defaults: 100 samples, the search with --programs): on the samples' single
frames, and on ``--sequences`` camera sequences of ``--frames`` consecutive frames rendered by the
bundled generator (training/streams.py, sequence s drawn from (--seed, s)), their sets predicted
by the bundled model. Median, 90th percentile and spread (min-max) of wall and CPU ms, tightness
and the certification check (certified bounds containing the true error when the true pose is in
PURSE). Rendering and prediction are not timed.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.api.predict.predict_input import predict_query  # noqa: E402
from service.api.predict.predict_presenter import predict_response  # noqa: E402
from service.api.predict.predict_schemas import BallSet, EllipseSet, PredictParameters  # noqa: E402
from service.infra.settings import Settings  # noqa: E402
from service.pose import Pose, PoseOptions, instance_pose_sets, membership  # noqa: E402
from service.pose.bounds import SampledPoses, boundary_poses, inner_bound, sample_poses_in_set  # noqa: E402
from service.pose.estimate import pnp_on_centres, refine_into_set  # noqa: E402
from service.pose.relaxation import outer_bound  # noqa: E402
from service.pose.rotations import rotation_angle_deg  # noqa: E402
from service.serving.container import build_state  # noqa: E402


def set_arrays(keypoints) -> tuple[np.ndarray, np.ndarray]:
    """Centres and shape matrices of a response's keypoint sets (zeros: unbounded)."""
    centers = np.array([kp.set.center if hasattr(kp.set, "center") else kp.point for kp in keypoints])
    shapes = np.zeros((len(keypoints), 2, 2))
    for row, kp in enumerate(keypoints):
        if isinstance(kp.set, BallSet):
            shapes[row] = np.eye(2) / kp.set.radius**2
        elif isinstance(kp.set, EllipseSet):
            shapes[row] = np.array(kp.set.shape_matrix)
    return centers, shapes


def instances(state, model_dir: Path, epsilon: float, images: int):
    """(camera, keypoints_3d, centers, shapes, true pose) of every sample instance."""
    coco = json.loads((model_dir / "samples" / "annotations.json").read_text())
    names = {c["id"]: c["name"] for c in coco["categories"]}
    for image in coco["images"][:images]:
        annotations = [a for a in coco["annotations"] if a["image_id"] == image["id"]]
        jpeg = (model_dir / "samples" / image["file_name"]).read_bytes()
        yield from predicted_cases(
            state, jpeg, [names[a["category_id"]] for a in annotations], annotations, epsilon
        )


def predicted_cases(state, image: bytes, names: list[str], annotations: list[dict], epsilon: float):
    """(camera, keypoints_3d, centers, shapes, true pose) per annotated instance of one image, its
    object-scope sets predicted by the service's predictor."""
    manifest = state.detector.manifest
    parameters = PredictParameters(
        instances=[{"object": n, "bbox": a["bbox"]} for n, a in zip(names, annotations, strict=True)],
        coverage="object",
        epsilon=epsilon,
    )
    query = predict_query(parameters)
    response = predict_response(state.predictor.predict(image, query), query, manifest)
    for ann, answer in zip(annotations, response.instances, strict=True):
        centers, shapes = set_arrays(answer.keypoints)
        points = np.array(manifest.object(answer.object).keypoints_3d)
        truth = Pose(np.array(ann["cam_R_m2c"]), np.array(ann["cam_t_m2c"]))
        yield np.array(ann["cam_K"]), points, centers, shapes, truth


def timed(function, *args):
    """(result, wall ms, CPU ms of this process): on a shared machine the CPU time is what the
    call would take alone (the solvers run on one thread)."""
    wall, cpu = time.perf_counter(), time.process_time()
    result = function(*args)
    return result, (time.perf_counter() - wall) * 1e3, (time.process_time() - cpu) * 1e3


def estimate(camera, points, centers, shapes):
    start = pnp_on_centres(camera, points, centers)
    if start is None or membership(start, camera, points, centers, shapes).inside:
        return start
    return refine_into_set(start, camera, points, centers, shapes)


def inner_poses(pose, camera, points, centers, shapes, samples: int) -> SampledPoses:
    sampled = sample_poses_in_set(pose, camera, points, centers, shapes, samples)
    boundary = boundary_poses(pose, camera, points, centers, shapes)
    return SampledPoses([*sampled.poses, *boundary], sampled.tried, len(boundary))


def methods(programs: int, splits: int) -> dict[str, tuple[int, int]]:
    """name -> (splits, programs) of outer_bound."""
    chosen = {"whole": (0, 0)}
    if splits:
        chosen[f"splits {splits}"] = (splits, 0)
    if programs:
        chosen[f"search {programs}"] = (0, programs)
    return chosen


def run(epsilon: float, samples: int, images: int, programs: int = 150, splits: int = 0) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-pose-") as data_dir:
        return _run(Settings(data_dir=Path(data_dir)), epsilon, samples, images, methods(programs, splits))


def _run(settings: Settings, epsilon: float, samples: int, images: int, chosen: dict) -> dict:
    state = build_state(settings)
    costs = {"estimate": [], "inner": []}
    counts = {"instances": 0, "estimated": 0, "true_inside": 0}
    truth_and_inner = {"error": [], "inner": []}  # (rotation deg, translation) per estimated instance
    outer = {
        name: {"ms": [], "cpu": [], "bounds": [], "ratios": [], "certified": 0, "checked": 0, "contained": 0}
        for name in chosen
    }
    try:
        for camera, points, centers, shapes, truth in instances(
            state, settings.model.directory, epsilon, images
        ):
            counts["instances"] += 1
            inside = membership(truth, camera, points, centers, shapes).inside
            counts["true_inside"] += inside
            pose, ms, _ = timed(estimate, camera, points, centers, shapes)
            costs["estimate"].append(ms)
            if pose is None:
                continue
            counts["estimated"] += 1
            found, ms, _ = timed(inner_poses, pose, camera, points, centers, shapes, samples)
            costs["inner"].append(ms)
            inner = inner_bound(pose, found)
            error = (
                rotation_angle_deg(pose.rotation, truth.rotation),
                float(np.linalg.norm(pose.translation - truth.translation)),
            )
            truth_and_inner["error"].append(error)
            truth_and_inner["inner"].append((inner.rotation_deg, inner.translation))
            for name, (splits, programs) in chosen.items():
                bound, ms, cpu = timed(
                    outer_bound, pose, camera, points, centers, shapes, found.poses, splits, programs
                )
                record = outer[name]
                record["ms"].append(ms)
                record["cpu"].append(cpu)
                if not bound.certified:
                    continue
                record["certified"] += 1
                record["bounds"].append((bound.rotation_deg, bound.translation))
                if inner.translation > 0 and inner.rotation_deg > 0:
                    record["ratios"].append(
                        (bound.rotation_deg / inner.rotation_deg, bound.translation / inner.translation)
                    )
                if inside:
                    record["checked"] += 1
                    record["contained"] += int(
                        error[0] <= bound.rotation_deg and error[1] <= bound.translation
                    )
    finally:
        state.close()
    return {"costs": costs, "counts": counts, "truth_and_inner": truth_and_inner, "outer": outer}


def sequence_instances(state, epsilon: float, seed: int, sequences: int, frames: int):
    """(camera, keypoints_3d, centers, shapes, true pose) of every instance of rendered camera
    sequences, frame after frame (training/streams.py; rendered and predicted now, not timed)."""
    import cv2

    from training.annotate import annotate_scene
    from training.objects import OBJECT_CLASSES
    from training.scene import World
    from training.streams import render_sequence

    world = World()
    try:
        for s in range(sequences):
            for view in render_sequence(world, np.random.default_rng([seed, s]), frames):
                annotations = annotate_scene(view)
                if not annotations:
                    continue
                names = [OBJECT_CLASSES[a["category_id"] - 1].name for a in annotations]
                png = cv2.imencode(".png", view.rgb[:, :, ::-1])[1].tobytes()
                yield from predicted_cases(state, png, names, annotations, epsilon)
    finally:
        world.close()


def per_instance(cases, samples: int, programs: int) -> dict:
    """The whole pose answer per instance, as the predict API computes it: times, tightness and the
    certification check."""
    record = {"ms": [], "cpu": [], "ratios": [], "certified": 0, "checked": 0, "contained": 0, "instances": 0}
    record["why not"] = Counter()
    for camera, points, centers, shapes, truth in cases:
        options = PoseOptions(camera, samples=samples, outer_programs=programs)
        answer, ms, cpu = timed(instance_pose_sets, points, centers, shapes, options)
        record["instances"] += 1
        record["ms"].append(ms)
        record["cpu"].append(cpu)
        outer, inner = answer.outer, answer.inner
        if answer.estimate is None or outer is None or not outer.certified or outer.empty:
            record["why not"][_why_not(answer)] += 1
            continue
        record["certified"] += 1
        if inner is not None and inner.rotation_deg > 0 and inner.translation > 0:
            record["ratios"].append(
                (outer.rotation_deg / inner.rotation_deg, outer.translation / inner.translation)
            )
        if membership(truth, camera, points, centers, shapes).inside:
            record["checked"] += 1
            error = (
                rotation_angle_deg(answer.estimate.rotation, truth.rotation),
                float(np.linalg.norm(answer.estimate.translation - truth.translation)),
            )
            record["contained"] += int(error[0] <= outer.rotation_deg and error[1] <= outer.translation)
    return record


def _why_not(answer) -> str:  # noqa: ANN001 - a PoseSets without a certified bound
    if answer.estimate is None:
        return "no estimate in PURSE"
    if answer.outer is None:
        return "no outer bound"
    return answer.outer.status.split(":")[0]


def report_per_instance(name: str, record: dict) -> str:
    ratios, wall = record["ratios"], record["ms"]
    spread = f"{min(wall):.0f}-{max(wall):.0f}" if wall else "-"
    rotation, translation = _quantiles([r[0] for r in ratios]), _quantiles([r[1] for r in ratios])
    return (
        f"  {name}: {record['instances']} instances; {_quantiles(wall, 0)} ms wall (spread {spread}), "
        f"{_quantiles(record['cpu'], 0)} ms CPU; outer / inner rotation {rotation}, translation "
        f"{translation}; certified {record['certified']}; certified bounds containing the true error: "
        f"{record['contained']} of {record['checked']} (true pose in PURSE); not certified: "
        f"{dict(record['why not']) or 'none'}"
    )


def _quantiles(values, digits: int = 2) -> str:
    """median / p90."""
    if not values:
        return "-"
    return f"{statistics.median(values):.{digits}f} / {np.percentile(values, 90):.{digits}f}"


def _pairs(pairs, unit: str = "") -> str:
    """median / p90 of rotation (deg) and translation."""
    if not pairs:
        return "-"
    rotation, translation = ([p[k] for p in pairs] for k in (0, 1))
    return (
        f"{statistics.median(rotation):.1f} / {np.percentile(rotation, 90):.1f} deg, "
        f"{statistics.median(translation):.0f} / {np.percentile(translation, 90):.0f}{unit}"
    )


def report(epsilon: float, samples: int, result: dict) -> list[str]:
    counts = result["counts"]
    lines = [
        f"epsilon {epsilon:g}, object coverage: {counts['instances']} instances, {counts['estimated']} "
        f"estimated, true pose in PURSE {counts['true_inside']}",
        f"{'step':<9} {'median ms':>10} {'p90 ms':>9} {'instances':>10}",
    ]
    for step, values in result["costs"].items():
        if values:
            median, p90 = statistics.median(values), np.percentile(values, 90)
            lines.append(f"{step:<9} {median:>10.2f} {p90:>9.2f} {len(values):>10}")
    lines.append(f"true error  (median / p90): {_pairs(result['truth_and_inner']['error'])}")
    lines.append(
        f"inner bound (median / p90): {_pairs(result['truth_and_inner']['inner'])} "
        f"({samples} samples + boundary search)"
    )
    lines.append("tightness (outer / inner, median / p90) and certified outer bounds per method:")
    for name, record in result["outer"].items():
        ratios = record["ratios"]
        lines.append(
            f"  {name:<10} rotation {_quantiles([r[0] for r in ratios])}, translation "
            f"{_quantiles([r[1] for r in ratios])}; bound {_pairs(record['bounds'])}; "
            f"{_quantiles(record['ms'], 0)} ms wall, {_quantiles(record['cpu'], 0)} ms CPU; "
            f"certified {record['certified']}; certified bounds containing the true error: "
            f"{record['contained']} of {record['checked']} (true pose in PURSE)"
        )
    return lines


def whole_answers(epsilon: float, args) -> dict:  # noqa: ANN001 - the parsed arguments
    """Per instance on the samples' single frames and on the rendered camera sequences."""
    with tempfile.TemporaryDirectory(prefix="bench-pose-") as data_dir:
        state = build_state(Settings(data_dir=Path(data_dir)))
        try:
            model_dir = (
                state.detector.manifest_path.parent if hasattr(state.detector, "manifest_path") else None
            )
            model_dir = model_dir or Settings(data_dir=Path(data_dir)).model.directory
            single = list(instances(state, model_dir, epsilon, args.images))
            records = {"single frames (samples)": per_instance(single, args.samples, args.programs)}
            if args.sequences > 0:
                frames = list(sequence_instances(state, epsilon, args.seed, args.sequences, args.frames))
                name = f"camera sequences ({args.sequences} x {args.frames} frames, seed {args.seed})"
                records[name] = per_instance(frames, args.samples, args.programs)
        finally:
            state.close()
    return records


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--epsilon", type=float, action="append", help="repeatable; default 0.1 and 0.3")
    parser.add_argument("--samples", type=int, default=100)
    parser.add_argument("--images", type=int, default=1000, help="use the first N sample images")
    parser.add_argument("--programs", type=int, default=150, help="the search's budget (pose.outer_programs)")
    parser.add_argument(
        "--splits", type=int, default=6, help="older branch-and-bound rounds; 0: leave it out"
    )
    parser.add_argument("--sequences", type=int, default=3, help="rendered camera sequences; 0: none")
    parser.add_argument("--frames", type=int, default=10, help="consecutive frames per sequence")
    parser.add_argument("--seed", type=int, default=0, help="sequence s is drawn from (seed, s)")
    args = parser.parse_args(argv)
    previous = logging.root.manager.disable
    logging.disable(logging.INFO)  # the service's startup lines
    try:
        print(f"load avg (1m) {os.getloadavg()[0]:.2f}")
        for epsilon in args.epsilon or [0.1, 0.3]:
            result = run(epsilon, args.samples, args.images, args.programs, args.splits)
            print("\n".join(report(epsilon, args.samples, result)))
            steps = f"estimate, {args.samples} samples, boundary search, search {args.programs}"
            print(f"pose sets per instance, median / p90 ({steps}):")
            for name, record in whole_answers(epsilon, args).items():
                print(report_per_instance(name, record))
    finally:
        logging.disable(previous)


if __name__ == "__main__":
    main()
