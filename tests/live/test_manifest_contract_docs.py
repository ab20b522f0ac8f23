"""The manifest's documents follow the model: the committed JSON Schema and docs/bring-your-own-model.md."""

from __future__ import annotations

import json
import re
from pathlib import Path

from service.detector.manifest import manifest_json_schema
from service.infra.settings import PACKAGE_ROOT
from tests.cli_calls import run

SCHEMA = PACKAGE_ROOT / "docs" / "manifest.schema.json"
PAGE = PACKAGE_ROOT / "docs" / "bring-your-own-model.md"


def test_the_committed_json_schema_is_generated_from_the_model(tmp_path: Path) -> None:
    result = run(["manifest-schema", "--output", "-"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == manifest_json_schema()
    assert SCHEMA.read_text(encoding="utf-8") == result.stdout, (
        "docs/manifest.schema.json is out of date with service/detector/manifest.py: "
        "run `keypoint-service manifest-schema` and commit the result"
    )


def schema_fields(schema: dict) -> dict[str, tuple[dict, bool]]:
    """Schema fields by their path on the page (``input.height``, ``keypoints[].name``): (node, required)."""
    definitions = schema["$defs"]
    fields: dict[str, tuple[dict, bool]] = {}

    def walk(node: dict, prefix: str) -> None:
        required = set(node.get("required", []))
        for name, field in node["properties"].items():
            path = prefix + name
            fields[path] = (field, name in required)
            reference = field.get("items", field).get("$ref")
            if reference:
                walk(definitions[reference.rsplit("/", 1)[1]], path + ("[]." if "items" in field else "."))

    walk(schema, "")
    return fields


def page_rows() -> dict[str, list[str]]:
    """The page's field table: path -> cells (path, default, meaning)."""
    rows = {}
    for line in PAGE.read_text(encoding="utf-8").splitlines():
        if match := re.match(r"\| `([^`]+)` \|", line):
            rows[match.group(1)] = [cell.strip() for cell in line.strip("|").split(" | ")]
    return rows


def test_the_page_documents_every_field_with_its_default() -> None:
    fields, rows = schema_fields(json.loads(SCHEMA.read_text(encoding="utf-8"))), page_rows()
    assert sorted(rows) == sorted(fields), "docs/bring-your-own-model.md's table and the schema differ"
    for path, (field, required) in fields.items():
        if required:
            expected = "required"
        elif "$ref" in field:  # a section: its fields' rows give the defaults
            expected = "all defaults"
        else:
            expected = f"`{json.dumps(field['default'])}`"
        assert rows[path][1] == expected, f"{path}: default cell {rows[path][1]!r}, expected {expected!r}"
        assert rows[path][2], f"{path} has no meaning in the table"
        assert field.get("description"), f"{path}: give it a Field(description=...) in manifest.py"
