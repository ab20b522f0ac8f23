"""Write keypoint_client/generated_models.py, the client's models, from openapi/openapi.json:

    python client/generate_models.py          # after the document changed
    python client/generate_models.py --check  # exit 1, with the diff, if the file is not what it writes

datamodel-code-generator (the test extra) writes them; ruff formats them as the repository's
style says. The methods they inherit are in keypoint_client/bases.py and sets.py (BASES).
"""

from __future__ import annotations

import difflib
import json
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCUMENT = "openapi/openapi.json"
TARGET = "client/keypoint_client/generated_models.py"
COMMAND = "python client/generate_models.py"
BASES = {
    "BallSet": "keypoint_client.sets.BallGeometry",
    "EllipseSet": "keypoint_client.sets.EllipseGeometry",
    "UnboundedSet": "keypoint_client.sets.UnboundedGeometry",
    "Guarantee": "keypoint_client.bases.GuaranteeBase",
    "ModelInfo": "keypoint_client.bases.ModelInfoBase",
    "JobOut": "keypoint_client.bases.JobBase",
    "ActivationLog": "keypoint_client.bases.ActivationLogBase",
    "PoseRequest": "keypoint_client.bases.PoseRequestBase",
    "PoseCheckIn": "keypoint_client.bases.TakesArrays",
}
# The document lists the bundled model's objects; the client serves any model's.
TYPES = {"InstanceIn.object": "str"}
FLAGS = """
    --input-file-type openapi --output-model-type pydantic_v2.BaseModel --target-python-version 3.11
    --use-standard-collections --use-union-operator --enum-field-as-literal all --field-constraints
    --collapse-root-models --use-type-alias --strict-nullable --omit-redundant-constraints
    --use-schema-description --use-field-description --use-single-line-docstring
    --use-double-quotes --disable-timestamp --formatters builtin
    --base-class keypoint_client.bases.Frozen
"""
OPTIONS = [*FLAGS.split(), "--base-class-map", json.dumps(BASES), "--type-overrides", json.dumps(TYPES)]


def header() -> str:
    # E501: the document's descriptions become docstrings, as long as they are there.
    return (
        f"# Generated from {DOCUMENT} by datamodel-code-generator "
        f"{version('datamodel-code-generator')}: do not edit.\n"
        f"# Regenerate with: {COMMAND}\n# ruff: noqa: E501"
    )


def run(command: list[str], text: str | None = None) -> str:
    result = subprocess.run(command, cwd=ROOT, input=text, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command[:3])}: exit {result.returncode}\n{result.stderr}")
    return result.stdout


def generated() -> str:
    """The models as this checkout's document, generator and ruff write them."""
    generate = ["datamodel_code_generator", "--input", DOCUMENT, *OPTIONS, "--custom-file-header", header()]
    models = run([sys.executable, "-m", *generate])
    ruff = [sys.executable, "-m", "ruff"]
    fixed = run([*ruff, "check", "--fix", "--quiet", "--stdin-filename", TARGET, "-"], models)
    return run([*ruff, "format", "--quiet", "--stdin-filename", TARGET, "-"], fixed)


def main(argv: list[str]) -> int:
    models, target = generated(), ROOT / TARGET
    if argv[1:] != ["--check"]:
        target.write_text(models, encoding="utf-8")
        return 0
    current = target.read_text(encoding="utf-8") if target.exists() else ""
    diff = difflib.unified_diff(current.splitlines(True), models.splitlines(True), TARGET, "regenerated")
    sys.stdout.writelines(diff)
    return int(current != models)


if __name__ == "__main__":
    sys.exit(main(sys.argv))
