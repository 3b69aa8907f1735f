"""Vectorized renderer of the simulated cube: ray casting in numpy, OpenCV for texture sampling.

Per camera, everything static (the walls with their tags, the table) is rendered once with
trilinear mip-mapped texture sampling and cached. Per frame only the rays that can meet the hand or
the object (their projected bounding box) are cast, `supersample`^2 rays per pixel, and averaged:
edges are anti-aliased and the per-pixel labels follow the majority of a pixel's rays (a tie goes
to the ray through the pixel's centre).
Lens distortion is exact: rays are cast through the undistorted position of each distorted pixel
(OpenCV's undistortion as the start, then Newton steps on the full model).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from manus_core.cameras import CameraRig
from manus_core.ground_truth import LABEL_HAND, LABEL_OBJECT, LABEL_PAINT, LABEL_WALLS

from . import shapes
from .world import MIP_LEVELS, Atlas, World

PAINT_BGR = np.array([0.2, 0.78, 0.12], np.float32)  # the green residue left on the hand
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


class Renderer:
    """Renders views of one world for the cameras of `rig` (the true cameras of the simulation)."""

    def __init__(self, world: World, rig: CameraRig, supersample: int = 2) -> None:
        self.world = world
        self.rig = rig
        self.supersample = max(1, int(supersample))
        self._background: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # the recorder reads each camera in its own thread and every first frame renders the empty
        # cube: all at once, 53 cameras at 1280x720 took 12-19 GB; one at a time, one camera's worth
        self._background_lock = threading.Lock()
        self._undistort: dict[int, np.ndarray] = {}
        self._single = [rig.subset([cam_id]) for cam_id in rig.ids]
        self._posed: tuple[bytes, tuple] | None = None
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
        with self._background_lock:
            return self._background_of(cam)

    def _background_of(self, cam: int) -> tuple[np.ndarray, np.ndarray]:
        if cam not in self._background:
            width, height = (int(x) for x in self.rig.size[cam])
            s = self.supersample
            gx, gy = self._subpixels(0, 0, width, height)
            dirs = self.rays(cam, gx.ravel(), gy.ravel())
            # each of the s x s rays samples a texture footprint 1/s of the pixel's, like a sensor
            # integrating over its pixel's area
            colour, depth = self._static(self.rig.centers[cam], dirs, self._focal(cam) * s)
            colour = colour.reshape(height, s, width, s, 3).mean(axis=(1, 3))
            depth = depth.reshape(height, s, width, s).min(axis=(1, 3))
            self._background[cam] = (colour, depth.astype(np.float32))
        return self._background[cam]

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

    def _hand_geometry(self, hand, angles) -> tuple:
        """Capsules, surface points and their search tree for a pose; cameras that expose at the
        same moment (triggered rigs, label renders) share them."""
        key = np.asarray(angles, np.float64).tobytes() + bytes(str(id(hand)), "ascii")
        if self._posed is None or self._posed[0] != key:
            a, b, r = hand.capsules(angles)
            surface, _ = hand.surface_points(angles)
            self._posed = (key, (a, b, r, surface, cKDTree(surface)))
        return self._posed[1]

    def _focal(self, cam: int) -> float:
        return float(np.sqrt(self.rig.K[cam, 0, 0] * self.rig.K[cam, 1, 1]))

    # -- the moving part -------------------------------------------------------------------
    def _bbox(self, cam: int, centre: np.ndarray, radius: float) -> tuple[int, int, int, int] | None:
        """Pixel box (x0, y0, x1, y1) inclusive that holds a sphere's image, or None if unseen."""
        width, height = (int(x) for x in self.rig.size[cam])
        c_cam = self.rig.R[cam] @ centre + self.rig.t[cam]
        if c_cam[2] <= radius:  # the sphere reaches behind the camera's image plane
            return (0, 0, width - 1, height - 1) if c_cam[2] > -radius else None
        corners = centre + radius * _CUBE_CORNERS
        uv = self._single[cam].project(corners)[0]
        x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 2
        x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 2
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width - 1), min(y1, height - 1)
        return None if x0 > x1 or y0 > y1 else (x0, y0, x1, y1)

    def render(self, cam: int, hand=None, hand_angles=None, paint=None, obj=None, object_pose=None,
               light: float = 1.0, labels: bool = False) -> Rendered:
        """One view. `hand` is a rig.sim.hand.HandModel posed by `hand_angles` (26,), `paint` its
        per-surface-point paint flags; `obj` a rig.sim.objects.SimObject at `object_pose` (R, t);
        `light` the LED level in [0, 1]."""
        bg_colour, bg_depth = self.background(cam)
        image = bg_colour.copy()
        label_img = np.full(bg_depth.shape, LABEL_WALLS, np.uint8) if labels else None
        spheres = []
        if hand is not None and hand_angles is not None:
            a, b, r, _, _ = self._hand_geometry(hand, hand_angles)
            ends = np.concatenate([a, b])
            centre = (ends.min(axis=0) + ends.max(axis=0)) / 2
            spheres.append((centre, float(np.max(np.linalg.norm(ends - centre, axis=1)) + r.max())))
        if obj is not None and object_pose is not None:
            spheres.append((np.asarray(object_pose[1], np.float64), float(obj.radius)))
        boxes = [b for b in (self._bbox(cam, c, rad) for c, rad in spheres) if b is not None]
        if boxes:
            x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
            x1, y1 = max(b[2] for b in boxes), max(b[3] for b in boxes)
            self._render_box(cam, (x0, y0, x1, y1), image, label_img, bg_colour, bg_depth,
                             hand, hand_angles, paint, obj, object_pose)
        level = AMBIENT + (1 - AMBIENT) * float(np.clip(light, 0.0, 1.0))
        return Rendered(image * np.float32(level), label_img)

    def _render_box(self, cam, box, image, label_img, bg_colour, bg_depth, hand, hand_angles, paint,
                    obj, object_pose) -> None:
        x0, y0, x1, y1 = box
        s = self.supersample
        bw, bh = x1 - x0 + 1, y1 - y0 + 1
        gx, gy = self._subpixels(x0, y0, bw, bh)
        # the static depth under each ray, from its own pixel: the table edge is sharp enough there
        py = (np.arange(bh * s) // s)[:, None].repeat(bw * s, axis=1).ravel() + y0
        px = (np.arange(bw * s) // s)[None, :].repeat(bh * s, axis=0).ravel() + x0
        near_hand = near_obj = None
        if hand is not None and hand_angles is not None:
            a, b, r, _, _ = self._hand_geometry(hand, hand_angles)
            near_hand = self._near(cam, (a + b) / 2, np.linalg.norm(b - a, axis=1) / 2 + r, box)
        if obj is not None and object_pose is not None:
            near_obj = self._near(cam, np.asarray(object_pose[1], np.float64), obj.radius, box)[0]
        colour, label = self._trace(cam, self.rays(cam, gx.ravel(), gy.ravel()), bg_colour[py, px], bg_depth[py, px],
                                    hand, hand_angles, paint, obj, object_pose, near_hand, near_obj)
        # average the s x s rays of each pixel
        image[y0:y1 + 1, x0:x1 + 1] = colour.reshape(bh, s, bw, s, 3).mean(axis=(1, 3))
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
            _, centre = self._trace(cam, self.rays(cam, tx, ty), bg_colour[ty, tx], bg_depth[ty, tx],
                                    hand, hand_angles, paint, obj, object_pose)
            counts[tie, centre] += 1
        label_img[y0:y1 + 1, x0:x1 + 1] = np.argmax(counts, axis=1).reshape(bh, bw).astype(np.uint8)

    def _trace(self, cam, dirs, colour, depth, hand, hand_angles, paint, obj, object_pose,
               near_hand=None, near_obj=None) -> tuple[np.ndarray, np.ndarray]:
        """(N,3) colour and (N,) label of rays `dirs` (N,3) of a camera over the static scene's
        `colour` and `depth` under them; `near_hand` (capsules,N) and `near_obj` (N,) say which rays
        may meet each capsule and the object (all of them when None)."""
        origin = self.rig.centers[cam]
        n = len(dirs)
        depth = depth.astype(np.float64)
        colour = colour.copy()
        label = np.full(n, LABEL_WALLS, np.uint8)
        if hand is not None and hand_angles is not None:
            a, b, r, surface, tree = self._hand_geometry(hand, hand_angles)
            t_h = np.full(n, np.inf)
            n_h = np.zeros((n, 3))
            near = np.ones((len(a), n), bool) if near_hand is None else near_hand
            # Each finger (and the palm) is cast on its own rays, those that can meet it: far fewer
            # ray-capsule pairs than all against all.
            for group in np.unique(hand.capsule_finger):
                caps = np.flatnonzero(hand.capsule_finger == group)
                sel = np.flatnonzero(near[caps].any(axis=0))
                if len(sel) == 0:
                    continue
                t_g, _, n_g = shapes.ray_capsules(np.broadcast_to(origin, (len(sel), 3)), dirs[sel],
                                                  a[caps], b[caps], r[caps])
                closer = t_g < t_h[sel]
                t_h[sel[closer]], n_h[sel[closer]] = t_g[closer], n_g[closer]
            hit = t_h < depth
            if hit.any():
                points = origin + t_h[hit, None] * dirs[hit]
                _, nearest = tree.query(points)
                albedo = np.broadcast_to(np.asarray(hand.skin_albedo, np.float32)[::-1], (len(points), 3)).copy()
                albedo *= self._skin_texture(len(surface))[nearest, None]
                painted = np.zeros(len(points), bool) if paint is None else np.asarray(paint)[nearest]
                albedo[painted] = PAINT_BGR
                colour[hit] = shade(albedo, n_h[hit], dirs[hit])
                label[hit] = np.where(painted, LABEL_PAINT, LABEL_HAND)
                depth = np.where(hit, t_h, depth)
        if obj is not None and object_pose is not None:
            sel = np.arange(n) if near_obj is None else np.flatnonzero(near_obj)
            t_o, n_o, albedo_o = obj.intersect(np.broadcast_to(origin, (len(sel), 3)), dirs[sel], object_pose)
            hit = t_o < depth[sel]
            if hit.any():
                rays = sel[hit]
                colour[rays] = shade(np.asarray(albedo_o, np.float32)[hit][:, ::-1], n_o[hit], dirs[rays])
                label[rays] = LABEL_OBJECT
        return colour, label

    def _near(self, cam: int, centres: np.ndarray, radii, box: tuple[int, int, int, int]) -> np.ndarray:
        """(M,N) which rays of a box (laid out as in _subpixels) may meet each of M spheres: those
        in the pixel box of its bounding cube; all of them for a cube reaching behind the camera."""
        x0, y0, x1, y1 = box
        s = self.supersample
        rows, cols = (y1 - y0 + 1) * s, (x1 - x0 + 1) * s
        centres = np.atleast_2d(centres)
        radii = np.broadcast_to(np.asarray(radii, np.float64), (len(centres),))
        z = centres @ self.rig.R[cam, 2] + self.rig.t[cam, 2]
        # the pixel box of each sphere's bounding cube, from its projected corners: a circle around
        # the projected centre, 1.2 times the sphere's size on the axis, fell short of spheres off
        # the axis, which perspective and pincushion lenses stretch (by up to a quarter more near
        # the image's corners)
        corners = centres[:, None, :] + radii[:, None, None] * _CUBE_CORNERS
        uv = self._single[cam].project(corners.reshape(-1, 3))[0].reshape(len(centres), 8, 2)
        front = (z > 1.05 * np.sqrt(3) * radii)[:, None]   # every corner in front of the camera
        low = np.where(front, uv.min(axis=1) - 2, -np.inf)
        high = np.where(front, uv.max(axis=1) + 2, np.inf)
        # ray (i, j) of the box looks through pixel position (x0 + (j + 0.5) / s - 0.5, y0 + ...)
        lo = np.ceil((low - (x0, y0) + 0.5) * s - 0.5)
        hi = np.floor((high - (x0, y0) + 0.5) * s - 0.5)
        lo = np.clip(np.nan_to_num(lo, nan=0, neginf=0, posinf=cols), 0, (cols, rows)).astype(int)
        hi = np.clip(np.nan_to_num(hi, nan=0, neginf=-1, posinf=cols), -1, (cols - 1, rows - 1)).astype(int)
        near = np.zeros((len(centres), rows, cols), bool)
        for m in range(len(centres)):
            near[m, lo[m, 1]:hi[m, 1] + 1, lo[m, 0]:hi[m, 0] + 1] = True
        return near.reshape(len(centres), -1)

    _skin_cache: dict[int, np.ndarray] = {}

    @classmethod
    def _skin_texture(cls, n: int) -> np.ndarray:
        """A fixed, mild brightness variation per hand surface point (freckles, creases)."""
        if n not in cls._skin_cache:
            cls._skin_cache[n] = (1.0 + 0.08 * np.random.default_rng(7).standard_normal(n)).astype(np.float32)
        return cls._skin_cache[n]
