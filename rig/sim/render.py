"""Vectorized renderer of the simulated cube: numpy and OpenCV for the static scene, Embree for the
hand and the object.

Per camera, everything static (the walls with their tags, the table) is ray-cast analytically once,
with trilinear mip-mapped texture sampling, and cached. Per frame the moving part, the hand's posed
mesh and the object's mesh at its pose, is built into one Embree scene (shared by the cameras that
expose at that instant) and the rays of the pixel box that can see it are cast there in one batch,
`supersample`^2 rays per pixel, and averaged: edges are anti-aliased and the per-pixel labels follow
the majority of a pixel's rays (a tie goes to the ray through the pixel's centre).
Lens distortion is exact: rays are cast through the undistorted position of each distorted pixel
(OpenCV's undistortion as the start, then Newton steps on the full model). Neither this nor the
culling box uses the pipeline's camera model, so that a convention error there shows in the
pipeline's results instead of cancelling out.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from manus_core.cameras import CameraRig
from manus_core.ground_truth import LABEL_OBJECT, LABEL_WALLS
from rig.layouts import MAX_INCIDENCE_DEG

from . import shapes
from .memo import SharedCache
from .mesh import PosedMesh
from .objects import SimObject
from .shapes import Pose
from .world import MIP_LEVELS, Atlas, World

AMBIENT = 0.25  # room light when the LEDs are off, as a fraction of full LED light


@dataclass(frozen=True)
class Rendered:
    image: np.ndarray         # (H,W,3) float32 BGR in [0, 1], before noise and encoding
    labels: np.ndarray | None  # (H,W) uint8 when asked for


def _undistortion_map(rig: CameraRig, cam: int) -> np.ndarray:
    """(H+2, W+2, 2) float32 normalized undistorted coordinates of every pixel centre, with a
    one-pixel border so that sub-pixel positions at the image's edge interpolate too."""
    width, height = (int(x) for x in rig.size[cam])
    yy, xx = np.mgrid[-1:height + 1, -1:width + 1]
    pts = np.stack([xx.ravel(), yy.ravel()], axis=1).reshape(-1, 1, 2).astype(np.float64)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-10)
    start = cv2.undistortPoints(pts, rig.K[cam], rig.dist[cam], criteria=criteria).reshape(-1, 2)
    xy = newton_undistort(rig.K[cam], rig.dist[cam], pts[:, 0, 0], pts[:, 0, 1], start)
    return xy.reshape(height + 2, width + 2, 2).astype(np.float32)


# The same Newton step as dataset_tools/undistort.py, written apart on purpose: the simulator must
# not share the pipeline's camera model, so that a convention error there shows instead of
# cancelling out. Newton runs in blocks of points whose temporaries stay in the CPU cache: on whole
# arrays of a 1280x720 camera's rays a step took 0.6 s
_NEWTON_BLOCK = 1 << 14
_NEWTON_DONE = 1e-8   # a step this small (normalized units) leaves an error of about its square


def newton_undistort(K: np.ndarray, dist: np.ndarray, px: np.ndarray, py: np.ndarray, start: np.ndarray,
                     steps: int = 8) -> np.ndarray:
    """Normalized undistorted points (N,2) of the pixel positions px, py (N,), by Newton steps on
    the full model (k1, k2, p1, p2, k3) from `start` (N,2), a close guess.

    OpenCV's fixed-point iteration contracts by 1 - (dr_d/dr) / (r_d/r) per step: near the corners
    of a strongly barrel-distorted lens (k1 = -0.3) that is 0.7 to 0.8, and 20 steps left rays a
    third of a pixel off. Newton converges quadratically from there.
    """
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    px, py = np.asarray(px, np.float64).ravel(), np.asarray(py, np.float64).ravel()
    out = np.array(start, np.float64).reshape(-1, 2)
    for b in range(0, len(px), _NEWTON_BLOCK):
        block = slice(b, b + _NEWTON_BLOCK)
        v = (py[block] - K[1, 2]) / K[1, 1]
        u = (px[block] - K[0, 2] - K[0, 1] * v) / K[0, 0]
        x, y = out[block, 0].copy(), out[block, 1].copy()
        for _ in range(steps):
            xx, yy, xy = x * x, y * y, x * y
            r2 = xx + yy
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            d_radial = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))   # 2 d radial / d r2
            ex = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * xx) - u
            ey = y * radial + p1 * (r2 + 2 * yy) + 2 * p2 * xy - v
            jxx = radial + xx * d_radial + 2 * p1 * y + 6 * p2 * x
            jyy = radial + yy * d_radial + 6 * p1 * y + 2 * p2 * x
            jxy = xy * d_radial + 2 * p1 * x + 2 * p2 * y
            det = jxx * jyy - jxy * jxy
            dx, dy = (jyy * ex - jxy * ey) / det, (jxx * ey - jxy * ex) / det
            x -= dx
            y -= dy
            if max(np.abs(dx).max(initial=0.0), np.abs(dy).max(initial=0.0)) < _NEWTON_DONE:
                break
        out[block, 0], out[block, 1] = x, y
    return out


