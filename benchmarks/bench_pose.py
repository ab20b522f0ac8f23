"""Cost and tightness of pose sets (service/pose) on the bundled samples, per instance.

Run: python -m benchmarks.bench_pose [--samples 100] [--epsilon 0.1 --epsilon 0.3] [--images N]
                                    [--splits 0]

Object-scope sets come from the bundled model and calibration (in process, a temporary data
directory); the camera matrix and true poses from the samples' annotations. For each instance it
times the three steps the predict API runs, in milliseconds per instance (median and mean):
    estimate  PnP on the set centres (+ refinement into PURSE when outside)
    inner     the sampled bound: --samples draws of keypoints inside the sets, PnP, membership
    outer     the relaxation (7 conic programs with Clarabel per rotation cell, certificates checked;
              --splits rounds of branch-and-bound over rotation cells, as pose.outer_splits)
and reports the tightness: outer / inner for translation and rotation (median over instances with
both), how many outer bounds were certified, how many true poses were in PURSE, and that every
certified bound contained the true pose's error when it was.
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
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.api.predict_input import predict_query  # noqa: E402
from service.api.predict_presenter import predict_response  # noqa: E402
from service.api.predict_schemas import BallSet, EllipseSet, PredictParameters  # noqa: E402
from service.pose import Pose, membership  # noqa: E402
from service.pose.bounds import inner_bound, sample_poses_in_set  # noqa: E402
from service.pose.estimate import pnp_on_centres, refine_into_set  # noqa: E402
from service.pose.relaxation import outer_bound  # noqa: E402
from service.pose.rotations import rotation_angle_deg  # noqa: E402
from service.runtime.container import build_state  # noqa: E402
from service.runtime.settings import Settings  # noqa: E402


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
    manifest = state.detector.manifest
    for image in coco["images"][:images]:
        annotations = [a for a in coco["annotations"] if a["image_id"] == image["id"]]
        jpeg = (model_dir / "samples" / image["file_name"]).read_bytes()
        parameters = PredictParameters(
            instances=[{"object": names[a["category_id"]], "bbox": a["bbox"]} for a in annotations],
            coverage="object",
            epsilon=epsilon,
        )
        query = predict_query(parameters)
        response = predict_response(state.predictor.predict(jpeg, query), query, manifest)
        for ann, answer in zip(annotations, response.instances, strict=True):
            centers, shapes = set_arrays(answer.keypoints)
            points = np.array(manifest.object(answer.object).keypoints_3d)
            truth = Pose(np.array(ann["cam_R_m2c"]), np.array(ann["cam_t_m2c"]))
            yield np.array(ann["cam_K"]), points, centers, shapes, truth


def timed(function, *args):
    start = time.perf_counter()
    result = function(*args)
    return result, (time.perf_counter() - start) * 1e3


def estimate(camera, points, centers, shapes):
    start = pnp_on_centres(camera, points, centers)
    if start is None or membership(start, camera, points, centers, shapes).inside:
        return start
    return refine_into_set(start, camera, points, centers, shapes)


def run(epsilon: float, samples: int, images: int, splits: int = 0) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-pose-") as data_dir:
        return _run(Settings(data_dir=Path(data_dir)), epsilon, samples, images, splits)


def _run(settings: Settings, epsilon: float, samples: int, images: int, splits: int) -> dict:
    state = build_state(settings)
    costs = {"estimate": [], "inner": [], "outer": []}
    ratios_t, ratios_r = [], []
    bounds = {"inner": [], "outer": [], "error": []}  # (rotation deg, translation) per instance
    counts = {
        "instances": 0,
        "estimated": 0,
        "certified": 0,
        "true_inside": 0,
        "certified_true_inside": 0,
        "contained": 0,
    }
    try:
        for camera, points, centers, shapes, truth in instances(
            state, settings.model.model_dir, epsilon, images
        ):
            counts["instances"] += 1
            counts["true_inside"] += membership(truth, camera, points, centers, shapes).inside
            pose, ms = timed(estimate, camera, points, centers, shapes)
            costs["estimate"].append(ms)
            if pose is None:
                continue
            counts["estimated"] += 1
            sampled, ms = timed(sample_poses_in_set, pose, camera, points, centers, shapes, samples)
            inner = inner_bound(pose, sampled)
            costs["inner"].append(ms)
            outer, ms = timed(outer_bound, pose, camera, points, centers, shapes, sampled.poses, splits)
            costs["outer"].append(ms)
            if not outer.certified:
                continue
            counts["certified"] += 1
            bounds["inner"].append((inner.rotation_deg, inner.translation))
            bounds["outer"].append((outer.rotation_deg, outer.translation))
            error = np.linalg.norm(pose.translation - truth.translation)
            bounds["error"].append((rotation_angle_deg(pose.rotation, truth.rotation), error))
            if inner.translation > 0:
                ratios_t.append(outer.translation / inner.translation)
                ratios_r.append(outer.rotation_deg / inner.rotation_deg)
            if membership(truth, camera, points, centers, shapes).inside:
                counts["certified_true_inside"] += 1
                counts["contained"] += int(
                    rotation_angle_deg(pose.rotation, truth.rotation) <= outer.rotation_deg
                    and np.linalg.norm(pose.translation - truth.translation) <= outer.translation
                )
    finally:
        state.close()
    return {"costs": costs, "ratios": (ratios_t, ratios_r), "counts": counts, "bounds": bounds}


def report(epsilon: float, samples: int, splits: int, result: dict) -> list[str]:
    lines = [
        f"epsilon {epsilon:g}, object coverage, {samples} samples for the inner bound, {splits} outer splits"
    ]
    lines.append(f"{'step':<9} {'median ms':>10} {'mean ms':>9} {'instances':>10}")
    for step, values in result["costs"].items():
        if values:
            median, mean = statistics.median(values), statistics.fmean(values)
            lines.append(f"{step:<9} {median:>10.2f} {mean:>9.2f} {len(values):>10}")
    counts = result["counts"]
    ratios_t, ratios_r = result["ratios"]
    if ratios_t:
        lines.append(
            f"tightness (outer / inner, median): translation {statistics.median(ratios_t):.1f}x, "
            f"rotation {statistics.median(ratios_r):.1f}x"
        )
    for name, label in [("error", "true error"), ("inner", "inner bound"), ("outer", "outer bound")]:
        pairs = result["bounds"][name]
        if pairs:
            rotation, translation = (statistics.median(p[k] for p in pairs) for k in (0, 1))
            lines.append(f"median {label:<11}: rotation {rotation:6.1f} deg, translation {translation:7.1f}")
    true_inside = counts["true_inside"]
    lines.append(
        f"instances {counts['instances']}, estimated {counts['estimated']}, outer certified "
        f"{counts['certified']}, true pose in PURSE {true_inside}; certified bounds containing the true "
        f"error: {counts['contained']} of {counts['certified_true_inside']} (certified, true pose in PURSE)"
    )
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--epsilon", type=float, action="append", help="repeatable; default 0.1 and 0.3")
    parser.add_argument("--samples", type=int, default=100)
    parser.add_argument("--images", type=int, default=1000, help="use the first N sample images")
    parser.add_argument("--splits", type=int, default=0, help="branch-and-bound rounds (pose.outer_splits)")
    args = parser.parse_args(argv)
    previous = logging.root.manager.disable
    logging.disable(logging.INFO)  # the service's startup lines
    try:
        print(f"load avg (1m) {os.getloadavg()[0]:.2f}")
        for epsilon in args.epsilon or [0.1, 0.3]:
            result = run(epsilon, args.samples, args.images, args.splits)
            print("\n".join(report(epsilon, args.samples, args.splits, result)))
    finally:
        logging.disable(previous)


if __name__ == "__main__":
    main()
