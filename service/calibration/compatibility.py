"""Stored scores are valid only under the manifest settings they were computed with.

A version records, next to its scores, the settings that turn an image and a box into
the statistics behind a score: the heatmap normalization, temperature and top-K, and a
fingerprint of the preprocessing (input transform, crop padding, output size, which
channels belong to which object). The model hash covers the ONNX bytes but not the
manifest, so an operator who edits one of these keeps the hash and would silently pair
new statistics with old thresholds: the coverage guarantee would no longer hold. Every
place that uses a version (prediction, activation, appending, the bundled bootstrap)
checks it. Names, keypoint names and 3D keypoints do not change a score and may be edited.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping

from calibration_store import VersionInfo
from service.detector.manifest import Manifest


def scoring_settings(manifest: Manifest) -> dict:
    """What stored scores depend on besides the model bytes (recorded with every version)."""
    heatmap = manifest.heatmap
    return {
        "mode": heatmap.normalization,
        "temperature": heatmap.temperature,
        "top_k": heatmap.top_k,
        "preprocessing": preprocessing_fingerprint(manifest),
    }


def preprocessing_fingerprint(manifest: Manifest) -> str:
    """A short sha256 of the manifest fields that map an image and a box to heatmap channels."""
    relevant = {
        "input": manifest.input.model_dump(mode="json", exclude={"name"}),
        "crop": manifest.crop.model_dump(mode="json"),
        "output": manifest.output.model_dump(mode="json", exclude={"name"}),
        "objects": [[spec.name, list(spec.keypoints)] for spec in manifest.objects],
    }
    return hashlib.sha256(json.dumps(relevant, sort_keys=True).encode()).hexdigest()[:16]


def incompatibility(recorded: Mapping, manifest: Manifest) -> str | None:
    """Why scores recorded under ``recorded`` cannot serve this manifest, or None if they can."""
    current = scoring_settings(manifest)
    changed = [key for key in current if recorded.get(key) != current[key]]
    if not changed:
        return None
    described = ", ".join(f"{_label(key)} {recorded.get(key)!r} -> {current[key]!r}" for key in changed)
    return (
        f"it was scored under other manifest settings ({described}); "
        "calibrate a new version with the current manifest"
    )


def version_incompatibility(info: VersionInfo, manifest: Manifest) -> str | None:
    reason = incompatibility(info.normalization, manifest)
    return None if reason is None else f"calibration version {info.number} cannot be used: {reason}"


def _label(key: str) -> str:
    if key == "preprocessing":
        return "input/crop/output/object-channel fingerprint"
    return f"heatmap {key}"
