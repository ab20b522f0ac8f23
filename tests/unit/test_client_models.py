"""The client's models are generated from openapi/openapi.json: the checked-in
client/keypoint_client/generated_models.py is exactly what ``python client/generate_models.py``
writes from the committed document, so the two cannot drift apart."""

from __future__ import annotations

import json
import subprocess
import sys

from service.infra.settings import PACKAGE_ROOT


def test_the_client_models_are_what_the_document_generates() -> None:
    command = [sys.executable, "client/generate_models.py", "--check"]
    result = subprocess.run(command, cwd=PACKAGE_ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"run: python client/generate_models.py\n{result.stdout}{result.stderr}"


def test_the_batch_endpoint_is_documented() -> None:
    """The client posts its multipart batch to /v1/predict/batch, which takes the form at run time
    as it always did; the document describes that form at /v1/predict/batch/form (docs/api.md)."""
    paths = json.loads((PACKAGE_ROOT / "openapi" / "openapi.json").read_text())["paths"]
    batch = paths["/v1/predict/batch/form"]["post"]
    assert list(batch["requestBody"]["content"]) == ["multipart/form-data"]
    assert batch["responses"]["200"]["content"]["application/json"]["schema"]["$ref"].endswith(
        "/BatchResponse"
    )
