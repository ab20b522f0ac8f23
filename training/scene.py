"""A pybullet world (TinyRenderer, headless) and random LM-O-like scenes rendered in it.

The world is built once per process: one body per annotated object class, a pool of
distractor bodies and ground planes. A scene moves the bodies it uses into place and
parks the others far outside the view, so rendering an image allocates nothing.
Everything a scene does is drawn from the generator it is given, so a scene is a
pure function of ``(seed, index)``.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pybullet as p

from training.camera import Camera, look_at
from training.objects import OBJECT_CLASSES, class_mesh, load_mesh, mesh_path
from training.textures import texture

PARKED = (50.0, 50.0, -50.0)
NUM_DISTRACTORS = 40
NUM_GROUND_TEXTURES = 24
FOCAL = 572.0  # LM-O's focal length at 640x480


@dataclass
class Placed:
    """One annotated object in a scene: class index, body and model->world pose."""

    class_index: int
    body: int
    rotation: np.ndarray
    position: np.ndarray


@dataclass
class Rendered:
    rgb: np.ndarray  # (H, W, 3) uint8, RGB
    depth: np.ndarray  # (H, W) metres along the optical axis
    seg: np.ndarray  # (H, W) body id, -1 for background
    camera: Camera
    objects: list[Placed] = field(default_factory=list)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return np.array(p.getMatrixFromQuaternion(q.tolist())).reshape(3, 3)


def _resting_rotation(rng: np.random.Generator, max_tilt_deg: float = 15.0) -> np.ndarray:
    """An object standing on the table as in LM-O: model z up, any yaw, a small tilt."""
    yaw = rng.uniform(0, 2 * np.pi)
    heading = rng.uniform(0, 2 * np.pi)
    axis = np.array([np.cos(heading), np.sin(heading), 0.0])
    tilt = np.deg2rad(rng.uniform(0, max_tilt_deg))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    tilt_rot = np.eye(3) + np.sin(tilt) * k + (1 - np.cos(tilt)) * k @ k
    c, s = np.cos(yaw), np.sin(yaw)
    return tilt_rot @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _quaternion(rotation: np.ndarray) -> list[float]:
    """Rotation matrix -> pybullet quaternion (x, y, z, w)."""
    m = rotation
    w = np.sqrt(max(0.0, 1 + m[0, 0] + m[1, 1] + m[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + m[0, 0] - m[1, 1] - m[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - m[0, 0] + m[1, 1] - m[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - m[0, 0] - m[1, 1] + m[2, 2])) / 2
    x = np.copysign(x, m[2, 1] - m[1, 2])
    y = np.copysign(y, m[0, 2] - m[2, 0])
    z = np.copysign(z, m[1, 0] - m[0, 1])
    return [float(x), float(y), float(z), float(w)]


class World:
    """A headless pybullet client holding every body a scene may use."""

    def __init__(self, width: int = 640, height: int = 480) -> None:
        self.width, self.height = width, height
        self.client = p.connect(p.DIRECT)
        self._tmp = tempfile.TemporaryDirectory(prefix="lmo_textures_")
        pool_rng = np.random.default_rng(12345)  # fixed: the pools never depend on the split seed
        self.targets = [self._target_body(i) for i in range(len(OBJECT_CLASSES))]
        self.distractors, self.distractor_radius = self._distractor_bodies(pool_rng)
        self.grounds = [self._ground_body(scale) for scale in (0.1, 0.2, 0.35)]
        self.ground_textures = [self._load_texture(pool_rng, i) for i in range(NUM_GROUND_TEXTURES)]

    def close(self) -> None:
        p.disconnect(self.client)
        self._tmp.cleanup()

    def _body(self, visual: int) -> int:
        return p.createMultiBody(
            baseMass=0, baseVisualShapeIndex=visual, basePosition=PARKED, physicsClientId=self.client
        )

    def _target_body(self, index: int) -> int:
        obj = OBJECT_CLASSES[index]
        mesh = class_mesh(obj)
        kwargs = {"rgbaColor": list(obj.rgba)} if obj.rgba else {}
        visual = p.createVisualShape(
            p.GEOM_MESH,
            fileName=str(mesh_path(obj.mesh)),
            meshScale=[mesh.scale] * 3,
            visualFramePosition=(-mesh.offset).tolist(),
            physicsClientId=self.client,
            **kwargs,
        )
        return self._body(visual)

    def _distractor_bodies(self, rng: np.random.Generator) -> tuple[list[int], list[float]]:
        ids = [i for i in range(1000) if i != 17]
        chosen = rng.choice(ids, NUM_DISTRACTORS, replace=False)
        bodies, radii = [], []
        for k, ident in enumerate(chosen):
            size = float(rng.uniform(0.04, 0.16))
            if k % 4 == 3:  # some simple boxes and cylinders, like the clutter in LM-O
                half = rng.uniform(0.3, 1.0, 3) * size / 2
                visual = p.createVisualShape(
                    p.GEOM_BOX, halfExtents=half.tolist(), physicsClientId=self.client
                )
            else:
                relative = f"random_urdfs/{ident:03d}/{ident:03d}.obj"
                mesh = load_mesh(relative, size)
                visual = p.createVisualShape(
                    p.GEOM_MESH,
                    fileName=str(mesh_path(relative)),
                    meshScale=[mesh.scale] * 3,
                    visualFramePosition=(-mesh.offset).tolist(),
                    physicsClientId=self.client,
                )
            bodies.append(self._body(visual))
            radii.append(size / 2)
        return bodies, radii

    def _ground_body(self, scale: float) -> int:
        visual = p.createVisualShape(
            p.GEOM_MESH,
            fileName=str(mesh_path("plane.obj")),
            meshScale=[scale, scale, 1.0],
            physicsClientId=self.client,
        )
        return self._body(visual)

    def _load_texture(self, rng: np.random.Generator, index: int) -> int:
        path = Path(self._tmp.name) / f"ground_{index:02d}.png"
        cv2.imwrite(str(path), texture(rng, (256, 256)))
        return p.loadTexture(str(path), physicsClientId=self.client)

    def move(self, body: int, rotation: np.ndarray, position: np.ndarray) -> None:
        p.resetBasePositionAndOrientation(
            body, position.tolist(), _quaternion(rotation), physicsClientId=self.client
        )

    def park_all(self) -> None:
        for body in [*self.targets, *self.distractors, *self.grounds]:
            p.resetBasePositionAndOrientation(body, PARKED, [0, 0, 0, 1], physicsClientId=self.client)

    def colour(self, body: int, rgba: np.ndarray) -> None:
        p.changeVisualShape(body, -1, rgbaColor=rgba.tolist(), physicsClientId=self.client)


def _place_positions(rng: np.random.Generator, radii: list[float], spread: float) -> list[np.ndarray | None]:
    """Ground positions in a disc, rejecting overlaps; None where no room was found."""
    placed: list[tuple[np.ndarray, float]] = []
    out: list[np.ndarray | None] = []
    for r in radii:
        spot = None
        for _ in range(40):
            xy = rng.uniform(-spread, spread, 2)
            if all(np.linalg.norm(xy - q) > 0.6 * (r + rq) for q, rq in placed):
                spot = xy
                break
        out.append(spot)
        if spot is not None:
            placed.append((spot, r))
    return out


def _rest_on_ground(vertices: np.ndarray, rotation: np.ndarray, xy: np.ndarray) -> np.ndarray:
    z = -float((vertices @ rotation.T)[:, 2].min())
    return np.array([xy[0], xy[1], z])


@dataclass(frozen=True)
class CameraPose:
    """Where the camera looks from: spherical coordinates around a target on the table."""

    azimuth: float  # radians
    elevation: float  # radians
    distance: float  # metres
    target: np.ndarray
    roll: float

    def camera(self, world: World) -> Camera:
        direction = np.array(
            [
                np.cos(self.elevation) * np.cos(self.azimuth),
                np.cos(self.elevation) * np.sin(self.azimuth),
                np.sin(self.elevation),
            ]
        )
        rotation, translation = look_at(self.target + self.distance * direction, self.target, self.roll)
        return Camera(world.width, world.height, FOCAL, rotation, translation)


def sample_pose(rng: np.random.Generator) -> CameraPose:
    azimuth = rng.uniform(0, 2 * np.pi)
    elevation = np.deg2rad(rng.uniform(15, 75))
    distance = rng.uniform(0.45, 1.0)
    target = np.array([*rng.normal(0, 0.04, 2), rng.uniform(0.0, 0.05)])
    return CameraPose(azimuth, elevation, distance, target, roll=rng.uniform(-0.3, 0.3))


def _place_targets(
    rng: np.random.Generator, world: World, spots: list[np.ndarray | None], classes: np.ndarray
) -> list[Placed]:
    placed = []
    for cls, xy in zip(classes, spots, strict=True):
        if xy is None:
            continue
        rotation = _resting_rotation(rng)
        position = _rest_on_ground(class_mesh(OBJECT_CLASSES[cls]).vertices, rotation, xy)
        body = world.targets[cls]
        world.move(body, rotation, position)
        rgba = OBJECT_CLASSES[cls].rgba
        if rgba is not None:
            world.colour(body, np.clip(np.array(rgba) + np.r_[rng.normal(0, 0.04, 3), 0], 0, 1))
        placed.append(Placed(int(cls), body, rotation, position))
    return placed


def _place_distractors(
    rng: np.random.Generator, world: World, chosen: np.ndarray, positions: list[np.ndarray | None]
) -> None:
    for index, position in zip(chosen, positions, strict=True):
        if position is None:
            continue
        world.move(world.distractors[index], _random_rotation(rng), position)
        world.colour(world.distractors[index], np.r_[rng.uniform(0, 1, 3), 1.0])


def _ground_position(rng: np.random.Generator, xy: np.ndarray | None, radius: float) -> np.ndarray | None:
    return None if xy is None else np.array([xy[0], xy[1], radius * rng.uniform(0.3, 0.9)])


def _occluder_position(rng: np.random.Generator, camera: Camera, target: np.ndarray) -> np.ndarray:
    """Between an annotated object and the camera: on the ground, or floating on the line of sight."""
    eye = -camera.rotation.T @ camera.translation
    if rng.random() < 0.5:
        toward = (eye - target)[:2] / max(np.linalg.norm((eye - target)[:2]), 1e-6)
        side = np.array([-toward[1], toward[0]])
        xy = target[:2] + toward * rng.uniform(0.06, 0.18) + side * rng.normal(0, 0.04)
        return np.array([xy[0], xy[1], rng.uniform(0.01, 0.05)])
    return target + rng.uniform(0.1, 0.4) * (eye - target) + rng.normal(0, 0.03, 3)


def _setup_ground(rng: np.random.Generator, world: World) -> None:
    ground = world.grounds[int(rng.integers(len(world.grounds)))]
    tex = world.ground_textures[int(rng.integers(len(world.ground_textures)))]
    angle = rng.uniform(0, 2 * np.pi)
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1.0]])
    world.move(ground, rot, np.zeros(3))
    p.changeVisualShape(ground, -1, textureUniqueId=tex, rgbaColor=[1, 1, 1, 1], physicsClientId=world.client)


def _render(rng: np.random.Generator, world: World, camera: Camera) -> tuple[np.ndarray, ...]:
    light = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.5, 2.0)])
    _, _, rgba, depth, seg = p.getCameraImage(
        world.width,
        world.height,
        viewMatrix=camera.view_matrix(),
        projectionMatrix=camera.projection_matrix(),
        renderer=p.ER_TINY_RENDERER,
        shadow=int(rng.random() < 0.5),
        lightDirection=light.tolist(),
        lightColor=rng.uniform(0.8, 1.0, 3).tolist(),
        lightAmbientCoeff=float(rng.uniform(0.35, 0.7)),
        lightDiffuseCoeff=float(rng.uniform(0.3, 0.7)),
        lightSpecularCoeff=float(rng.uniform(0.0, 0.3)),
        physicsClientId=world.client,
    )
    shape = (world.height, world.width)
    rgb = np.asarray(rgba, dtype=np.uint8).reshape(*shape, 4)[:, :, :3]
    depth = camera.metric_depth(np.asarray(depth, dtype=np.float64).reshape(shape))
    return rgb, depth, np.asarray(seg, dtype=np.int64).reshape(shape)


def render_scene(world: World, rng: np.random.Generator, extra_occluders: int = 0) -> Rendered:
    """Sample and render one scene: 3-6 annotated objects, clutter, occluders, ground, light, camera.

    ``extra_occluders`` adds that many distractors between the camera and the annotated
    objects (heavier occlusion); with 0 the scene, and every random draw, is the default's.
    """
    world.park_all()
    camera = sample_pose(rng).camera(world)
    objects = compose_scene(world, rng, camera, extra_occluders)
    rgb, depth, seg = _render(rng, world, camera)
    return _with_background(
        Rendered(rgb, depth, seg, camera, objects), texture(rng, (world.height, world.width))
    )


def compose_scene(
    world: World, rng: np.random.Generator, camera: Camera, extra_occluders: int
) -> list[Placed]:
    """Place the ground, the annotated objects, clutter and occluders (between them and ``camera``)."""
    _setup_ground(rng, world)
    classes = rng.choice(len(OBJECT_CLASSES), int(rng.integers(3, len(OBJECT_CLASSES) + 1)), replace=False)
    chosen = rng.choice(len(world.distractors), int(rng.integers(3, 9)) + extra_occluders, replace=False)
    occluders = int(rng.integers(1, 3)) + extra_occluders
    clutter = chosen[:-occluders]
    radii = [class_mesh(OBJECT_CLASSES[c]).diameter / 2 for c in classes]
    radii += [world.distractor_radius[i] for i in clutter]
    spots = _place_positions(rng, radii, spread=0.12)
    objects = _place_targets(rng, world, spots[: len(classes)], classes)
    positions = [
        _ground_position(rng, xy, r)
        for xy, r in zip(spots[len(classes) :], radii[len(classes) :], strict=True)
    ]
    targets = [
        objects[int(rng.integers(len(objects)))].position if objects else np.zeros(3)
        for _ in range(occluders)
    ]
    positions += [_occluder_position(rng, camera, t) for t in targets]
    _place_distractors(rng, world, chosen, positions)
    return objects


def render_view(world: World, camera: Camera, light_seed: int, background: np.ndarray) -> Rendered:
    """Render the composed scene from ``camera``; the same ``light_seed`` gives the same light."""
    rgb, depth, seg = _render(np.random.default_rng(light_seed), world, camera)
    return _with_background(Rendered(rgb, depth, seg, camera), background)


def _with_background(rendered: Rendered, background: np.ndarray) -> Rendered:
    rendered.rgb = np.where((rendered.seg < 0)[:, :, None], background, rendered.rgb)
    return rendered
