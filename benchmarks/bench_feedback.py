"""Field labels on camera streams: the live coverage alarm, static vs adaptive sets, retention's cost.

Run: python -m benchmarks.bench_feedback --shift-sequences 100   (also --sequences, --frames,
--orders, --delay, --gamma, --requests; the first run renders and infers for about 20 minutes on 2
shared cores, later runs replay the cache in seconds)

Data: camera sequences of the bundled generator (training/streams.py, rendered and cached by
benchmarks/bench_drift_streams.py under data/streams/), seeds the calibration never used:
``--sequences`` in distribution and ``--shift-sequences`` with heavy occlusion. Every frame's true
keypoints come with it (the generator's labels); the detector's statistics and the ``cov`` score
of every labelled keypoint are cached beside the renders.

Replay (epsilon 0.1, keypoint coverage, the bundled calibration, version 1), as the service does it
(service/feedback/): a frame is served, its labels arrive ``--delay`` frames later (a review queue
30 frames = 1 s behind a 30 fps camera), then
- live coverage: one vote per look (service.monitoring.looks.LookTracker), the share covered of a
  look's first labelled frame; the alarm (service.feedback.confidence_sequence.BettingAlarm) when
  coverage is proven below the version's floor (CKS_FEEDBACK_ALARM_LEVEL 0.01: Beta band at 0.005,
  e-process at 0.005);
- adaptive sets: ACI with gamma ``--gamma`` on the labels in the order they arrive.
False alarms: the in-distribution sequences in ``--orders`` random orders, the alarm restarted after
each. Shift: ``WARM_UP`` in-distribution frames, then the occluded sequences; frames from the shift
to the alarm; coverage per window of ``WINDOW`` frames after the shift, static and adaptive.
Retention cost: POST /v1/predict in process (the ASGI app, SQLite store) on a bundled sample image,
``retain`` false and true alternated (paired), p50 of each.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastapi.testclient import TestClient  # noqa: E402

from benchmarks.bench_drift_streams import CACHE, SEED_IN, SEED_SHIFT, images_with_boxes, rendered  # noqa: E402
from benchmarks.service_bench.breakdown import service_state  # noqa: E402
from service.conformal import CovScore, heatmap_statistics  # noqa: E402
from service.detector.crop import apply_affines  # noqa: E402
from service.feedback.adaptive import AdaptiveView, aci_step  # noqa: E402
from service.feedback.confidence_sequence import BettingAlarm, promised_floor  # noqa: E402
from service.infra.settings import Settings  # noqa: E402
from service.monitoring.looks import Frame, LookTracker  # noqa: E402
from service.serving.app import create_app  # noqa: E402
from tests.predict_client import instances_of  # noqa: E402
from tests.samples import load_samples, samples_by_image  # noqa: E402
from training.coco import read_coco  # noqa: E402

EPSILON, LEVEL = 0.1, 0.01
WARM_UP, WINDOW = 300, 100
SHIFT = "heavy_occlusion"


@dataclass(frozen=True)
class LabelledFrame:
    sequence: int
    frame: Frame
    channels: np.ndarray  # (M,) of the labelled rows
    scores: np.ndarray  # (M,) cov scores of their true points


def labelled_frames(folder: Path, state) -> list[LabelledFrame]:  # noqa: ANN001
    """Every frame with boxes, its labelled keypoints' cov scores (cached beside the renders)."""
    cache = folder / f"feedback-{state.detector.model_hash[:12]}.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    spec = state.detector.manifest.heatmap
    frames = []
    for image, instances, objects, boxes in images_with_boxes(folder):
        result = state.detector.infer(cv2.imread(str(folder / image["file_name"])), boxes, list(objects))
        triples = np.concatenate([np.reshape(a["keypoints"], (-1, 3)) for a in instances])
        labelled = triples[:, 2] > 0
        points = apply_affines(result.affines[result.instance_index], triples[:, :2])
        statistics = heatmap_statistics(
            result.heatmaps[labelled], spec.normalization, spec.top_k, spec.temperature
        )
        scores = CovScore().score(statistics, points[labelled])
        frames.append(
            LabelledFrame(image["sequence"], Frame(objects, boxes), result.channel[labelled], scores)
        )
    cache.write_bytes(pickle.dumps(frames))
    return frames


