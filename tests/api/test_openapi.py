"""The committed openapi/openapi.json is exactly what the app generates."""

from __future__ import annotations

import json

from service.infra.settings import PACKAGE_ROOT
from service.serving.app import create_app

COMMITTED = PACKAGE_ROOT / "openapi" / "openapi.json"


def test_committed_openapi_matches_the_app() -> None:
    # as service/cli.py writes it
    generated = json.dumps(create_app().openapi(), indent=2, sort_keys=True) + "\n"
    committed = COMMITTED.read_text(encoding="utf-8")
    assert committed == generated, (
        f"{COMMITTED.relative_to(PACKAGE_ROOT)} is out of date with the app: "
        "run `keypoint-service export-openapi` and commit the result"
    )


def test_the_document_covers_the_documented_api() -> None:
    paths = json.loads(COMMITTED.read_text(encoding="utf-8"))["paths"]
    expected = {
        "/v1/predict": {"post"},
        "/v1/predict/batch": {"post"},
        "/v1/predict/frame": {"post"},
        "/v1/model": {"get"},
        "/v1/admin/calibrations": {"get", "post"},
        "/v1/admin/calibrations/{version}": {"get"},
        "/v1/admin/calibrations/{version}/activate": {"post"},
        "/v1/admin/activations": {"get"},
        "/v1/admin/jobs/{job_id}": {"get"},
        "/v1/admin/audits": {"get", "post"},
        "/v1/admin/audits/{audit_id}": {"get"},
        "/v1/admin/drift": {"get"},
        "/healthz": {"get"},
        "/readyz": {"get"},
        "/metrics": {"get"},
    }
    for path, methods in expected.items():
        assert methods <= set(paths.get(path, {})), f"{path} {sorted(methods)} missing from the document"
