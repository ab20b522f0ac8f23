"""What a read of live coverage costs at the sizes the retention bounds allow.

Run: python -m benchmarks.bench_live_coverage --rows 1000 10000 100000 --reads 3

Each bundled sample image is predicted in process (the ASGI app, SQLite store, the bundled model)
with ``retain: true`` (every other one with ``stratify: difficulty``) and labelled with its true
keypoints through POST /v1/feedback: real records and real labels. Those labelled rows are then
copied, with fresh ids, 20 camera streams and one frame every 33 ms, until the store holds
``--rows`` labelled rows (written straight into calib_retained and calib_verdicts: the read is what
is measured, and CKS_FEEDBACK_MAX_RETAINED, 100,000 by default, is the most a read can see). Then,
per size, median wall seconds of ``--reads`` of each: a fresh reader's full count of rows labelled
before verdicts were stored (their verdicts removed: every record decoded and judged, what every
first read cost before), the same with the verdicts stored, and GET /v1/admin/coverage/live (the
admin endpoint): its first read, with nothing new, with 100 new labels.
"""

from __future__ import annotations

import argparse
import json
import sqlite3
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from datetime import timedelta
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastapi.testclient import TestClient  # noqa: E402

from calibration_store import codec, sqlite_path  # noqa: E402
from service.feedback.live_coverage import LiveCoverageReader  # noqa: E402
from service.feedback.retention import new_prediction_id  # noqa: E402
from service.feedback.verdicts import verdicts  # noqa: E402
from service.infra.settings import Settings  # noqa: E402
from service.serving.app import create_app  # noqa: E402
from tests.predict_client import instances_of, predict_ok  # noqa: E402
from tests.samples import load_samples, samples_by_image  # noqa: E402
from training.coco import read_coco  # noqa: E402

TOKEN = "bench-live-coverage-admin-token"
HEADERS = {"Authorization": f"Bearer {TOKEN}"}
STREAMS = 20
FRAME = timedelta(milliseconds=33)
SCENE = 10


def labelled_seed(client: TestClient, settings: Settings) -> None:
    """Every sample image retained and labelled with its true keypoints, over HTTP."""
    folder = settings.model.directory / "samples"
    samples = load_samples(folder, read_coco(folder / "annotations.json"))
    for k, (path, group) in enumerate(samples_by_image(samples).items()):
        options = {"stratify": "difficulty"} if k % 2 else {}
        body = {"instances": instances_of(group), "retain": True, "stream": "cam-0", **options}
        answer = predict_ok(client, Path(path).read_bytes(), body)
        labels = {"instances": [{"instance": i, "keypoints": s.keypoints} for i, s in enumerate(group)]}
        response = client.post(
            f"/v1/feedback/{answer['prediction_id']}",
            json=labels,
            headers=HEADERS,
        )
        assert response.status_code == 200, response.text


def fill(database: Path, seed: list, have: int, rows: int, names: list[str]) -> None:
    """Copies of the ``seed`` labelled rows and their verdicts, fresh ids, STREAMS streams, scenes
    of SCENE frames (a look each), until ``rows`` are labelled (``have`` are)."""
    start = max(p.created_at for p in seed) + (have + 1) * FRAME
    copies, looks = [], {}
    for n in range(rows - have):
        source, at = seed[n % len(seed)], start + n * FRAME
        prediction_id, stream = new_prediction_id(at), n % STREAMS
        look = looks[stream] = prediction_id if n // STREAMS % SCENE == 0 else looks[stream]
        record = {**source.record, "look": look}
        copies.append(
            replace(
                source, id=prediction_id, stream=f"cam-{stream}", created_at=at, labelled_at=at, record=record
            )
        )
    with sqlite3.connect(database) as connection:
        connection.executemany(
            "INSERT INTO calib_retained (id, model_hash, version, stream, created_at, expires_at, record,"
            " labels, labelled_at, labelled_by) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            [
                (
                    p.id,
                    p.model_hash,
                    p.version,
                    p.stream,
                    p.created_at.isoformat(),
                    (p.created_at + timedelta(days=7)).isoformat(),
                    codec.encode_json(p.record),
                    codec.encode_json(p.labels),
                    p.labelled_at.isoformat(),
                    "bench",
                )
                for p in copies
            ],
        )
        judged = [(p.id, verdicts(p, names)) for p in copies]
        connection.executemany(
            "INSERT INTO calib_verdicts (id, shape, tally) VALUES (?, ?, ?)",
            [(i, v.shape, codec.encode_json(v.tally)) for i, v in judged],
        )


def without_verdicts(database: Path, action) -> list[float]:  # noqa: ANN001
    """``action``'s wall seconds while the stored verdicts are set aside (as if labelled before)."""
    with sqlite3.connect(database) as connection:
        connection.execute("ALTER TABLE calib_verdicts RENAME TO calib_verdicts_aside")
        connection.execute("CREATE TABLE calib_verdicts AS SELECT * FROM calib_verdicts_aside LIMIT 0")
    try:
        return action()
    finally:
        with sqlite3.connect(database) as connection:
            connection.execute("DROP TABLE calib_verdicts")
            connection.execute("ALTER TABLE calib_verdicts_aside RENAME TO calib_verdicts")


def timed(action, reads: int) -> list[float]:  # noqa: ANN001
    """Wall seconds of ``reads`` calls of ``action``."""
    spent = []
    for _ in range(reads):
        began = time.perf_counter()
        action()
        spent.append(time.perf_counter() - began)
    return spent


def spread(values: list[float]) -> str:
    median = statistics.median(values)
    return f"{median:.3f}" if len(values) == 1 else f"{median:.3f} ({min(values):.3f}-{max(values):.3f})"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, nargs="+", default=[1000, 10_000, 100_000])
    parser.add_argument("--reads", type=int, default=3)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="cks-bench-live-") as data:
        settings = Settings(data_dir=Path(data), admin_token=TOKEN, inference_threads=1)
        app = create_app(settings)
        with TestClient(app) as client:

            def get() -> None:
                response = client.get("/v1/admin/coverage/live", headers=HEADERS)
                assert response.status_code == 200, response.text

            state = app.state.service
            store, model_hash = state.store, state.detector.model_hash
            names = [k.name for k in state.detector.manifest.keypoints]
            labelled_seed(client, settings)
            seed = store.labelled_predictions(model_hash, 1000)
            database = sqlite_path(settings.storage.resolved_url)

            def count() -> int:
                return len(store.labelled_since(model_hash, None))

            size = len(json.dumps(seed[0].record))
            print(f"record: {size} bytes of JSON (one labelled prediction, before its labels)")
            print(
                "rows | full count, records judged s (before) | full count, verdicts s"
                " | GET, first s | GET, nothing new s | GET, 100 new s"
            )

            def fresh() -> None:
                LiveCoverageReader(store, model_hash, names, 10**6, 0.01).report()

            for rows in sorted(args.rows):
                fill(database, seed, count(), rows, names)
                judged = without_verdicts(database, lambda: timed(fresh, args.reads))
                stored = timed(fresh, args.reads)
                first = timed(get, 1)
                quiet = timed(get, args.reads)
                fill(database, seed, count(), rows + 100, names)
                new = timed(get, 1)
                figures = (judged, stored, first, quiet, new)
                print(f"{rows} | " + " | ".join(spread(f) for f in figures), flush=True)


if __name__ == "__main__":
    main()
