"""Stored scores are valid only under the heatmap settings they were computed with.

A version records the model's normalization, temperature and top-K next to its scores.
The model hash covers the ONNX bytes but not the manifest, so an operator who edits
``heatmap`` in manifest.json keeps the hash and would silently pair new statistics
with old thresholds: the coverage guarantee would no longer hold. Every place that
uses a version (prediction, activation, appending, the bundled bootstrap) checks it.
"""

from __future__ import annotations

from collections.abc import Mapping

from calibration_store import VersionInfo
from service.detector.manifest import HeatmapSpec


def scoring_settings(heatmap: HeatmapSpec) -> dict:
    """What stored scores depend on besides the model bytes."""
    return {"mode": heatmap.normalization, "temperature": heatmap.temperature, "top_k": heatmap.top_k}


def incompatibility(recorded: Mapping, heatmap: HeatmapSpec) -> str | None:
    """Why scores recorded under ``recorded`` cannot serve this manifest, or None if they can."""
    if dict(recorded) == scoring_settings(heatmap):
        return None
    return (
        f"it was scored with {dict(recorded)} but the model's manifest now uses {scoring_settings(heatmap)}; "
        "calibrate a new version with the current manifest"
    )


def version_incompatibility(info: VersionInfo, heatmap: HeatmapSpec) -> str | None:
    reason = incompatibility(info.normalization, heatmap)
    return None if reason is None else f"calibration version {info.number} cannot be used: {reason}"