def remap_points(table: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup of `table` (rows, cols, ch) at float positions; cv2.remap, in rows of 1024
    because it wants maps under 32767 on a side."""
    n = x.size
    rows = -(-n // 1024)
    mx = np.zeros(rows * 1024, np.float32)
    my = np.zeros(rows * 1024, np.float32)
    mx[:n], my[:n] = x.ravel(), y.ravel()
    out = cv2.remap(table, mx.reshape(rows, 1024), my.reshape(rows, 1024), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * 1024, -1)[:n]


def shade(albedo: np.ndarray, normals: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Diffuse light from all around plus a term facing the viewer (the LED panels surround the
    cube), so that curved surfaces show their shape."""
    facing = np.abs(np.einsum("ij,ij->i", normals, dirs))
    return albedo * (0.55 + 0.45 * facing)[:, None].astype(np.float32)


def sample_atlas(atlas: Atlas, face: np.ndarray, u: np.ndarray, v: np.ndarray, texels_per_px: np.ndarray,
                 cos: np.ndarray) -> np.ndarray:
    """Trilinear (mip-mapped) colour (N,3) in [0, 1] of faces at (u, v) texels, seen with
    `texels_per_px` texels under a pixel's width head-on and at `cos` to the face's normal."""
    # grazing views stretch the footprint along one axis
    footprint = texels_per_px / np.sqrt(np.maximum(cos, 1e-3))
    lod = np.clip(np.log2(np.maximum(footprint, 1.0)), 0, MIP_LEVELS - 1)
    x0 = u + atlas.pad[1]
    y0 = face * atlas.stride + atlas.pad[0] + v
    colour = np.zeros((len(u), 3), np.float32)
    for level in range(int(np.floor(lod.min())), int(np.ceil(lod.max())) + 1):
        weight = np.maximum(0.0, 1.0 - np.abs(lod - level)).astype(np.float32)
        if not weight.any():
            continue
        scale = 2.0 ** level
        sample = remap_points(atlas.levels[level], x0 / scale - 0.5, y0 / scale - 0.5)
        colour += weight[:, None] * sample.astype(np.float32) / 255.0
    return colour


_CUBE_CORNERS = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T   # (8,3)
_MAX_INCIDENCE_TAN = np.tan(np.radians(MAX_INCIDENCE_DEG))
_SCENES_KEPT = 32
_RAY_GRID_BYTES = 4 << 20   # a camera's rays are kept when they take this little (320x180 at s = 2: 2.8 MB)
# the static views of the last cameras rendered, for every renderer of the process: a take's
# renderer starts where the previous take of the same rig left off
_STATIC: SharedCache[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = SharedCache(64)


@dataclass(frozen=True, eq=False)
class _Moving:
    """The hand's posed mesh and the posed object at one instant, in one Embree scene: geometry 0
    is the hand when there is one, the object the next; bounds are their bounding spheres
    (centre (3,), radius)."""

    scene: rtcs.EmbreeScene
    hand: PosedMesh | None
    obj: SimObject | None
    pose: Pose | None
    bounds: tuple[tuple[np.ndarray, float], ...]

    @classmethod
    def build(cls, hand: PosedMesh | None, obj: SimObject | None, pose: Pose | None) -> _Moving:
        scene = rtcs.EmbreeScene()
        bounds = []
        if hand is not None:
            TriangleMesh(scene, hand.vertices.astype(np.float32), hand.faces.astype(np.int32, copy=False))
            centre = (hand.vertices.min(axis=0) + hand.vertices.max(axis=0)) / 2
            bounds.append((centre, float(np.linalg.norm(hand.vertices - centre, axis=1).max())))
        if obj is not None:
            R, t = (np.asarray(p, np.float64) for p in pose)
            vertices, faces = obj.mesh()
            TriangleMesh(scene, (vertices @ R.T + t).astype(np.float32), faces)
            bounds.append((t, float(obj.radius)))
        # Embree builds its tree at the first cast, and cameras rendering in their own threads
        # must not race to do that: one ray builds it now
        scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))
        return cls(scene, hand, obj, pose, tuple(bounds))

    @property
    def hand_geom(self) -> int:
        """Embree's geometry id of the hand; -2, which no hit has, without one."""
        return -2 if self.hand is None else 0

    def cast(self, origin: np.ndarray, dirs: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, dict]:
        """The rays from `origin` (3,) along unit `dirs` (N,3) that meet the scene nearer than
        `depth` (N,), and Embree's answer for each of them: geomID, primID, barycentric u and v
        (a hit is (1 - u - v) v0 + u v1 + v v2 of its triangle), tfar (the distance)."""
        # embreex takes writable float32 arrays, one origin per ray, and writes the distances it
        # finds into `dists`: the caller's depth stays as it was
        origins = np.empty(dirs.shape, np.float32)
        origins[:] = origin
        hit = self.scene.run(origins, dirs.astype(np.float32), dists=depth.astype(np.float32), output=1)
        rays = np.flatnonzero(hit["geomID"] >= 0)
        return rays, {k: hit[k][rays] for k in ("geomID", "primID", "u", "v", "tfar")}

    def hand_surface(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Albedo (N,3) RGB, unit normal (N,3) and label (N,) at barycentric (u, v) of the hand's
        triangles `prim`: the label that of the corner with the largest weight (blended labels would
        make up classes between skin and paint), the colour blended over the corners of that label
        only (so that paint ends where its label does, not a triangle's width further), the normal
        over all three."""
        corners = self.hand.faces[prim]
        w = np.stack([1 - u - v, u, v], axis=1)
        labels = self.hand.label[corners]
        label = labels[np.arange(len(prim)), np.argmax(w, axis=1)]
        same = np.where(labels == label[:, None], w, 0.0)
        albedo = np.einsum("nk,nkc->nc", same / same.sum(axis=1, keepdims=True), self.hand.albedo[corners])
        normal = np.einsum("nk,nkc->nc", w.astype(np.float64), self.hand.normals[corners])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
        return albedo.astype(np.float32), normal, label


class Renderer:
    """Renders views of one world for the cameras of `rig` (the true cameras of the simulation)."""

    def __init__(self, world: World, rig: CameraRig, supersample: int = 2) -> None:
        self.world = world
        self.rig = rig
        self.supersample = max(1, int(supersample))
        # the recorder reads each camera in its own thread and every first frame renders the empty
        # cube: all at once, 53 cameras at 1280x720 took 12-19 GB; one at a time, one camera's worth
        self._background_lock = threading.Lock()
        self._undistort: dict[int, np.ndarray] = {}
        # the scenes of the last few instants: camera threads run up to a few frames apart
        self._posed: SharedCache[tuple[object, _Moving]] = SharedCache(_SCENES_KEPT)
        self._faces = world.faces
        self._normals = np.array([f.normal for f in self._faces])
        self._origins = np.array([f.origin for f in self._faces])
        self._us = np.array([f.u for f in self._faces])
        self._vs = np.array([f.v for f in self._faces])

    # -- the static part -------------------------------------------------------------------
    def _walls(self, origin: np.ndarray, dirs: np.ndarray, focal: float) -> tuple[np.ndarray, np.ndarray]:
        """Colour (N,3) and distance (N,) where rays from inside the cube meet the walls."""
        w = self.world
        h = w.edge / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            s_axes = (np.where(dirs > 0, h, -h) - origin) / dirs
        s_axes = np.where(np.isfinite(s_axes) & (s_axes > 0), s_axes, np.inf)
        axis = np.argmin(s_axes, axis=1)
        s = s_axes[np.arange(len(dirs)), axis]
        face = 2 * axis + (dirs[np.arange(len(dirs)), axis] < 0)
        hit = origin + s[:, None] * dirs
        rel = hit - self._origins[face]
        u = np.clip(np.einsum("ij,ij->i", rel, self._us[face]), 0, w.edge)
        v = np.clip(np.einsum("ij,ij->i", rel, self._vs[face]), 0, w.edge)
        cos = np.abs(np.einsum("ij,ij->i", dirs, self._normals[face]))
        return sample_atlas(w.atlas, face, u / w.texel, v / w.texel, s / focal / w.texel, cos), s

    def _static(self, origin: np.ndarray, dirs: np.ndarray, focal: float) -> tuple[np.ndarray, np.ndarray]:
        """Walls and table: colour (N,3) and distance (N,)."""
        colour, depth = self._walls(origin, dirs, focal)
        t_table, n_table = shapes.ray_box(np.broadcast_to(origin, dirs.shape), dirs,
                                          self.world.table_lo, self.world.table_hi)
        on_table = t_table < depth
        if on_table.any():
            points = origin + t_table[on_table, None] * dirs[on_table]
            normals = n_table[on_table]
            albedo = self.world.table_albedo(points)
            if self.world.table_tags:
                self._tagged_sides(albedo, points, normals, t_table[on_table], dirs[on_table], focal)
            colour[on_table] = shade(albedo, normals, dirs[on_table])
            depth = np.where(on_table, t_table, depth)
        return colour, depth

    def _tagged_sides(self, albedo: np.ndarray, points: np.ndarray, normals: np.ndarray, dist: np.ndarray,
                      dirs: np.ndarray, focal: float) -> None:
        """Replaces, in place, the albedo of table points on its sides by the sides' tagged texture."""
        w = self.world
        faces = w.table_faces
        side_normals = np.array([f.normal for f in faces])
        match = normals @ side_normals.T > 0.5
        side = match.any(axis=1)
        if not side.any():
            return
        face = np.argmax(match[side], axis=1)
        rel = points[side] - np.array([f.origin for f in faces])[face]
        u = np.einsum("ij,ij->i", rel, np.array([f.u for f in faces])[face])
        v = np.einsum("ij,ij->i", rel, np.array([f.v for f in faces])[face])
        cos = np.abs(np.einsum("ij,ij->i", dirs[side], side_normals[face]))
        albedo[side] = sample_atlas(w.table_atlas, face, u / w.texel, v / w.texel, dist[side] / focal / w.texel, cos)

    def background(self, cam: int) -> tuple[np.ndarray, np.ndarray]:
        """(H,W,3) colour and (H,W) distance of the empty cube with full LED light, cached."""
        return self._static_view(cam)[:2]

    def _static_view(self, cam: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The background of a camera and, for a small one, every ray's direction: the same in every
        take of a rig, so kept for the process (the demo records five takes with one rig)."""
        key = (self.world, self.supersample, self.rig.size[cam].tobytes(), self.rig.K[cam].tobytes(),
               self.rig.dist[cam].tobytes(), self.rig.R[cam].tobytes(), self.rig.t[cam].tobytes())
        with self._background_lock:
            return _STATIC.get(key, lambda: self._render_static(cam))

    def _render_static(self, cam: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        width, height = (int(x) for x in self.rig.size[cam])
        s = self.supersample
        gx, gy = self._subpixels(0, 0, width, height)
        dirs = self.rays(cam, gx.ravel(), gy.ravel())
        # each of the s x s rays samples a texture footprint 1/s of the pixel's, like a sensor
        # integrating over its pixel's area
        colour, depth = self._static(self.rig.centers[cam], dirs, self._focal(cam) * s)
        colour = colour.reshape(height, s, width, s, 3).mean(axis=(1, 3))
        depth = depth.reshape(height, s, width, s).min(axis=(1, 3))
        # per frame only the box around the hand is cast: a small camera keeps its rays undistorted
        grid = dirs.astype(np.float32).reshape(height * s, width * s, 3) if dirs.size * 4 <= _RAY_GRID_BYTES else None
        return colour, depth.astype(np.float32), grid

    def _box_rays(self, cam: int, x0: int, y0: int, width: int, height: int) -> np.ndarray:
        """Unit world directions (N,3) of the s x s rays of each pixel of a box, laid out as
        _subpixels: from the camera's kept rays when it has them."""
        grid = self._static_view(cam)[2]
        if grid is None:
            gx, gy = self._subpixels(x0, y0, width, height)
            return self.rays(cam, gx.ravel(), gy.ravel())
        s = self.supersample
        # unit to float32's precision, 1e-7: 1e-4 px at the focal lengths of the cube's cameras
        return grid[y0 * s:(y0 + height) * s, x0 * s:(x0 + width) * s].reshape(-1, 3).astype(np.float64)

    def _subpixels(self, x0: int, y0: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Positions (height*s, width*s) of the s x s rays of each pixel of a box, row-major."""
        s = self.supersample
        sub = (np.arange(s) + 0.5) / s - 0.5
        xs = (x0 + np.arange(width)[:, None] + sub[None, :]).ravel()
        ys = (y0 + np.arange(height)[:, None] + sub[None, :]).ravel()
        gy, gx = np.meshgrid(ys, xs, indexing="ij")
        return gx, gy

    def rays(self, cam: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Unit world directions (N,3) of the rays through distorted pixel positions."""
        if cam not in self._undistort:
            self._undistort[cam] = _undistortion_map(self.rig, cam)
        xy = remap_points(self._undistort[cam], np.asarray(x) + 1, np.asarray(y) + 1).astype(np.float64)
        # the map is exact at pixel centres only: between them its interpolation was 0.02 px off at
        # 320x180 for k1 = -0.3, which Newton steps from there remove
        xy = newton_undistort(self.rig.K[cam], self.rig.dist[cam], x, y, xy, steps=3)
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.einsum("ij,nj->ni", self.rig.R[cam].T, d)

    def _focal(self, cam: int) -> float:
        return float(np.sqrt(self.rig.K[cam, 0, 0] * self.rig.K[cam, 1, 1]))

    # -- the moving part -------------------------------------------------------------------
    def _moving(self, hand, hand_angles, paint, obj, object_pose) -> _Moving | None:
        """The hand and the object at one instant in their Embree scene; cameras that expose at the
        same moment (triggered rigs, label renders) share it."""
        with_hand, with_obj = hand is not None and hand_angles is not None, obj is not None and object_pose is not None
        if not (with_hand or with_obj):
            return None
        key = (id(hand) if with_hand else None,
               np.asarray(hand_angles, np.float64).tobytes() if with_hand else None,
               None if paint is None or not with_hand else np.asarray(paint).tobytes(),
               obj if with_obj else None,
               np.concatenate([np.ravel(p) for p in object_pose]).tobytes() if with_obj else None)

        def build() -> tuple[object, _Moving]:
            mesh = hand.posed_mesh(hand_angles, paint, obj, object_pose) if with_hand else None
            # the value holds the hand itself too, so that its id stays its own while the key is cached
            return hand, _Moving.build(mesh, obj if with_obj else None, object_pose if with_obj else None)

        return self._posed.get(key, build)[1]

    def _bbox(self, cam: int, centre: np.ndarray, radius: float) -> tuple[int, int, int, int] | None:
        """Pixel box (x0, y0, x1, y1) inclusive that holds a sphere's image, or None if unseen.

        The box holds the projected corners of the sphere's bounding cube: a circle around the
        projected centre, 1.2 times the sphere's size on the axis, fell short of spheres off the axis,
        which perspective and pincushion lenses stretch (by up to a quarter more near the image's
        corners). OpenCV projects them, not the pipeline's camera model, which the renderer must not
        share."""
        width, height = (int(x) for x in self.rig.size[cam])
        R, t = self.rig.R[cam], self.rig.t[cam]
        if R[2] @ centre + t[2] <= -radius:   # wholly behind the camera
            return None
        corners = (centre + radius * _CUBE_CORNERS) @ R.T + t
        # the lens polynomial holds out to MAX_INCIDENCE_DEG off the axis; a corner beyond it (or
        # behind the camera) may project anywhere, so the whole image is cast then
        if np.any(corners[:, 2] * _MAX_INCIDENCE_TAN <= np.hypot(corners[:, 0], corners[:, 1])):
            return 0, 0, width - 1, height - 1
        uv = cv2.projectPoints(corners, np.zeros(3), np.zeros(3), self.rig.K[cam], self.rig.dist[cam])[0][:, 0]
        x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 2
        x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 2
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width - 1), min(y1, height - 1)
        return None if x0 > x1 or y0 > y1 else (x0, y0, x1, y1)

    def render(self, cam: int, hand=None, hand_angles=None, paint=None, obj: SimObject | None = None,
               object_pose: Pose | None = None, light: float = 1.0, labels: bool = False) -> Rendered:
        """One view. `hand` is a hand model (rig.sim.hand) posed by `hand_angles` (26,) whose
        `posed_mesh(hand_angles, paint, obj, object_pose)` is its surface at that instant, `paint`
        its paint state; `obj` a SimObject at `object_pose` (R, t); `light` the LED level in [0, 1]."""
        bg_colour, bg_depth = self.background(cam)
        image = bg_colour.copy()
        label_img = np.full(bg_depth.shape, LABEL_WALLS, np.uint8) if labels else None
        moving = self._moving(hand, hand_angles, paint, obj, object_pose)
        boxes = [] if moving is None else [b for b in (self._bbox(cam, c, r) for c, r in moving.bounds) if b]
        if boxes:
            x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
            x1, y1 = max(b[2] for b in boxes), max(b[3] for b in boxes)
            self._render_box(cam, (x0, y0, x1, y1), image, label_img, bg_colour, bg_depth, moving)
        level = AMBIENT + (1 - AMBIENT) * float(np.clip(light, 0.0, 1.0))
        return Rendered(image * np.float32(level), label_img)

    def _render_box(self, cam: int, box: tuple[int, int, int, int], image: np.ndarray, label_img: np.ndarray | None,
                    bg_colour: np.ndarray, bg_depth: np.ndarray, moving: _Moving) -> None:
        """Casts every ray of a pixel box at the moving scene, in one batch: Embree's tree skips the
        rays that pass by, so nothing is culled here."""
        x0, y0, x1, y1 = box
        s = self.supersample
        bw, bh = x1 - x0 + 1, y1 - y0 + 1
        # the static depth under each ray, from its own pixel: the table edge is sharp enough there
        py = (np.arange(bh * s) // s)[:, None].repeat(bw * s, axis=1).ravel() + y0
        px = (np.arange(bw * s) // s)[None, :].repeat(bh * s, axis=0).ravel() + x0
        colour, label = self._trace(cam, self._box_rays(cam, x0, y0, bw, bh), bg_colour[py, px],
                                    bg_depth[py, px], moving)
        # average the s x s rays of each pixel (OpenCV's area resize by a whole factor is that mean,
        # and 5x faster than numpy's over the strided axes)
        image[y0:y1 + 1, x0:x1 + 1] = cv2.resize(colour.reshape(bh * s, bw * s, 3), (bw, bh),
                                                 interpolation=cv2.INTER_AREA)
        if label_img is None:
            return
        counts = np.zeros((bh * bw, 5), np.int32)
        pix = (np.arange(bh * s) // s)[:, None] * bw + (np.arange(bw * s) // s)[None, :]
        np.add.at(counts, (pix.ravel(), label), 2)
        # the majority of the pixel's rays; a tie (an even s, an edge through the middle) goes to the
        # ray through the pixel's centre, which for a straight edge is on the side covering more of it
        top = np.sort(counts, axis=1)
        tie = np.flatnonzero(top[:, -1] == top[:, -2])
        if len(tie):
            ty, tx = tie // bw + y0, tie % bw + x0
            _, centre = self._trace(cam, self.rays(cam, tx, ty), bg_colour[ty, tx], bg_depth[ty, tx], moving)
            counts[tie, centre] += 1
        label_img[y0:y1 + 1, x0:x1 + 1] = np.argmax(counts, axis=1).reshape(bh, bw).astype(np.uint8)

    def _trace(self, cam: int, dirs: np.ndarray, colour: np.ndarray, depth: np.ndarray,
               moving: _Moving) -> tuple[np.ndarray, np.ndarray]:
        """(N,3) colour and (N,) label of rays `dirs` (N,3) of a camera over the static scene's
        `colour` (overwritten where a ray meets the hand or the object) and `depth` under them."""
        origin = self.rig.centers[cam]
        label = np.full(len(dirs), LABEL_WALLS, np.uint8)
        rays, hit = moving.cast(origin, dirs, depth)
        if len(rays) == 0:
            return colour, label
        # hit points on the float64 ray through the pixel, at Embree's distance: the float32 copy
        # of the ray that Embree followed strays from it by up to 1e-7 of the distance
        points = origin + hit["tfar"][:, None].astype(np.float64) * dirs[rays]
        albedo = np.empty((len(rays), 3), np.float32)
        normals = np.empty((len(rays), 3))
        on_hand = hit["geomID"] == moving.hand_geom
        if on_hand.any():
            albedo[on_hand], normals[on_hand], label[rays[on_hand]] = moving.hand_surface(
                hit["primID"][on_hand], hit["u"][on_hand], hit["v"][on_hand])
        on_obj = ~on_hand
        if on_obj.any():
            obj, pose = moving.obj, moving.pose
            albedo[on_obj] = obj.albedo(shapes.points_to_local(points[on_obj], pose))
            normals[on_obj] = obj.normal(points[on_obj], pose)
            label[rays[on_obj]] = LABEL_OBJECT
        colour[rays] = shade(albedo[:, ::-1], normals, dirs[rays])   # RGB albedo, BGR image
        return colour, label
