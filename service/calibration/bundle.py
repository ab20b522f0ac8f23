"""A calibration version as one ``.npz`` file (no pickles; the bundled default is loaded on first
start): ``metadata`` (JSON) and per object ``<object>/keypoint_ids``, ``/refs``, ``/<function>``
(scores), and ``/features/<feature>`` and ``/groups`` when the version has them."""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibration_store import CalibrationStore, NewVersion, ObjectScores, ScoreTable, VersionInfo
from service.calibration.compatibility import incompatibility
from service.calibration.stratification import version_strata
from service.detector.session import Detector

BUNDLE_FILENAME = "default_calibration.npz"
log = logging.getLogger(__name__)


def save_bundle(path: Path, info: VersionInfo, table: ScoreTable) -> None:
    metadata = {k: getattr(info, k) for k in ("model_hash", "model_name", "author", "note")}
    metadata |= {"normalization": dict(info.normalization)}
    metadata |= {"source_batches": [batch.as_dict() for batch in info.source_batches]}
    arrays = {"metadata": np.array(json.dumps(metadata))}
    for block in table.objects:
        name = block.object_name
        arrays |= {f"{name}/keypoint_ids": block.keypoint_ids, f"{name}/refs": np.array(block.instance_refs)}
        arrays |= {f"{name}/{function}": matrix for function, matrix in block.scores.items()}
        arrays |= {f"{name}/features/{feature}": matrix for feature, matrix in block.features.items()}
        if block.has_groups:
            arrays[f"{name}/groups"] = np.array(block.groups)
    with open(path, "wb") as handle:
        np.savez_compressed(handle, **arrays)


def load_bundle(path: Path) -> tuple[NewVersion, ScoreTable]:
    with np.load(path, allow_pickle=False) as data:
        metadata = json.loads(str(data["metadata"]))
        names = sorted({key.split("/")[0] for key in data.files if "/" in key})
        blocks = [_block(data, name) for name in names]
    return NewVersion(**metadata), ScoreTable(tuple(blocks))


def _block(data: np.lib.npyio.NpzFile, name: str) -> ObjectScores:
    parts = [key.split("/")[1:] for key in data.files if key.startswith(f"{name}/")]
    scores = {p[0]: data[f"{name}/{p[0]}"] for p in parts if len(p) == 1 and p[0] not in _BLOCK_KEYS}
    features = {p[1]: data[f"{name}/features/{p[1]}"] for p in parts if len(p) == 2 and p[0] == "features"}
    groups = tuple(str(g) for g in data[f"{name}/groups"]) if f"{name}/groups" in data.files else ()
    refs = tuple(str(ref) for ref in data[f"{name}/refs"])
    return ObjectScores(name, data[f"{name}/keypoint_ids"], refs, scores, features=features, groups=groups)


_BLOCK_KEYS = ("keypoint_ids", "refs", "groups")


def bootstrap_default_calibration(store: CalibrationStore, detector: Detector, model_dir: Path) -> int | None:
    """Store and activate the model's bundled calibration when the store has none for it yet;
    atomic: replicas starting at once on an empty shared store bootstrap it once."""
    path = Path(model_dir) / BUNDLE_FILENAME
    if not path.is_file() or store.list_versions(detector.model_hash):  # the usual restart: skip the file
        return None
    new, table = load_bundle(path)
    if new.model_hash != detector.model_hash:
        log.warning("%s was computed for another model (%s); not loading it", path, new.model_hash[:12])
        return None
    if (reason := incompatibility(new.normalization, detector.manifest)) is not None:
        log.warning("%s is not loaded: %s", path, reason)
        return None
    strata = version_strata(table, None)
    new = replace(new, strata=None if strata is None else strata.as_dict())
    info = store.create_first_version(new, table, "bootstrap", f"bundled default calibration {path.name}")
    if info is None:  # another process bootstrapped it first
        return None
    log.info("loaded the bundled calibration as version %d", info.number)
    return info.number