class Thresholds:
    """The bundled calibration's cov thresholds per channel, at any level (cached per level)."""

    def __init__(self, state) -> None:  # noqa: ANN001
        self._registry, self._version = state.registry, state.registry.resolve(None)
        self._cache: dict[float, np.ndarray] = {}
        guarantees = state.registry.thresholds(self._version, "cov", "keypoint", EPSILON, None).guarantees
        self.floors = np.array([promised_floor(g.n, g.t, g.epsilon, None, LEVEL / 2) for g in guarantees])

    def at(self, level: float) -> np.ndarray:
        if level not in self._cache:
            self._cache[level] = self._registry.thresholds(
                self._version, "cov", "keypoint", level, None
            ).values
        return self._cache[level]


@dataclass
class Replay:
    """Per served frame: static misses, adaptive misses (labelled keypoints), alarm position."""

    static: list[tuple[int, int]]  # (misses, labelled) per frame
    adaptive: list[tuple[int, int]]
    alarms: list[int]  # frames (1-based) at which the alarm fired (restarted after each)
    bound: float  # the ACI bound widened for the labels in flight: (0.9 + gamma (1 + d)) / (gamma T)
    labelled_frames: int  # frames whose labels arrived (T counts their keypoints)
    votes: list[tuple[float, float, int]]  # (vote, floor, frame) of each look, in order


def replay(stream: list[LabelledFrame], thresholds: Thresholds, delay: int, gamma: float) -> Replay:
    """Serve every frame, learn from its labels ``delay`` frames later (see the module's doc)."""
    static_thr = thresholds.at(EPSILON)
    tracker, looks = LookTracker(), []
    alpha, steps, alarms = EPSILON, 0, []
    alarm, votes = BettingAlarm(LEVEL), []
    static, adaptive, served = [], [], []
    for position, frame in enumerate(stream, 1):
        new_look = tracker.is_new_look(frame.frame)
        looks.append(0 if not looks else looks[-1] + new_look)
        level = AdaptiveView("", EPSILON, alpha, gamma, steps, 0).served_epsilon
        static_miss = frame.scores > static_thr[frame.channels]
        adaptive_miss = frame.scores > thresholds.at(level)[frame.channels]
        static.append((int(static_miss.sum()), frame.channels.size))
        adaptive.append((int(adaptive_miss.sum()), frame.channels.size))
        served.append((static_miss, adaptive_miss))
        arrived = position - delay  # the labels of this frame (1-based) arrive now
        if arrived < 1:
            continue
        missed_static, missed_adaptive = served[arrived - 1]
        for missed in missed_adaptive:
            alpha, steps = aci_step(alpha, EPSILON, gamma, bool(missed)), steps + 1
        look = looks[arrived - 1]
        if missed_static.size and (arrived == 1 or looks[arrived - 2] != look):  # the look's first frame
            floor = float(thresholds.floors[stream[arrived - 1].channels].mean())
            votes.append((float(1 - missed_static.mean()), floor, arrived))
            if alarm.observe(*votes[-1][:2]):
                alarms.append(position)
                alarm = BettingAlarm(LEVEL)
    in_flight = max(sum(f.channels.size for f in stream[i : i + delay]) for i in range(len(stream)))
    bound = (max(EPSILON, 1 - EPSILON) + gamma * (1 + in_flight)) / (gamma * steps)
    return Replay(static, adaptive, alarms, bound, len(stream) - delay, votes)


