"""TypeScript clients generated from openapi/openapi.json by three more generator families
(openapi-typescript with openapi-fetch, @hey-api/openapi-ts, and openapi-generator's
typescript-axios, which reads anyOf and multipart encodings literally), as a user in another
language would make them: generated untouched, compiled with tsc (strict), then run with node
against a live server through predict (JSON and form, the drawing), batches, uploads (raw and
form), jobs, activation, an audit and typed errors, every error parsed as the document's Problem;
the typescript-axios client also sends frames (whole, and as regions of two encodings).

The node generators and axios are pinned in tests/live/generators/package-lock.json; .ci/run
installs them (``npm ci``); openapi-generator comes with the pinned PyPI wheel
``openapi-generator-cli`` (Java). Nothing is downloaded here. The drivers are
tests/live/generators/*.ts.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from service.detector.crop import crop_contexts
from service.detector.images import decode_image
from service.detector.manifest import load_manifest
from service.infra.settings import PACKAGE_ROOT
from tests.api.in_process import OnLoopback
from tests.live.generated_clients import MAX_REQUEST_BYTES, generated_client_server
from tests.predict_client import instances_of
from tests.samples import Sample, batch_zip, model_dir, samples_by_image
from tests.service_calls import ADMIN_TOKEN

GENERATORS = Path(__file__).with_name("generators")
BIN = GENERATORS / "node_modules" / ".bin"
DOCUMENT = PACKAGE_ROOT / "openapi" / "openapi.json"
# driver -> the generator's command, given where to write (a directory or a file under generated/)
CLIENTS = {
    "hey_api": [str(BIN / "openapi-ts"), "-i", str(DOCUMENT), "-o", "generated/hey"],
    # Its documented switch for request bodies: a property with a default may be left out (by
    # default openapi-typescript makes such properties required, as they are in answers).
    "openapi_fetch": [
        str(BIN / "openapi-typescript"),
        str(DOCUMENT),
        "-o",
        "generated/schema.d.ts",
        "--default-non-nullable",
        "false",
    ],
    "typescript_axios": ["openapi-generator-cli", "generate", "-g", "typescript-axios", "-i", str(DOCUMENT)]
    + ["-o", "generated/axios"],
}
# What openapi-generator says about itself, not about the document: its OpenAPI 3.1 support is
# "beta", and the other two it says for a minimal valid 3.0.3 document too (7.26.0).
KNOWN_WARNINGS = (
    "OpenAPI 3.1 support is still in beta",
    "Failed to get the schema name: null",
    "Could not compute datatypeWithEnum from any, null",
)
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
# and the frame steps, where a driver has them
FRAME_CALLS = {"typescript_axios": {"predict_frame", "predict_frame_regions"}}


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
        "frame": frame_of(samples_by_image(samples), folder),
        "whole_zip": str(folder / "whole.zip"),
        "part_zip": str(folder / "part.zip"),
        "max_request_bytes": MAX_REQUEST_BYTES,
        "token": ADMIN_TOKEN,
    }
    return fixture


def frame_of(by_image: dict[Path, list[Sample]], folder: Path) -> dict:
    """An image of several boxes as a frame: its size, and its first box's crop context as raw bgr8
    pixels (the rest go as the JPEG, whole)."""
    path, group = next((path, group) for path, group in by_image.items() if len(group) > 1)
    pixels = decode_image(path.read_bytes(), 10**8)
    height, width = pixels.shape[:2]
    padding = load_manifest(model_dir()).crop.padding
    x0, y0, x1, y1 = (int(v) for v in crop_contexts(np.array([group[0].bbox]), padding, width, height)[0])
    (folder / "region.raw").write_bytes(pixels[y0:y1, x0:x1].tobytes())
    region = {"x_offset": x0, "y_offset": y0, "width": x1 - x0, "height": y1 - y0, "encoding": "bgr8"}
    frame = {"path": str(path), "instances": instances_of(group), "width": width, "height": height}
    return {**frame, "region": {**region, "path": str(folder / "region.raw")}}


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
    output = run(CLIENTS[driver], work)
    said = [
        line for line in output.lower().splitlines() if not any(w.lower() in line for w in KNOWN_WARNINGS)
    ]
    assert not [line for line in said if "warn" in line or "error" in line], output
    run([str(BIN / "tsc"), "-p", "."], work)  # strict: the calls type-check against the generated code

    (work / "fixture.json").write_text(json.dumps({**fixture_file, "url": server.url}))
    env = {**os.environ, "CKS_FIXTURE": str(work / "fixture.json")}
    lines = run(["node", f"dist/{driver}.js"], work, env).strip().splitlines()
    summary = json.loads(lines[-1])
    assert set(summary["calls"]) >= CALLS | FRAME_CALLS.get(driver, set()), summary
    assert set(summary["problems"]) == PROBLEMS, summary
