"""The drift alarm on camera streams: false alarms in distribution and detection delay per shift,
the frame-window Kolmogorov-Smirnov alarm (``ks``, the old default) and the sequential alarm
over independent looks (``sequential``, service/monitoring/looks.py) side by side.

Run: python -m benchmarks.bench_drift_streams   (--runs, --seeds, --frames, --sequences,
--shift-sequences, --orders)

Data: camera sequences of the bundled generator (training/streams.py), ``--frames`` frames of
one scene each, with seeds the calibration never used: ``--sequences`` in distribution (seed
9100, the scenes bench_feedback replays too) and, for each of ``--runs`` runs, ``--shift-sequences``
of each shift (heavy occlusion, blur, low resolution, farther camera) on a scene seed drawn afresh
(printed; ``--seeds`` replays them): streams nobody tuned on. Renders and the detector's statistics
of every frame are cached under data/streams/ (ignored by git): a run renders its fresh shifts
(0.15-0.4 s a frame on 2 shared cores), the rest only replays.

Replay: the frames go through ``DriftMonitor.record`` exactly as predict records them (every
statistic computed, as with CKS_DRIFT_FULL_STATISTICS_SHARE=1), the alarm read every
``CHECK_EVERY`` frames, against the bundled calibration (version 1).
- False alarms: the in-distribution sequences in ``--orders`` random orders, one after the
  other; an alarm counts once, then the monitor starts afresh (as after an operator's check).
  Per 10,000 frames.
- Delay, per run: ``WARM_UP`` in-distribution frames, then the run's sequences of the shift in a
  random order; frames from the shift's start to the alarm: min/median/max over the runs (">N"
  when not raised within the N shifted frames rendered), and in how many runs it was raised.

Measured on 2 shared cores (load average 1.5), 10 frames per scene (docs/operations.md):

    $ python -m benchmarks.bench_drift_streams \\
        --seeds 866990420 775392690 106361530 795434330 205979320 604791570
    1000 in-distribution sequences of 10 frames (seed 9100, 10000 frames with boxes) in 1 random
    order(s); 30 per shift and run, 6 runs; alarm read every 10 frames; level 0.01; load 1.5

    method      false alarms / 10k frames  heavy_occlusion      blur  low_resolution    farther
                                      delay min/median/max (runs where raised)
    ks                         1000.0    10/10/10 (6/6)  10/10/10 (6/6) 10/10/10 (6/6) 10/10/10 (6/6)
    sequential                    0.0  240/290/>300 (3/6) 90/140/280 (6/6) 20/>300/>300 (1/6) >300 (0/6)

    rendering and inference (cached after the first run): 429 s  (3 of the 6 seeds' shifts)
    whole run: 481 s

``ks`` raises its alarm at every reading of an in-distribution stream (a window of one scene's
frames is no sample), so its "delays" mean nothing. ``sequential``: no false alarm in the
10,000 frames (1,000 looks); blur is caught within 300 frames in every run, heavy occlusion in
half of them; a lower resolution (x4) and a farther camera (x1.6) change the heatmaps too little
to be seen within 30 scenes.
"""

from __future__ import annotations

import argparse
import os
import pickle
import secrets
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.service_bench.breakdown import service_state  # noqa: E402
from calibration_store import ScoreTable  # noqa: E402
from service.calibration.bundle import BUNDLE_FILENAME, load_bundle  # noqa: E402
from service.conformal import HeatmapStatistics  # noqa: E402
from service.infra.settings import Settings  # noqa: E402
from service.monitoring.drift_monitor import DriftMonitor, DriftSettings  # noqa: E402
from service.monitoring.looks import Frame  # noqa: E402
from service.prediction import calibrated_sets  # noqa: E402
from training.coco import ANNOTATIONS_FILENAME, read_coco  # noqa: E402
from training.generate import generate  # noqa: E402
from training.streams import SHIFTS  # noqa: E402

CACHE = Path("data/streams")
KIND = "cov"
CHECK_EVERY = 10
WARM_UP = 300
SEED_IN = 9100  # never used by the bundled model's splits (training/README.md)
FRESH_SEEDS_FROM = 1_000_000  # above every fixed seed of the splits and the benchmarks
METHODS = ("ks", "sequential")


@dataclass(frozen=True)
class RecordedFrame:
    """What predict hands the drift monitor for one frame."""

    sequence: int
    channels: np.ndarray
    statistics: HeatmapStatistics
    shapes: np.ndarray
    frame: Frame


