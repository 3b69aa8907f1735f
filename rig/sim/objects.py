"""The graspable objects of the simulated cube: a box, a mug-like cylinder and a sphere.

Each object lives in its own frame (origin at its centre, z up) and is placed by a pose
(R, t), x_world = R @ x_local + t. Its surface carries a procedural texture fixed to the object
(checker cells, colour patches and dark spots) so that feature matching and splatting find
detail; a painted object is coated with wet green paint instead, as in MANUS-Grasps.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np

from rig.sim import shapes
from rig.sim.mesh import icosphere

OBJECTS = ("box", "mug", "sphere")

BOX_HALF = (0.03, 0.03, 0.045)          # 6 x 6 x 9 cm
MUG_RADIUS, MUG_HEIGHT = 0.04, 0.10
SPHERE_RADIUS = 0.04

PAINT_RGB = np.array([0.15, 0.75, 0.20])
_BASE_RGB = {"box": (0.80, 0.55, 0.30), "mug": (0.25, 0.40, 0.80), "sphere": (0.85, 0.25, 0.22)}
_ACCENT_RGB = {"box": (0.95, 0.90, 0.75), "mug": (0.95, 0.85, 0.30), "sphere": (0.95, 0.95, 0.90)}
_CELL = 0.012                            # texture cell size (m): a few cells per face
# Largest distance (m) of the objects' triangle meshes from their true curved surfaces: a silhouette
# moves by at most this, 0.03 px for a 1280x720 camera (f ~ 830 px) half a metre away. The sphere
# then takes 20480 triangles (its Embree scene builds in about 13 ms, once per instant) and the
# mug 100 segments.
FACET_ERROR = 2e-5


def _cell_hash(cells: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic pseudo-random number in [0, 1) per integer cell (N,3)."""
    c = cells.astype(np.uint64) + np.uint64(1 << 20)
    h = (c[:, 0] * np.uint64(73856093)) ^ (c[:, 1] * np.uint64(19349663)) ^ (c[:, 2] * np.uint64(83492791))
    h ^= np.uint64(salt * 2654435761)
    h = (h ^ (h >> np.uint64(13))) * np.uint64(0x5BD1E995)
    h ^= h >> np.uint64(15)
    return (h % np.uint64(1 << 24)).astype(np.float64) / float(1 << 24)


def texture(name: str, p_local: np.ndarray) -> np.ndarray:
    """Albedo (N,3) float32 of an unpainted object at local surface points (N,3)."""
    p = np.asarray(p_local, dtype=np.float64)
    cells = np.floor(p / _CELL).astype(np.int64)
    checker = (cells.sum(axis=1) % 2).astype(np.float64)
    mix = (_cell_hash(cells, 1) > 0.7).astype(np.float64)[:, None]
    rgb = (1 - mix) * np.asarray(_BASE_RGB[name]) + mix * np.asarray(_ACCENT_RGB[name])
    rgb = rgb * (0.6 + 0.4 * checker)[:, None]
    # One dark spot per cell at a hashed position: blobs give corners at many scales.
    centre = (cells + 0.2 + 0.6 * np.stack([_cell_hash(cells, s) for s in (2, 3, 4)], axis=1)) * _CELL
    radius = _CELL * (0.15 + 0.2 * _cell_hash(cells, 5))
    spot = np.linalg.norm(p - centre, axis=1) < radius
    rgb[spot] *= 0.25
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


