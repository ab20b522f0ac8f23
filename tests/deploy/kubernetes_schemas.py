"""The Kubernetes schemas deploy/k8s is checked against, kept in the repository (the kinds it
uses, of one Kubernetes version, descriptions left out: about 100 kB) instead of the 100+ MB of
every kind and version that the kubernetes-validate package bundles.

``python -m tests.deploy.kubernetes_schemas`` rewrites ``kubernetes-schemas.json`` from an
installed kubernetes-validate (``pip install kubernetes-validate``, only to add a kind or move
to another version): the strict schemas (an unknown or misspelt field fails) of ``KINDS``, with
every definition they reach.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

import jsonschema

KUBERNETES_VERSION = "1.33"
KINDS = [
    ("apps/v1", "Deployment"),
    ("v1", "Service"),
    ("v1", "Secret"),
    ("autoscaling/v2", "HorizontalPodAutoscaler"),
    ("policy/v1", "PodDisruptionBudget"),
]
SCHEMAS = Path(__file__).with_name("kubernetes-schemas.json")
_REFERENCE = "/api/_definitions.json#/$defs/"


def validate(doc: dict[str, Any]) -> None:
    """Raise ``jsonschema.ValidationError`` unless ``doc`` is a valid object of its kind."""
    definitions = json.loads(SCHEMAS.read_text(encoding="utf-8"))["$defs"]
    kind = _kind_name(doc["apiVersion"], doc["kind"])
    assert kind in definitions, f"{kind}: not kept; add it to KINDS and run python -m {__name__}"
    jsonschema.Draft202012Validator({"$defs": definitions, "$ref": f"#/$defs/{kind}"}).validate(doc)


def _kind_name(api_version: str, kind: str) -> str:
    return f"kind.{api_version.replace('/', '.')}.{kind}"


def _bundle(source: Path) -> dict[str, Any]:
    definitions = json.loads((source / "_definitions.json").read_text(encoding="utf-8"))["$defs"]
    kept = {}
    for api_version, kind in KINDS:
        group = re.sub(r"^([^./]*)(?:\.[^/]*)?/", r"\1-", api_version)  # apps/v1 -> apps-v1
        path = source / f"{kind.lower()}-{group}.json"
        kept[_kind_name(api_version, kind)] = json.loads(path.read_text(encoding="utf-8"))
    pending = list(kept.values())
    while pending:
        for name in _references(pending.pop()):
            if name not in kept:
                kept[name] = definitions[name]
                pending.append(definitions[name])
    return {"$defs": _plain(kept)}


def _references(schema: Any) -> list[str]:
    if isinstance(schema, dict):
        found = [_local(schema["$ref"]).removeprefix("#/$defs/")] if "$ref" in schema else []
        return found + [name for value in schema.values() for name in _references(value)]
    if isinstance(schema, list):
        return [name for value in schema for name in _references(value)]
    return []


def _local(reference: str) -> str:
    """A kind's reference into the definitions file, as one inside the one document."""
    return reference.replace(_REFERENCE, "#/$defs/")


def _plain(schema: Any) -> Any:
    """Without descriptions and ids (each would be a document of its own), references inside one."""
    if isinstance(schema, dict):
        return {
            key: _local(value) if key == "$ref" else _plain(value)
            for key, value in schema.items()
            if key not in ("$id", "$schema") and not (key == "description" and isinstance(value, str))
        }
    if isinstance(schema, list):
        return [_plain(value) for value in schema]
    return schema


if __name__ == "__main__":
    import kubernetes_validate

    source = Path(kubernetes_validate.__file__).parent / "kubernetes-json-schema"
    bundle = _bundle(source / f"v{KUBERNETES_VERSION}.0-local-strict")
    SCHEMAS.write_text(json.dumps(bundle, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    print(f"{SCHEMAS}: {len(bundle['$defs'])} schemas, {SCHEMAS.stat().st_size} bytes", file=sys.stderr)