def rendered(cache: Path, shift: str, sequences: int, frames: int, seed: int) -> Path:
    """The cached renders of a shift (rendered now when missing)."""
    out = cache / f"{shift}-{sequences}x{frames}-seed{seed}"
    if not (out / ANNOTATIONS_FILENAME).exists():
        spec = SHIFTS[shift]
        generate(
            out,
            sequences,
            seed,
            f"stream-{shift}",
            extra_occluders=spec.extra_occluders,
            frames=frames,
            shift=spec,
            progress=False,
        )
    return out


def fresh_seeds(count: int) -> list[int]:
    """Scene seeds drawn afresh, for streams nobody tuned on (print them: ``--seeds`` replays a
    run); multiples of 10 apart, so ``seed + i`` (one per shift) never meets another's."""
    return [FRESH_SEEDS_FROM + 10 * secrets.randbelow(10**8) for _ in range(count)]


def recorded_frames(folder: Path, state) -> list[RecordedFrame]:  # noqa: ANN001
    """Every frame of a rendered folder as the drift monitor records it (cached per model)."""
    cache = folder / f"frames-{state.detector.model_hash[:12]}.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    manifest = state.detector.manifest
    thresholds = state.registry.thresholds(state.registry.resolve(None), KIND, "keypoint", 0.1, None)
    frames = []
    for image, _, objects, boxes in images_with_boxes(folder):
        result = state.detector.infer(cv2.imread(str(folder / image["file_name"])), boxes, list(objects))
        sets = calibrated_sets(result, KIND, thresholds.values, manifest.heatmap, all_statistics=True)
        frames.append(
            RecordedFrame(
                image["sequence"], result.channel, sets.statistics, sets.shapes, Frame(objects, boxes)
            )
        )
    cache.write_bytes(pickle.dumps(frames))
    return frames


def images_with_boxes(folder: Path) -> Iterator[tuple[dict, list[dict], tuple[str, ...], np.ndarray]]:
    """Each rendered image that has boxes (a client sends no request without one): the image's
    COCO entry, its annotations, their objects and boxes."""
    coco = read_coco(folder / ANNOTATIONS_FILENAME)
    names = {c["id"]: c["name"] for c in coco["categories"]}
    annotations: dict[int, list[dict]] = {}
    for annotation in coco["annotations"]:
        annotations.setdefault(annotation["image_id"], []).append(annotation)
    for image in coco["images"]:
        instances = annotations.get(image["id"], [])
        if instances:
            boxes = np.array([a["bbox"] for a in instances], dtype=np.float64)
            yield image, instances, tuple(names[a["category_id"]] for a in instances), boxes


def by_sequence(frames: list[RecordedFrame]) -> list[list[RecordedFrame]]:
    sequences: dict[int, list[RecordedFrame]] = {}
    for frame in frames:
        sequences.setdefault(frame.sequence, []).append(frame)
    return list(sequences.values())


def monitor(method: str, table: ScoreTable, manifest) -> DriftMonitor:  # noqa: ANN001
    defaults = Settings().drift
    settings = DriftSettings(
        window=defaults.window,
        test=method,
        alarm_level=defaults.alarm_level,
        psi_threshold=defaults.psi_threshold,
        full_statistics_share=1.0,
        history_seconds=3600.0,
    )
    return DriftMonitor(manifest, lambda: (1, table), settings)


def replay(make, stream: list[RecordedFrame], start: int | None = None) -> tuple[int, int | None, int]:  # noqa: ANN001
    """Feed ``stream``; (alarms before the shift at frame ``start``, frames from ``start`` to the
    first alarm after it or None, looks at the end). After an alarm the monitor starts afresh;
    at ``start`` too, if its alarm is raised (the delay is measured from a quiet monitor)."""
    current, alarms = make(), 0
    for position, frame in enumerate(stream, 1):
        current.record(frame.channels, frame.statistics, KIND, frame.shapes, frame.frame)
        if position % CHECK_EVERY and position != start:
            continue
        alarm = current.report().alarm
        if start is not None and position > start and alarm:
            return alarms, position - start, _looks(current)
        if alarm:
            alarms += position != start
            current = make()
    return alarms, None, _looks(current)


def _looks(current: DriftMonitor) -> int:
    state = current.report().sequential
    return 0 if state is None else state.looks