def paint_texture(p_local: np.ndarray) -> np.ndarray:
    """Albedo (N,3) float32 of wet green paint: a mild, smooth brightness variation."""
    p = np.asarray(p_local, dtype=np.float64)
    wave = np.sin(p @ np.array([97.0, 61.0, 43.0])) * np.sin(p @ np.array([-37.0, 83.0, 71.0]))
    cells = np.floor(p / (2 * _CELL)).astype(np.int64)
    shade = 1.0 + 0.06 * wave + 0.05 * (_cell_hash(cells, 7) - 0.5)
    return np.clip(PAINT_RGB * shade[:, None], 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class SimObject:
    """A rigid object: name in OBJECTS; painted = coated with green paint."""

    name: str
    painted: bool = False

    def __post_init__(self) -> None:
        if self.name not in OBJECTS:
            raise ValueError(f"unknown object {self.name!r}; choose one of {', '.join(OBJECTS)}")

    @property
    def half_height(self) -> float:
        """Distance from the object's centre to its base."""
        return {"box": BOX_HALF[2], "mug": MUG_HEIGHT / 2, "sphere": SPHERE_RADIUS}[self.name]

    @property
    def radius(self) -> float:
        """Radius of the bounding sphere about the object's centre."""
        return {"box": float(np.linalg.norm(BOX_HALF)), "mug": float(np.hypot(MUG_RADIUS, MUG_HEIGHT / 2)),
                "sphere": SPHERE_RADIUS}[self.name]

    def resting_pose(self, table_top_z: float = -0.15) -> shapes.Pose:
        """Upright on the table top, centred at x = y = 0."""
        return np.eye(3), np.array([0.0, 0.0, table_top_z + self.half_height])

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The surface as triangles in the object's frame: vertices (V,3) float64 on the surface,
        faces (T,3) int32 counter-clockwise seen from outside, within FACET_ERROR of it."""
        return _local_mesh(self.name)

    def sdf_local(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (N,) at points in the object's frame."""
        if self.name == "box":
            return shapes.sdf_box(p, -np.asarray(BOX_HALF), np.asarray(BOX_HALF))
        if self.name == "mug":
            return shapes.sdf_cylinder(p, MUG_RADIUS, -MUG_HEIGHT / 2, MUG_HEIGHT / 2)
        return shapes.sdf_sphere(p, np.zeros(3), SPHERE_RADIUS)

    def sdf(self, p_world: np.ndarray, pose: shapes.Pose) -> np.ndarray:
        """Signed distance (...,) at world points (...,3) for the object posed at (R, t)."""
        p = np.asarray(p_world)
        return self.sdf_local(shapes.points_to_local(p.reshape(-1, 3), pose)).reshape(p.shape[:-1])

    def normal(self, p_world: np.ndarray, pose: shapes.Pose, eps: float = 1e-5) -> np.ndarray:
        """Unit gradient (N,3) of the SDF at world points: the outward direction away from the object."""
        p = np.asarray(p_world, dtype=np.float64)
        steps = np.eye(3) * eps
        g = np.stack([self.sdf(p + s, pose) - self.sdf(p - s, pose) for s in steps], axis=-1)
        return g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-30)

    def albedo(self, p_local: np.ndarray) -> np.ndarray:
        """Albedo (N,3) float32 RGB at surface points (N,3) in the object's frame."""
        return paint_texture(p_local) if self.painted else texture(self.name, p_local)

    def intersect(self, o: np.ndarray, d: np.ndarray,
                  pose: shapes.Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World rays -> (t (N,), world normal (N,3), albedo (N,3) float32); t = inf on miss."""
        ol, dl = shapes.rays_to_local(o, d, pose)
        if self.name == "box":
            t, nl = shapes.ray_box(ol, dl, -np.asarray(BOX_HALF), np.asarray(BOX_HALF))
        elif self.name == "mug":
            t, nl = shapes.ray_cylinder(ol, dl, MUG_RADIUS, -MUG_HEIGHT / 2, MUG_HEIGHT / 2)
        else:
            t = shapes.ray_sphere(ol, dl, np.zeros(3), SPHERE_RADIUS)
            hit = np.isfinite(t)
            nl = np.zeros((len(ol), 3), dtype=ol.dtype)
            nl[hit] = (ol[hit] + t[hit, None] * dl[hit]) / SPHERE_RADIUS
        hit = np.isfinite(t)
        albedo = np.zeros((len(t), 3), dtype=np.float32)
        albedo[hit] = self.albedo(ol[hit] + t[hit, None] * dl[hit])
        return t, shapes.vectors_to_world(nl, pose), albedo


@functools.cache
def _local_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    vertices, faces = _build_mesh(name)
    # shared by every caller: read-only, so that none can change another's
    vertices.flags.writeable = faces.flags.writeable = False
    return vertices, faces


def _build_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    if name == "box":
        # corner i sits at -half or +half by its bits (x, y, z); the box's faces are flat, so two
        # triangles each are exact
        corners = (np.array([[i & 1, i >> 1 & 1, i >> 2 & 1] for i in range(8)]) * 2 - 1) * np.asarray(BOX_HALF)
        quads = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
        return corners, quads[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3).astype(np.int32)
    if name == "mug":
        # n segments: a chord of the rim lies r (1 - cos(pi / n)) inside the circle
        n = int(np.ceil(np.pi / np.arccos(1 - FACET_ERROR / MUG_RADIUS)))
        angle = 2 * np.pi * np.arange(n) / n
        ring = MUG_RADIUS * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        z = np.repeat([-MUG_HEIGHT / 2, MUG_HEIGHT / 2], n)[:, None]
        centres = [[0.0, 0.0, -MUG_HEIGHT / 2], [0.0, 0.0, MUG_HEIGHT / 2]]
        vertices = np.concatenate([np.concatenate([np.tile(ring, (2, 1)), z], axis=1), centres])
        i, j = np.arange(n), (np.arange(n) + 1) % n   # bottom ring i, top ring n + i
        faces = np.concatenate([np.stack(f, axis=1) for f in (
            (i, j, n + j), (i, n + j, n + i),                        # the side
            (np.full(n, 2 * n), j, i), (np.full(n, 2 * n + 1), n + i, n + j))])   # bottom, top
        return vertices, faces.astype(np.int32)
    # an icosphere's facets come about 4 times closer to the sphere with each subdivision
    for subdivisions in itertools.count():
        vertices, faces = icosphere(subdivisions)
        tri = vertices[faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nearest_plane = np.min(np.einsum("ij,ij->i", normals, tri[:, 0]) / np.linalg.norm(normals, axis=1))
        if SPHERE_RADIUS * (1 - nearest_plane) <= FACET_ERROR:
            return SPHERE_RADIUS * vertices, faces


def make_object(name: str, painted: bool = False) -> SimObject:
    """The object called name (one of OBJECTS); ValueError names the choices otherwise."""
    return SimObject(name, painted)
