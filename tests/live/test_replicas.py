"""Two server processes sharing one PostgreSQL store see each other's activations."""

from __future__ import annotations

import time
from pathlib import Path

from tests.live.server import LiveServer
from tests.predict_client import instances_of, predict_ok
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import ADMIN_TOKEN, BUSY_MACHINE_MARGIN_S

POLL_S = 1.0  # CKS_STORE_POLL_SECONDS' default: a replica sees another's activation at its next poll
DEADLINE_S = 2 * POLL_S + BUSY_MACHINE_MARGIN_S


def wait_for_active(server: LiveServer, version: int, since: float) -> float:
    """Seconds from ``since`` until the server's /readyz reports ``version`` as active; fails
    beyond DEADLINE_S."""
    last = None
    while time.monotonic() - since < DEADLINE_S:
        response = server.client.get("/readyz")
        last = response.json() if response.status_code == 200 else response.text
        if response.status_code == 200 and last["active_calibration"] == version:
            return time.monotonic() - since
        time.sleep(0.1)
    raise AssertionError(f"replica did not report version {version} within {DEADLINE_S} s; last: {last}")


def test_replicas_share_the_active_version(
    postgres_url: str, tmp_path: Path, samples_dir: Path, coco: dict, samples: list[Sample]
) -> None:
    path, group = next(iter(samples_by_image(samples).items()))
    image, parameters = path.read_bytes(), {"instances": instances_of(group)}
    # Sequential start: the first replica stores the bundled calibration, the second finds it.
    with (
        LiveServer(tmp_path / "a", admin_token=ADMIN_TOKEN, store_url=postgres_url) as a,
        LiveServer(tmp_path / "b", admin_token=ADMIN_TOKEN, store_url=postgres_url) as b,
    ):
        assert a.versions() == b.versions() == [1]
        assert predict_ok(b.client, image, parameters)["calibration"]["version"] == 1

        job = a.calibrate(batch_zip(samples_dir, coco, images=4), activate=True, force=True, reason="small")
        activated_at = time.monotonic()
        version = job["result"]["version"]
        assert version == 2
        assert a.client.get("/readyz").json()["active_calibration"] == version

        wait_for_active(b, version, activated_at)  # within two polls, and a busy machine's margin
        assert predict_ok(b.client, image, parameters)["calibration"]["version"] == version
        assert b.versions() == [1, 2]

        # and the other way round: a rollback on B reaches A
        response = b.client.post(
            "/v1/admin/calibrations/1/activate", json={"reason": "rollback from B"}, headers=b.admin
        )
        assert response.status_code == 200, response.text
        wait_for_active(a, 1, time.monotonic())
        assert predict_ok(a.client, image, parameters)["calibration"]["version"] == 1
        log = a.client.get("/v1/admin/activations", headers=a.admin).json()["activations"]
        assert [(e["version"], e["reason"]) for e in log[-2:]] == [
            (2, "small"),
            (1, "rollback from B"),
        ]