def looks_to_alarm(runs: list[Replay], warm_up: int, draws: int = 200, limit: int = 5000) -> str:
    """Median looks the alarm needs on a long stream whose looks vote like the shifted ones (drawn
    with replacement from the measured votes after the shift): a projection, not a replay."""
    shifted = [(vote, floor) for r in runs for vote, floor, frame in r.votes if frame > warm_up]
    rng = np.random.default_rng(5)
    needed = []
    for _ in range(draws):
        alarm = BettingAlarm(LEVEL)
        picks = rng.integers(len(shifted), size=limit)
        needed.append(next((i for i, k in enumerate(picks, 1) if alarm.observe(*shifted[k])), limit + 1))
    mean_vote = np.mean([v for v, _ in shifted])
    return (
        f"median {np.median(needed):.0f} looks (votes' mean {mean_vote:.3f}, {len(shifted)} votes drawn from)"
    )


def coverage(rows: list[tuple[int, int]]) -> float:
    misses, labelled = np.sum(np.reshape(rows, (-1, 2)), axis=0)
    return float("nan") if labelled == 0 else 1 - misses / labelled


def retention_cost(pairs: int) -> tuple[float, float, float]:
    """p50 (ms) of POST /v1/predict without and with retain, and the median paired difference: one
    in-process app, each pair's order drawn at random, after a warm-up."""
    settings = Settings()
    folder = settings.model.directory / "samples"
    samples = load_samples(folder, read_coco(folder / "annotations.json"))
    path, group = next(iter(samples_by_image(samples).items()))
    image = Path(path).read_bytes()
    rng = np.random.default_rng(1)
    timings: dict[bool, list[float]] = {False: [], True: []}
    with tempfile.TemporaryDirectory() as data:
        app = create_app(Settings(data_dir=Path(data), inference_threads=1, cpu_workers=2))
        with TestClient(app) as client:

            def predict(retain: bool) -> float:
                body = json.dumps({"instances": instances_of(group), "retain": retain})
                parts = {"image": ("i.jpg", image, "image/jpeg"), "request": (None, body, "application/json")}
                began = time.perf_counter()
                response = client.post("/v1/predict", files=parts)
                elapsed = 1000 * (time.perf_counter() - began)
                assert response.status_code == 200 and ("prediction_id" in response.json()) == retain
                return elapsed

            for _ in range(10):
                predict(False)
            for _ in range(pairs):
                first = bool(rng.integers(2))
                timings[first].append(predict(first))
                timings[not first].append(predict(not first))
    without, with_retain = np.array(timings[False]), np.array(timings[True])
    return float(np.median(without)), float(np.median(with_retain)), float(np.median(with_retain - without))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10, help="frames per sequence (one scene)")
    parser.add_argument("--sequences", type=int, default=100, help="in-distribution sequences")
    parser.add_argument("--shift-sequences", type=int, default=30, help="heavy-occlusion sequences")
    parser.add_argument("--orders", type=int, default=10, help="random orders replayed")
    parser.add_argument("--delay", type=int, default=30, help="frames between a frame and its labels")
    parser.add_argument("--gamma", type=float, default=0.005, help="ACI step size")
    parser.add_argument("--requests", type=int, default=300, help="pairs of predict requests (cost)")
    parser.add_argument("--cache", type=Path, default=CACHE)
    arguments = parser.parse_args(argv)
    began = time.perf_counter()
    settings = Settings()
    with service_state(settings.model.directory, 1) as state:
        thresholds = Thresholds(state)
        data = {}
        kinds = (("none", arguments.sequences, SEED_IN), (SHIFT, arguments.shift_sequences, SEED_SHIFT + 1))
        for shift, count, seed in kinds:  # the seeds of bench_drift_streams: one cache for both
            folder = rendered(arguments.cache, shift, count, arguments.frames, seed)
            sequences: dict[int, list[LabelledFrame]] = {}
            for frame in labelled_frames(folder, state):
                sequences.setdefault(frame.sequence, []).append(frame)
            data[shift] = list(sequences.values())
        prepared = time.perf_counter() - began
        rng = np.random.default_rng(0)
        quiet_frames = alarms = 0
        shifted_runs = []
        warm_up = min(WARM_UP, sum(map(len, data["none"])) // 2)
        for _ in range(arguments.orders):
            quiet = [f for i in rng.permutation(len(data["none"])) for f in data["none"][i]]
            run = replay(quiet, thresholds, arguments.delay, arguments.gamma)
            quiet_frames, alarms = quiet_frames + len(quiet), alarms + len(run.alarms)
            shifted = [f for i in rng.permutation(len(data[SHIFT])) for f in data[SHIFT][i]]
            shifted_runs.append(
                replay(quiet[:warm_up] + shifted, thresholds, arguments.delay, arguments.gamma)
            )
    print(
        f"{len(data['none'])} in-distribution sequences, {len(data[SHIFT])} {SHIFT}, {arguments.frames}"
        f" frames each; {arguments.orders} orders; labels {arguments.delay} frames late; epsilon {EPSILON},"
        f" alarm level {LEVEL} (floors {thresholds.floors.min():.3f}-{thresholds.floors.max():.3f});"
        f" ACI gamma {arguments.gamma};"
        f" load {os.getloadavg()[0]:.1f}"
    )
    print(f"\nin distribution: {alarms} false alarms in {quiet_frames} labelled frames")
    first = [next((a - warm_up for a in r.alarms if a > warm_up), None) for r in shifted_runs]
    raised = [f for f in first if f is not None]
    span = len(shifted_runs[0].static) - warm_up
    median = f"{np.median(raised):.0f}" if raised else f">{span}"
    print(f"after the shift: alarm in {len(raised)}/{len(first)} orders, median {median} frames after it")
    print(f"\ncoverage per window of {WINDOW} frames after the shift (mean over orders): static / adaptive")
    for start in range(warm_up, warm_up + span, WINDOW):
        window = slice(start, start + WINDOW)
        static = np.mean([coverage(r.static[window]) for r in shifted_runs])
        adaptive = np.mean([coverage(r.adaptive[window]) for r in shifted_runs])
        print(
            f"  frames {start - warm_up:4d}-{start - warm_up + WINDOW - 1:4d}: {static:.3f} / {adaptive:.3f}"
        )
    long_static = np.mean([coverage(r.static[warm_up:]) for r in shifted_runs])
    long_adaptive = np.mean([coverage(r.adaptive[warm_up:]) for r in shifted_runs])
    print(f"after the shift: static {long_static:.3f}, adaptive {long_adaptive:.3f} (target {1 - EPSILON})")
    whole = [coverage(r.adaptive[: r.labelled_frames]) for r in shifted_runs]
    held = sum(abs(c - (1 - EPSILON)) <= r.bound for c, r in zip(whole, shifted_runs, strict=True))
    bound = np.mean([r.bound for r in shifted_runs])
    print(
        f"whole stream (warm-up and shift, labelled frames), adaptive: {min(whole):.3f} to {max(whole):.3f};"
        f" within the ACI bound widened for the labels in flight (+-{bound:.3f}) in {held}/{len(whole)}"
        f" orders; static {np.mean([coverage(r.static) for r in shifted_runs]):.3f}"
    )
    projected = looks_to_alarm(shifted_runs, warm_up)
    print(f"looks to alarm, resampling the shifted looks' measured votes: {projected}")
    without, with_retain, paired = retention_cost(arguments.requests)
    print(
        f"\nretention cost, POST /v1/predict over {arguments.requests} pairs: p50 {without:.2f} ms without,"
        f" {with_retain:.2f} ms with retain ({100 * (with_retain / without - 1):+.1f} %); median paired"
        f" difference {paired:+.2f} ms ({100 * paired / without:+.1f} %); load {os.getloadavg()[0]:.1f}"
    )
    print(f"\nrendering and inference (cached after the first run): {prepared:.0f} s")
    print(f"whole run: {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
