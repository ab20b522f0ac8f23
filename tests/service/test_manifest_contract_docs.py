"""The manifest's documents follow the model: the committed JSON Schema and docs/bring-your-own-model.md."""

from __future__ import annotations

import json
from pathlib import Path

from service.detector.manifest import manifest_json_schema
from service.settings import PACKAGE_ROOT
from tests.service.live import cli, service_env
from tests.service.test_model_mismatch import run_until_exit

SCHEMA = PACKAGE_ROOT / "docs" / "manifest.schema.json"


def test_the_committed_json_schema_is_generated_from_the_model(tmp_path: Path) -> None:
    result = run_until_exit([*cli(), "manifest-schema", "--output", "-"], service_env(tmp_path))
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == manifest_json_schema()
    assert SCHEMA.read_text(encoding="utf-8") == result.stdout, (
        "docs/manifest.schema.json is out of date with service/detector/manifest.py: "
        "run `keypoint-service manifest-schema` and commit the result"
    )
