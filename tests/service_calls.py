"""What tests ask of a running service, in process (tests/api) or a server process (tests/live).

``ServiceCalls`` needs ``client`` (an httpx.Client on the service), ``settings`` (the settings given
to the service, by name) and ``data_dir``; it adds the admin conveniences: the token's headers, upload,
job polling, calibrate, versions, and the upload workspaces left on disk.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

ADMIN_TOKEN = "test-admin-token"
PROBLEM_JSON = "application/problem+json"
JOB_POLL_S = 0.02
#: What a busy machine adds to a step that takes well under a second on a quiet one: 2 cores at load
#: average 10-20 stretched a 10 s shutdown bound to 13.6 s (issue 39). A timing bound in a test is the
#: time the behaviour needs plus this margin, so that it fails on a wait the behaviour must not have
#: (the store's outage, a Retry-After of an hour), never on the machine being busy.
BUSY_MACHINE_MARGIN_S = 10.0


def wait_until(condition: Callable[[], bool], what: str = "condition", timeout: float = 30.0) -> None:
    """Poll ``condition`` every 10 ms; fail naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {timeout} s waiting until {what}"
        time.sleep(0.01)


def assert_problem(response: httpx.Response, status: int, *fragments: str) -> dict:
    """An RFC 9457 problem with this status whose detail (or errors) mentions every fragment."""
    assert response.status_code == status, f"expected {status}, got {response.status_code}: {response.text}"
    assert response.headers["content-type"].startswith(PROBLEM_JSON), response.headers
    body = response.json()
    assert body["status"] == status, body
    assert isinstance(body["title"], str) and body["title"], body
    assert isinstance(body["detail"], str) and body["detail"], body
    text = " ".join([body["detail"], *map(str, body.get("errors", []))]).lower()
    for fragment in fragments:
        assert fragment.lower() in text, f"{fragment!r} not in the problem: {body}"
    return body


class ServiceCalls:
    """Admin conveniences over ``self.client``."""

    client: httpx.Client
    settings: dict[str, Any]
    data_dir: Path

    @property
    def admin_token(self) -> str | None:
        return self.settings.get("admin_token")

    @property
    def admin(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.admin_token}"}

    @property
    def uploads_dir(self) -> Path:
        return self.data_dir / "uploads"

    def upload_workspaces(self) -> list[Path]:
        """Upload workspaces left under the uploads folder (one folder per server process)."""
        return sorted(self.uploads_dir.glob("*/*"))

    def versions(self) -> list[int]:
        response = self.client.get("/v1/admin/calibrations", headers=self.admin)
        assert response.status_code == 200, response.text
        return [v["version"] for v in response.json()["versions"]]

    def upload(self, body: bytes, content_type: str = "application/zip", **params: Any) -> httpx.Response:
        params = {k: (str(v).lower() if isinstance(v, bool) else v) for k, v in params.items()}
        return self.client.post(
            "/v1/admin/calibrations",
            content=body,
            params=params,
            headers={**self.admin, "Content-Type": content_type},
        )

    def job(self, job_id: str) -> dict:
        """GET one job (must answer 200)."""
        response = self.client.get(f"/v1/admin/jobs/{job_id}", headers=self.admin)
        assert response.status_code == 200, response.text
        return response.json()

    def wait_job(self, job_id: str, timeout: float = 120.0) -> dict:
        """Poll a job until it succeeds or fails; returns the final job body."""
        deadline = time.monotonic() + timeout
        while True:
            response = self.client.get(f"/v1/admin/jobs/{job_id}", headers=self.admin)
            assert response.status_code == 200, response.text
            job = response.json()
            if job["state"] in ("succeeded", "failed", "interrupted"):
                return job
            assert time.monotonic() < deadline, f"job {job_id} still {job['state']} after {timeout} s: {job}"
            time.sleep(JOB_POLL_S)

    def calibrate(self, body: bytes, **params: Any) -> dict:
        """Upload a batch, wait for its job and require success; returns the job."""
        response = self.upload(body, **params)
        assert response.status_code == 202, response.text
        job = self.wait_job(response.json()["id"])
        assert job["state"] == "succeeded", job
        return job
