"""TypeScript clients generated from openapi/openapi.json by two more generator families
(openapi-typescript with openapi-fetch, and @hey-api/openapi-ts), as a user in another language
would make them: generated untouched, compiled with tsc (strict), then run with node against a live
server through predict (JSON and form, the drawing), batches, uploads (raw and form), jobs,
activation, an audit and typed errors, every error parsed as the document's Problem.

The generators are pinned in tests/live/generators/package-lock.json; .ci/run installs them
(``npm ci``), nothing is downloaded here. The drivers are tests/live/generators/*.ts.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.infra.settings import PACKAGE_ROOT
from tests.api.in_process import OnLoopback
from tests.live.generated_clients import MAX_REQUEST_BYTES, generated_client_server
from tests.predict_client import instances_of
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import ADMIN_TOKEN

GENERATORS = Path(__file__).with_name("generators")
BIN = GENERATORS / "node_modules" / ".bin"
DOCUMENT = PACKAGE_ROOT / "openapi" / "openapi.json"
# driver -> the generator's command, given where to write (a directory or a file under generated/)
CLIENTS = {
    "hey_api": ["openapi-ts", "-i", str(DOCUMENT), "-o", "generated/hey"],
    # Its documented switch for request bodies: a property with a default may be left out (by
    # default openapi-typescript makes such properties required, as they are in answers).
    "openapi_fetch": [
        "openapi-typescript",
        str(DOCUMENT),
        "-o",
        "generated/schema.d.ts",
        "--default-non-nullable",
        "false",
    ],
}
# Every operation issue 38 names, and the error statuses each driver parses as a Problem.
CALLS = {
    "predict",
    "predict_form",
    "predict_png",
    "predict_batch",
    "predict_batch_form",
    "upload_calibration",
    "upload_calibration_form",
    "upload_calibration_overrides",
    "get_job",
    "activate_calibration",
    "start_audit",
}
PROBLEMS = {401, 404, 409, 413, 415, 422, 503}


def run(command: list[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    result = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    output = result.stdout + result.stderr
    assert result.returncode == 0, f"{' '.join(command)}:\n{output[-6000:]}"
    return output


@pytest.fixture(scope="module")
def node_tools() -> None:
    """The pinned generators, as .ci/run installs them (npm ci in tests/live/generators)."""
    assert shutil.which("node"), "node is not installed (.ci/run installs Debian's nodejs and npm)"
    assert (BIN / "tsc").exists(), "run `npm ci` in tests/live/generators (.ci/run does)"


@pytest.fixture(scope="module")
def fixture_file(
    tmp_path_factory: pytest.TempPathFactory, samples: list[Sample], samples_dir: Path, coco: dict
):
    """What the drivers send: sample images with their instances, a whole and a partial batch."""
    folder = tmp_path_factory.mktemp("ts-fixture")
    (folder / "whole.zip").write_bytes(batch_zip(samples_dir, coco))
    (folder / "part.zip").write_bytes(batch_zip(samples_dir, coco, images=6))
    images = [
        {"path": str(path), "instances": instances_of(group)}
        for path, group in samples_by_image(samples).items()
    ]
    fixture = {
        "images": images,
        "whole_zip": str(folder / "whole.zip"),
        "part_zip": str(folder / "part.zip"),
        "max_request_bytes": MAX_REQUEST_BYTES,
        "token": ADMIN_TOKEN,
    }
    return fixture


@pytest.fixture
def server(tmp_path: Path) -> Iterator[OnLoopback]:
    """A fresh server per client: no calibration yet (predict answers 503 until one is activated)."""
    with generated_client_server(tmp_path / "data") as live:
        yield live


@pytest.mark.usefixtures("node_tools")
@pytest.mark.parametrize("driver", sorted(CLIENTS))
def test_a_generated_typescript_client_drives_every_kind_of_call(
    driver: str, server: OnLoopback, fixture_file: dict, tmp_path: Path
) -> None:
    work = tmp_path / "client"
    work.mkdir()
    (work / "node_modules").symlink_to(GENERATORS / "node_modules")
    for name in ("tsconfig.json", "common.ts", f"{driver}.ts"):
        shutil.copy(GENERATORS / name, work / name)
    generator, *arguments = CLIENTS[driver]
    output = run([str(BIN / generator), *arguments], work)
    assert "warn" not in output.lower() and "error" not in output.lower(), output
    run([str(BIN / "tsc"), "-p", "."], work)  # strict: the calls type-check against the generated code

    (work / "fixture.json").write_text(json.dumps({**fixture_file, "url": server.url}))
    env = {**os.environ, "CKS_FIXTURE": str(work / "fixture.json")}
    lines = run(["node", f"dist/{driver}.js"], work, env).strip().splitlines()
    summary = json.loads(lines[-1])
    assert set(summary["calls"]) >= CALLS, summary
    assert set(summary["problems"]) == PROBLEMS, summary