def delay_spread(found: list[int | None], total: int) -> str:
    """min/median/max frames to the alarm over the runs (">N": not raised within the N shifted
    frames), and in how many runs it was raised."""
    delays = sorted(total + 1 if d is None else d for d in found)
    shown = [f">{total}" if d > total else str(d) for d in (delays[0], int(np.median(delays)), delays[-1])]
    return f"{'/'.join(shown)} ({sum(d is not None for d in found)}/{len(found)})"


def main(argv: list[str] | None = None) -> dict[str, tuple[float, dict[str, str]]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10, help="frames per sequence (one scene)")
    parser.add_argument("--sequences", type=int, default=1000, help="in-distribution sequences")
    parser.add_argument("--shift-sequences", type=int, default=30, help="sequences of each shift, per run")
    parser.add_argument("--orders", type=int, default=1, help="random orders of the in-distribution ones")
    parser.add_argument("--runs", type=int, default=3, help="runs, each on fresh scene seeds for the shifts")
    parser.add_argument("--seeds", type=int, nargs="+", help="replay these runs' seeds instead of fresh ones")
    parser.add_argument("--cache", type=Path, default=CACHE, help=f"renders and statistics (default {CACHE})")
    arguments = parser.parse_args(argv)
    began = time.perf_counter()
    seeds = arguments.seeds or fresh_seeds(arguments.runs)
    print(f"scene seeds of this run (shift i: seed + i): {' '.join(map(str, seeds))}")
    settings = Settings()
    _, table = load_bundle(settings.model.directory / BUNDLE_FILENAME)
    shifts = [s for s in SHIFTS if s != "none"]
    with service_state(settings.model.directory, 1) as state:
        manifest = state.detector.manifest

        def scenes(shift: str, count: int, seed: int) -> list[list[RecordedFrame]]:
            folder = rendered(arguments.cache, shift, count, arguments.frames, seed)
            return by_sequence(recorded_frames(folder, state))

        quiet = scenes("none", arguments.sequences, SEED_IN)
        runs = [
            {s: scenes(s, arguments.shift_sequences, seed + list(SHIFTS).index(s)) for s in shifts}
            for seed in seeds
        ]
    prepared = time.perf_counter() - began
    rng = np.random.default_rng(0)
    orders = [rng.permutation(len(quiet)) for _ in range(arguments.orders)]
    frames = sum(len(s) for s in quiet)
    print(
        f"{len(quiet)} in-distribution sequences of {arguments.frames} frames (seed {SEED_IN},"
        f" {frames} frames with boxes) in {arguments.orders} random order(s);"
        f" {arguments.shift_sequences} per shift and run, {len(seeds)} runs; alarm read every"
        f" {CHECK_EVERY} frames; level {Settings().drift.alarm_level:g};"
        f" load {os.getloadavg()[0]:.1f}"
    )
    rows = {}
    for method in METHODS:
        make = lambda method=method: monitor(method, table, manifest)  # noqa: E731
        alarms = 0
        for order in orders:
            alarms += replay(make, [f for i in order for f in quiet[i]])[0]
        delays = {}
        for shift in shifts:
            found = []
            for run in runs:
                warm = [f for i in rng.permutation(len(quiet)) for f in quiet[i]][:WARM_UP]
                shifted = [f for i in rng.permutation(len(run[shift])) for f in run[shift][i]]
                found.append(replay(make, warm + shifted, start=len(warm))[1])
            delays[shift] = delay_spread(found, min(sum(len(s) for s in run[shift]) for run in runs))
        rows[method] = (1e4 * alarms / (frames * len(orders)), delays)
    width = max(22, *(len(d) for _, delays in rows.values() for d in delays.values()))
    print(
        f"\n{'method':12s} {'false alarms / 10k frames':>26s}  " + "  ".join(f"{s:>{width}s}" for s in shifts)
    )
    header = "delay min/median/max"
    print(f"{'':12s} {'':>26s}  " + "  ".join(f"{header:>{width}s}" for _ in shifts))
    for method, (rate, delays) in rows.items():
        print(f"{method:12s} {rate:26.1f}  " + "  ".join(f"{delays[s]:>{width}s}" for s in shifts))
    print(f"\nrendering and inference (cached after the first run): {prepared:.0f} s")
    print(f"whole run: {time.perf_counter() - began:.0f} s; load {os.getloadavg()[0]:.1f}")
    return rows


if __name__ == "__main__":
    from benchmarks.bench_drift_streams import main as run  # RecordedFrame pickles as the module's

    run()
