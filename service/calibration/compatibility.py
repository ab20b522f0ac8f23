"""Stored scores are valid only under the manifest settings they were computed with: the model
hash covers the ONNX bytes, not the manifest, whose edits would pair new statistics with old
thresholds and void the guarantee. Names and 3D keypoints do not change a score.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping

from calibration_store import VersionInfo
from service.detector.manifest import Manifest


def scoring_settings(manifest: Manifest) -> dict:
    """What stored scores depend on besides the model bytes (preprocessing: a short sha256)."""
    relevant = {
        "input": manifest.input.model_dump(mode="json", exclude={"name"}),
        "crop": manifest.crop.model_dump(mode="json"),
        "output": manifest.output.model_dump(mode="json", exclude={"name"}),
        "objects": [[spec.name, list(spec.keypoints)] for spec in manifest.objects],
    }
    heatmap = manifest.heatmap
    return {
        "mode": heatmap.normalization,
        "temperature": heatmap.temperature,
        "top_k": heatmap.top_k,
        "preprocessing": hashlib.sha256(json.dumps(relevant, sort_keys=True).encode()).hexdigest()[:16],
    }


def incompatibility(recorded: Mapping, manifest: Manifest) -> str | None:
    """Why scores recorded under ``recorded`` cannot serve this manifest, or None if they can."""
    current = scoring_settings(manifest)
    changed = [key for key in current if recorded.get(key) != current[key]]
    if not changed:
        return None
    labels = {"preprocessing": "input/crop/output/object-channel fingerprint"}
    described = ", ".join(
        f"{labels.get(key, f'heatmap {key}')} {recorded.get(key)!r} -> {current[key]!r}" for key in changed
    )
    return (
        f"it was scored under other manifest settings ({described}); "
        "calibrate a new version with the current manifest"
    )


def version_incompatibility(info: VersionInfo, manifest: Manifest) -> str | None:
    reason = incompatibility(info.normalization, manifest)
    return None if reason is None else f"calibration version {info.number} cannot be used: {reason}"
