"""Field labels on camera streams: the live coverage alarm, static vs adaptive sets, retention's cost.

Run: python -m benchmarks.bench_feedback   (--runs shifted runs on fresh scene seeds, printed;
--seeds replays given ones; also --sequences, --shift-sequences, --frames, --orders, --delay,
--gamma, --requests). Renders take about 0.15-0.4 s a frame on 2 shared cores (the 10,000
in-distribution frames once, each fresh seed's shifted frames, ``--shift-sequences`` scenes of
each shift, every run); the replay takes seconds.

Data: camera sequences of the bundled generator (training/streams.py, rendered and cached with
benchmarks/bench_drift_streams.rendered under data/streams/), seeds the calibration never used:
``--sequences`` in distribution (seed 9100) and, per run, ``--shift-sequences`` of each shift
of ``SHIFT_SEEDS`` on a seed drawn afresh: heavy occlusion (3 more occluders), which the label-free
drift monitor finds, and a 4x lower resolution (which issue 37 saw it find late); and a shift
no image shows: ``labels_moved``, in-distribution scenes whose labels sit ``LABELS_MOVED_PX``
right of the trained keypoints (the truth moved: the drift monitor, which sees only images, cannot
find it; only labels can). Every frame's true keypoints come with it (the generator's labels);
the detector's statistics, the ``cov`` score of every labelled keypoint (of the moved labels
too) and what the drift monitor records are cached beside the renders.

Replay (epsilon 0.1, keypoint coverage, the bundled calibration, version 1), as the service does it
(service/feedback/): a frame is served, its labels arrive ``--delay`` frames later (a review queue
30 frames = 1 s behind a 30 fps camera), then
- live coverage: one vote per look (service.monitoring.looks.LookTracker), the share covered of
  the units of all its labelled frames, cast when the first label of the next look arrives (the
  stream's last look stays open, as in service.feedback.live_coverage); the alarm
  (service.feedback.confidence_sequence.CoverageAlarm, CKS_FEEDBACK_ALARM_LEVEL 0.01) when coverage
  is proven below what the calibration gives (its ladder of floors: quantiles 0.002, 0.01, 0.05 of
  each threshold's coverage law); floors printed: each threshold's 0.005 quantile;
- adaptive sets: ACI with gamma ``--gamma`` on the labels in the order they arrive, the label lag
  L counted as the service counts it (service.feedback.adaptive).
False alarms: the in-distribution sequences in ``--orders`` random orders, the alarm restarted after
each alarm. Per shift and run: ``WARM_UP`` in-distribution frames, then the run's shifted
sequences; frames from the shift to the coverage alarm and to the label-free drift alarm (the
sequential one, as served: benchmarks.bench_drift_streams.replay, on the same frames), min,
median, max over runs; miscoverage of static and
adaptive sets over the labels of the shifted frames, against ACI's bound over them (alpha_1 the
level at the shift, L the largest label lag); coverage per window of ``WINDOW`` frames.
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

from benchmarks.bench_drift_streams import (  # noqa: E402
    CACHE,
    SEED_IN,
    RecordedFrame,
    by_sequence,
    delay_spread,
    fresh_seeds,
    images_with_boxes,
    monitor,
    recorded_frames,
    rendered,
)
from benchmarks.bench_drift_streams import replay as drift_replay  # noqa: E402
from benchmarks.service_bench.breakdown import service_state  # noqa: E402
from calibration_store import ScoreTable  # noqa: E402
from service.calibration.bundle import BUNDLE_FILENAME, load_bundle  # noqa: E402
from service.conformal import CovScore, heatmap_statistics  # noqa: E402
from service.detector.crop import apply_affines  # noqa: E402
from service.feedback.adaptive import AdaptiveView, aci_step, long_run_bound  # noqa: E402
from service.feedback.confidence_sequence import (  # noqa: E402
    BettingEProcess,
    CoverageAlarm,
    promised_floor,
    rung_floors,
)
from service.infra.settings import Settings  # noqa: E402
from service.monitoring.looks import Frame, LookTracker  # noqa: E402
from service.serving.app import create_app  # noqa: E402
from tests.predict_client import instances_of  # noqa: E402
from tests.samples import load_samples, samples_by_image  # noqa: E402
from training.coco import read_coco  # noqa: E402

EPSILON, LEVEL = 0.1, 0.01
WARM_UP, WINDOW = 300, 500
#: the shifts replayed, and the offset of each one's scene seed from the run's seed: heavy occlusion
#: on the run's seed itself (as before the second shift), a lower resolution (x4) on seed + 3 (as
#: bench_drift_streams renders it)
SHIFT_SEEDS = {"heavy_occlusion": 0, "low_resolution": 3}
SHIFT_SEQUENCES = 250
#: a shift of the truth, not of the images: in-distribution scenes whose labels sit this many pixels
#: right of the points the model was trained on (a re-defined keypoint, a part revision that moved a
#: grasp point, a motion-capture rig whose extrinsics drifted); the drift monitor cannot see it
LABELS_MOVED, LABELS_MOVED_PX = "labels_moved", 3.0


@dataclass(frozen=True)
class LabelledFrame:
    sequence: int
    frame: Frame
    channels: np.ndarray  # (M,) of the labelled rows
    scores: np.ndarray  # (M,) cov scores of their true points


def labelled_frames(folder: Path, state, moved: float = 0.0) -> list[LabelledFrame]:  # noqa: ANN001
    """Every frame with boxes, its labelled keypoints' cov scores (cached beside the renders); with
    ``moved``, of labels that many pixels right of the true points (the truth moved, not the images)."""
    suffix = f"-labels-moved-{moved:g}px" if moved else ""
    cache = folder / f"feedback-{state.detector.model_hash[:12]}{suffix}.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    spec = state.detector.manifest.heatmap
    frames = []
    for image, instances, objects, boxes in images_with_boxes(folder):
        result = state.detector.infer(cv2.imread(str(folder / image["file_name"])), boxes, list(objects))
        triples = np.concatenate([np.reshape(a["keypoints"], (-1, 3)) for a in instances])
        labelled = triples[:, 2] > 0
        points = apply_affines(result.affines[result.instance_index], triples[:, :2] + [moved, 0.0])
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
        self.rungs = np.array([rung_floors(g.n, g.t, g.epsilon, None, LEVEL) for g in guarantees])

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
    alarms: list[int]  # frames (1-based; past the end: after it) at which the alarm fired
    former: list[int]  # the same for main's former alarm (a look's first frame, one e-process)
    levels: list[float]  # alpha before each label learned, and after the last
    served_at: list[int]  # per frame: the labels learned when it was served
    lag: int  # L: the largest label lag (updates between a label's serving and its own)


def replay(stream: list[LabelledFrame], thresholds: Thresholds, delay: int, gamma: float) -> Replay:
    """Serve every frame, learn from its labels ``delay`` frames later, the last frames' after the
    stream ended (see the module's doc)."""
    static_thr = thresholds.at(EPSILON)
    tracker, looks = LookTracker(), []
    alpha, levels, served_at, lag = EPSILON, [EPSILON], [], 0
    alarm, alarms = CoverageAlarm(LEVEL), []
    former, former_alarms = BettingEProcess(LEVEL / 2), []
    look_misses = look_units = 0  # the open look's labelled units (its vote waits for the next look)
    look_floors = np.zeros(thresholds.rungs.shape[1])  # their floors' sums, per rung of the alarm
    static, adaptive, served = [], [], []
    for position in range(1, len(stream) + delay + 1):
        if position <= len(stream):
            frame = stream[position - 1]
            new_look = tracker.is_new_look(frame.frame)
            looks.append(0 if not looks else looks[-1] + new_look)
            level = AdaptiveView("", EPSILON, alpha, gamma, 0, 0).served_epsilon
            static_miss = frame.scores > static_thr[frame.channels]
            adaptive_miss = frame.scores > thresholds.at(level)[frame.channels]
            static.append((int(static_miss.sum()), frame.channels.size))
            adaptive.append((int(adaptive_miss.sum()), frame.channels.size))
            served.append((static_miss, adaptive_miss))
            served_at.append(len(levels) - 1)
        arrived = position - delay  # the labels of this frame (1-based) arrive now
        if arrived < 1:
            continue
        missed_static, missed_adaptive = served[arrived - 1]
        if missed_adaptive.size:  # lags of this frame's labels: up to the last one's
            lag = max(lag, len(levels) - 1 - served_at[arrived - 1] + missed_adaptive.size - 1)
        for missed in missed_adaptive:
            alpha = aci_step(alpha, EPSILON, gamma, bool(missed))
            levels.append(alpha)
        opens = arrived == 1 or looks[arrived - 2] != looks[arrived - 1]
        if missed_static.size and opens:  # the former alarm: the look's first frame votes
            floor = float(thresholds.floors[stream[arrived - 1].channels].mean())
            if former.observe(float(1 - missed_static.mean()), floor):
                former_alarms.append(position)
                former = BettingEProcess(LEVEL / 2)
        if arrived > 1 and opens and look_units:  # the last look is complete
            if alarm.observe(1 - look_misses / look_units, (look_floors / look_units).tolist()):
                alarms.append(position)
                alarm = CoverageAlarm(LEVEL)
            look_misses = look_units = 0
            look_floors = np.zeros_like(look_floors)
        look_misses += int(missed_static.sum())
        look_units += missed_static.size
        look_floors += thresholds.rungs[stream[arrived - 1].channels].sum(axis=0)
    return Replay(static, adaptive, alarms, former_alarms, levels, served_at, lag)


def held_to_bound(run: Replay, start: int, gamma: float) -> tuple[float, float, float]:
    """Over the labels learned of the frames served from ``start`` (0-based) on: (adaptive
    miscoverage, static miscoverage, ACI's bound on |miscoverage - epsilon| over them). Labels are
    learned in frame order, so they are the updates from the first label of ``start`` on, and the
    bound is the module's with alpha_1 the level then (service.feedback.adaptive)."""
    begin = sum(labelled for _, labelled in run.adaptive[:start])
    learned = len(run.levels) - 1 - begin
    frames = slice(start, None)
    adaptive, static = coverage(run.adaptive[frames]), coverage(run.static[frames])
    assert sum(labelled for _, labelled in run.adaptive[frames]) == learned
    return 1 - adaptive, 1 - static, long_run_bound(run.levels[begin], gamma, learned, run.lag)


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


def scenes_of(folder: Path, state, moved: float = 0.0) -> list[list[LabelledFrame]]:  # noqa: ANN001
    sequences: dict[int, list[LabelledFrame]] = {}
    for frame in labelled_frames(folder, state, moved):
        sequences.setdefault(frame.sequence, []).append(frame)
    return list(sequences.values())


def in_order(scenes: list[list[LabelledFrame]], rng: np.random.Generator) -> list[LabelledFrame]:
    return [frame for i in rng.permutation(len(scenes)) for frame in scenes[i]]


def within(miscoverage: float, bound: float) -> str:
    return "within" if abs(miscoverage - EPSILON) <= bound else "outside"


def drift_delay(frames: list[RecordedFrame], start: int, table: ScoreTable, manifest) -> int | None:  # noqa: ANN001
    """Frames from ``start`` to the label-free drift alarm (the sequential one, as served) or None."""
    return drift_replay(lambda: monitor("sequential", table, manifest), frames, start=start)[1]


def shifted_run(
    labelled: list[list[LabelledFrame]],
    recorded: list[list[RecordedFrame]],
    context: dict,
    warm: np.ndarray | None = None,
    drift: bool = True,
) -> tuple[Replay, int | None]:
    """One run: WARM_UP in-distribution frames (of the scenes in ``warm`` order, or a random
    one), then the shift's scenes in a random order; the labels' replay and the drift monitor's
    frames to alarm, on the same frames."""
    quiet, quiet_recorded, rng = context["quiet"], context["quiet_recorded"], context["rng"]
    warm = rng.permutation(len(quiet)) if warm is None else warm
    order = rng.permutation(len(labelled))
    warm_up = [frame for i in warm for frame in quiet[i]][: context["warm_up"]]
    warm_recorded = [frame for i in warm for frame in quiet_recorded[i]][: context["warm_up"]]
    stream = warm_up + [frame for i in order for frame in labelled[i]]
    run = replay(stream, context["thresholds"], context["delay"], context["gamma"])
    if not drift:
        return run, None
    frames = warm_recorded + [frame for i in order for frame in recorded[i]]
    return run, drift_delay(frames, len(warm_up), context["table"], context["manifest"])


def moved_labels_run(
    seed: int, moved: list[list[LabelledFrame]], context: dict, draw: int = 0
) -> tuple[Replay, int | None]:
    """A run of the labels-moved shift: in-distribution scenes (drawn by ``seed``, and ``draw``
    for the paired orders), the first WARM_UP frames' with their true labels, the next
    --shift-sequences scenes' with moved ones; no scene twice (the look tracker would take a scene
    seen again for the same look)."""
    quiet, recorded = context["quiet"], context["quiet_recorded"]
    order = np.random.default_rng([seed, draw] if draw else seed).permutation(len(quiet))
    first = int(np.searchsorted(np.cumsum([len(quiet[i]) for i in order]), context["warm_up"])) + 1
    picked = order[first : first + context["count"]]
    scenes = [moved[i] for i in picked], [recorded[i] for i in picked]
    return shifted_run(*scenes, context, warm=order, drift=not draw)


def report_shift(shift: str, runs: dict[int, tuple[Replay, int | None]], warm_up: int, gamma: float) -> dict:
    span = min(len(run.static) for run, _ in runs.values()) - warm_up
    print(
        f"\nafter {warm_up} in-distribution frames, {shift} ({span}+ frames a run): frames to the coverage"
        f" alarm and to the label-free drift alarm; miscoverage over the labels learned of the shifted"
        f" frames, and ACI's bound on |miscoverage - {EPSILON}| there (alpha_1 = the level at the shift,"
        " L = the largest label lag)"
    )
    delays, former, drift, summary = [], [], [], {}
    for seed, (run, drift_found) in runs.items():
        first = first_alarm(run.alarms, warm_up)
        delays.append(first)
        former.append(first_alarm(run.former, warm_up))
        drift.append(drift_found)
        adaptive, static, bound = held_to_bound(run, warm_up, gamma)
        whole_adaptive, _, whole_bound = held_to_bound(run, 0, gamma)
        summary[seed] = (first, adaptive, static, bound, whole_adaptive, whole_bound, drift_found)
        print(
            f"  seed {seed}: coverage alarm {_after(first)} (the former alarm: {_after(former[-1])}),"
            f" drift alarm {_after(drift_found)};"
            f" miscoverage adaptive {adaptive:.3f} ({within(adaptive, bound)}),"
            f" static {static:.3f} ({within(static, bound)}) the bound"
            f" {bound:.3f} (L {run.lag}); whole stream adaptive {whole_adaptive:.3f}, bound {whole_bound:.3f}"
        )
    print(
        f"frames from the shift to the alarm, min/median/max over the runs (raised in): coverage"
        f" {delay_spread(delays, span)} (former {delay_spread(former, span)}),"
        f" drift {delay_spread(drift, span)}"
    )
    print(f"coverage per window of {WINDOW} frames after the shift (mean over runs): static / adaptive")
    for begin in range(warm_up, warm_up + span, WINDOW):
        window = slice(begin, begin + WINDOW)
        static = np.mean([coverage(run.static[window]) for run, _ in runs.values()])
        adaptive = np.mean([coverage(run.adaptive[window]) for run, _ in runs.values()])
        print(
            f"  frames {begin - warm_up:5d}-{begin - warm_up + WINDOW - 1:5d}: {static:.3f} / {adaptive:.3f}"
        )
    return summary


def paired_orders(shift: str, runs: list[Replay], warm_up: int) -> None:
    """The alarm and the former one on the same streams, each run's scenes in more orders."""
    span = min(len(run.static) for run in runs) - warm_up

    def frames(alarms: str) -> np.ndarray:  # not raised: past the end
        return np.array([first_alarm(getattr(run, alarms), warm_up) or span + 1 for run in runs])

    now, was = frames("alarms"), frames("former")
    print(
        f"paired, {len(runs)} streams of {shift} (more orders of each run's scenes), frames to the alarm:"
        f" raised within {span} now {(now <= span).sum()}, former {(was <= span).sum()}; median now"
        f" {np.median(now):.0f}, former {np.median(was):.0f}; 10-90 % now {np.quantile(now, 0.1):.0f}-"
        f"{np.quantile(now, 0.9):.0f}, former {np.quantile(was, 0.1):.0f}-{np.quantile(was, 0.9):.0f};"
        f" max now {_most(now, span)}, former {_most(was, span)}"
    )


def first_alarm(alarms: list[int], warm_up: int) -> int | None:
    return next((frame - warm_up for frame in alarms if frame > warm_up), None)


def _most(frames: np.ndarray, span: int) -> str:
    return f">{span}" if frames.max() > span else str(frames.max())


def _after(frames: int | None) -> str:
    return "not raised" if frames is None else f"{frames} frames after the shift"


def main(argv: list[str] | None = None) -> dict[str, object]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10, help="frames per sequence (one scene)")
    parser.add_argument("--sequences", type=int, default=1000, help="in-distribution sequences")
    parser.add_argument(
        "--orders", type=int, default=1, help="orders the in-distribution ones are replayed in"
    )
    parser.add_argument(
        "--shift-sequences", type=int, default=SHIFT_SEQUENCES, help="sequences of each shift per run"
    )
    parser.add_argument("--runs", type=int, default=4, help="shifted runs, each on fresh scene seeds")
    parser.add_argument("--seeds", type=int, nargs="+", help="replay these runs' seeds instead of fresh ones")
    parser.add_argument("--delay", type=int, default=30, help="frames between a frame and its labels")
    parser.add_argument("--gamma", type=float, default=0.005, help="ACI step size")
    parser.add_argument(
        "--paired-orders",
        type=int,
        default=0,
        help="per shift and run, this many more orders of its scenes, with the alarm and the former one",
    )
    parser.add_argument("--requests", type=int, default=300, help="pairs of predict requests (cost)")
    parser.add_argument("--cache", type=Path, default=CACHE)
    arguments = parser.parse_args(argv)
    began = time.perf_counter()
    seeds = arguments.seeds or fresh_seeds(arguments.runs)
    print(
        f"scene seeds of this run (heavy occlusion: seed, low resolution: seed + 3):"
        f" {' '.join(map(str, seeds))}; load {os.getloadavg()[0]:.1f}"
    )
    settings = Settings()
    _, table = load_bundle(settings.model.directory / BUNDLE_FILENAME)
    frames, count = arguments.frames, arguments.shift_sequences
    with service_state(settings.model.directory, 1) as state:
        thresholds, manifest = Thresholds(state), state.detector.manifest

        def scenes(shift: str, sequences: int, seed: int) -> tuple[list, list]:
            folder = rendered(arguments.cache, shift, sequences, frames, seed)
            return scenes_of(folder, state), by_sequence(recorded_frames(folder, state))

        quiet, quiet_recorded = scenes("none", arguments.sequences, SEED_IN)
        quiet_folder = rendered(arguments.cache, "none", arguments.sequences, frames, SEED_IN)
        moved = scenes_of(quiet_folder, state, LABELS_MOVED_PX)
        shifted = {
            shift: {seed: scenes(shift, count, seed + offset) for seed in seeds}
            for shift, offset in SHIFT_SEEDS.items()
        }
    prepared = time.perf_counter() - began
    gamma, delay = arguments.gamma, arguments.delay
    rungs = ", ".join(f"{rung.min():.3f}-{rung.max():.3f}" for rung in thresholds.rungs.T)
    print(
        f"{len(quiet)} in-distribution sequences (seed {SEED_IN}), {count} sequences of each shift per run,"
        f" {frames} frames each; labels {delay} frames late; epsilon {EPSILON}, alarm level {LEVEL}"
        f" (floors {thresholds.floors.min():.3f}-{thresholds.floors.max():.3f}; the alarm's rungs"
        f" {rungs}); ACI gamma {gamma}"
    )
    rng = np.random.default_rng(0)
    alarms = replayed = 0
    for _ in range(arguments.orders):
        stream = in_order(quiet, rng)
        alarms, replayed = (
            alarms + len(replay(stream, thresholds, delay, gamma).alarms),
            replayed + len(stream),
        )
    print(
        f"\nin distribution: {alarms} false alarms in {replayed} labelled frames ({arguments.orders}"
        f" order(s) of {len(quiet)} scenes, the alarm restarted after each)"
    )
    warm_up = min(WARM_UP, sum(map(len, quiet)) // 2)
    context = {
        "quiet": quiet,
        "quiet_recorded": quiet_recorded,
        "rng": rng,
        "warm_up": warm_up,
        "thresholds": thresholds,
        "delay": delay,
        "gamma": gamma,
        "table": table,
        "manifest": manifest,
        "count": count,
    }
    shifts, orders = {}, range(arguments.paired_orders)
    for shift, by_seed in shifted.items():
        runs = {seed: shifted_run(*pair, context) for seed, pair in by_seed.items()}
        shifts[shift] = report_shift(shift, runs, warm_up, gamma)
        if orders:
            more = [shifted_run(*pair, context, drift=False)[0] for pair in by_seed.values() for _ in orders]
            paired_orders(shift, more, warm_up)
    runs = {seed: moved_labels_run(seed, moved, context) for seed in seeds}
    shifts[LABELS_MOVED] = report_shift(
        f"{LABELS_MOVED} ({LABELS_MOVED_PX:g} px right)", runs, warm_up, gamma
    )
    if orders:
        more = [moved_labels_run(seed, moved, context, draw)[0] for seed in seeds for draw in orders]
        paired_orders(LABELS_MOVED, more, warm_up)
    without, with_retain, paired = retention_cost(arguments.requests)
    print(
        f"\nretention cost, POST /v1/predict over {arguments.requests} pairs: p50 {without:.2f} ms without,"
        f" {with_retain:.2f} ms with retain ({100 * (with_retain / without - 1):+.1f} %); median paired"
        f" difference {paired:+.2f} ms ({100 * paired / without:+.1f} %); load {os.getloadavg()[0]:.1f}"
    )
    print(f"\nrendering and inference (cached after the first run): {prepared:.0f} s")
    print(f"whole run: {time.perf_counter() - began:.0f} s")
    return {"false_alarms": alarms, "shifts": shifts, "retention": (without, with_retain, paired)}


if __name__ == "__main__":
    from benchmarks.bench_feedback import main as run  # LabelledFrame pickles as the module's

    run()
