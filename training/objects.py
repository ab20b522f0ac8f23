"""The annotated object classes: meshes from ``pybullet_data``, their scale and model frame.

The model frame of an object is its mesh scaled to metres and centred on the centre of
its axis-aligned bounding box. Every 3D quantity (keypoints, poses) is in this frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pybullet_data


@dataclass(frozen=True)
class ObjectClass:
    name: str
    mesh: str  # relative to pybullet_data
    size: float  # longest bounding-box side in metres
    rgba: tuple[float, float, float, float] | None  # None keeps the mesh's own texture


OBJECT_CLASSES: tuple[ObjectClass, ...] = (
    ObjectClass("duck", "duck.obj", 0.11, None),
    ObjectClass("mug", "objects/mug.obj", 0.12, (0.85, 0.15, 0.12, 1.0)),
    ObjectClass("teddy", "teddy2_VHACD_CHs.obj", 0.15, (0.55, 0.33, 0.16, 1.0)),
    ObjectClass("bunny", "bunny.obj", 0.12, (0.85, 0.85, 0.8, 1.0)),
    ObjectClass("lego", "lego/lego.obj", 0.08, (0.15, 0.35, 0.9, 1.0)),
    ObjectClass("blob", "random_urdfs/017/017.obj", 0.12, (0.2, 0.75, 0.3, 1.0)),
)


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh in the model frame (metres)."""

    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3) vertex indices
    scale: float  # file units -> metres
    offset: np.ndarray  # model frame = file * scale - offset

    @property
    def diameter(self) -> float:
        return float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0)))


def mesh_path(relative: str) -> Path:
    return Path(pybullet_data.getDataPath()) / relative


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and fan-triangulated faces of a Wavefront OBJ file."""
    vertices: list[list[float]] = []
    faces: list[list[int]] = []
    for line in path.read_text(errors="replace").splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            vertices.append([float(x) for x in parts[1:4]])
        elif parts[0] == "f":
            idx = [int(tok.split("/")[0]) for tok in parts[1:]]
            idx = [i - 1 if i > 0 else len(vertices) + i for i in idx]
            faces.extend([idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1))
    return np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)


@cache
def load_mesh(relative: str, size: float) -> Mesh:
    """Load a mesh, scale its longest side to ``size`` metres and centre its bounding box."""
    vertices, faces = read_obj(mesh_path(relative))
    scale = size / float((vertices.max(0) - vertices.min(0)).max())
    scaled = vertices * scale
    offset = (scaled.max(0) + scaled.min(0)) / 2
    return Mesh(vertices=scaled - offset, faces=faces, scale=scale, offset=offset)


def class_mesh(obj: ObjectClass) -> Mesh:
    return load_mesh(obj.mesh, obj.size)
