"""The simulated hand: subjects, their anatomical skin mesh on the 26-DOF skeleton, soft tissue
at contact, and the paint the skin picks up.

The skin is the mesh of skin.py (anatomy.py's flesh, skinned to the bones). Posed by linear
blend skinning, it then flattens against the object wherever it would enter it (the pulp of a
finger pressed on a mug), so contact patches have an area; the vertices that touch pick up the
wet paint of a painted object. The vertices are the hand's surface points: contact, paint and
ground truth are per vertex.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import tomli_w

from manus_core.errors import SessionError
from manus_core.ground_truth import LABEL_HAND, LABEL_PAINT
from manus_core.skeleton import BONES, DEFAULT_BONE_LENGTHS, FINGERS, REST_FRAMES
from rig.sim.anatomy import MAX_PAD_FULLNESS, HandShape, RestHand
from rig.sim.mesh import PosedMesh
from rig.sim.objects import PAINT_RGB, SimObject
from rig.sim.shapes import Pose
from rig.sim.skin import blend, skinned_mesh

_PALM = np.array([1, 0, 0, 0] * 5, dtype=float)        # metacarpal segments
_THUMB = np.array([0, 1, 1, 1] + [0] * 16, dtype=float)  # moving thumb segments
_FINGER = 1.0 - _PALM - _THUMB                            # moving finger segments
# Built-in subjects. Beyond their bones, hands differ in the girth of their fingers, the fullness
# of their pads and the width and depth of their palms, which bone lengths do not tell and a
# template that knows only the bones misses.
SUBJECTS: dict[str, HandShape] = {
    # an average adult hand
    "s01": HandShape("s01", DEFAULT_BONE_LENGTHS.copy()),
    # a smaller hand with slim fingers, flat pads, a narrow thin palm and light skin
    "s02": HandShape("s02", DEFAULT_BONE_LENGTHS * (0.88 * _PALM + 0.93 * _FINGER + 0.86 * _THUMB),
                     finger_thickness=0.88, pad_fullness=0.7, palm_width=0.92, palm_thickness=0.88,
                     skin_rgb=(0.93, 0.75, 0.65), nail_rgb=(0.96, 0.82, 0.80)),
    # a larger hand with a long palm, thick fingers, full pads, a broad deep palm and dark skin
    "s03": HandShape("s03", DEFAULT_BONE_LENGTHS * (1.12 * _PALM + 1.02 * _FINGER + 1.10 * _THUMB),
                     finger_thickness=1.08, pad_fullness=1.35, palm_width=1.1, palm_thickness=1.15,
                     skin_rgb=(0.58, 0.40, 0.30), nail_rgb=(0.80, 0.62, 0.56)),
}

SEGMENTS = {f: ("metacarpal", "proximal", "distal") if f == "thumb" else ("proximal", "middle", "distal")
            for f in FINGERS}
REGION_NAMES = ("palm", "back", "wrist") + tuple(
    name for f in FINGERS
    for name in [f"{f}_{s}_{side}" for s in SEGMENTS[f] for side in ("palmar", "dorsal")] + [f"{f}_tip"])
# The grasping side of the hand: the palm, the finger pads and the fingertips.
PALMAR_REGIONS = tuple(i for i, n in enumerate(REGION_NAMES)
                       if n == "palm" or n.endswith("_palmar") or n.endswith("_tip"))
_TIP_COS = np.cos(np.radians(40.0))   # fingertip: the end of the finger within 40 deg of its axis
TOUCH_M = 0.0005           # skin this close to the object touches it and takes its paint
_PRESSED_GAP_M = 2e-5      # flattened skin stays this far out, so that the ray caster never ties
_PRESS_STEPS = 4
_PROXY_M = 0.002           # planning measures clearance on vertices about this far apart
_CHUNK_FRAMES = 16
_CLUSTER_M = 0.01          # the cells of the vertex groups that contact tests cull with


class HandModel:
    """One subject's skin mesh on its skeleton.

    Attributes: skeleton, subject, shape (HandShape), rest (RestHand), faces (T,3),
    surface_rest (V,3), surface_normal_rest (V,3), weights (V,20) of blend skinning, surface_bone
    (V,) the heaviest bone, surface_region (V,), surface_palmar (V,) bool, vertex_albedo (V,3) RGB,
    skin_albedo (3,), proxy (indices of vertices about 2 mm apart, for grasp planning).
    """

    def __init__(self, shape: HandShape) -> None:
        self.shape = shape
        self.subject = shape.name
        self.rest = RestHand(shape)
        self.skeleton = self.rest.skeleton
        mesh = skinned_mesh(self.rest)
        self.weights = mesh.weights
        self.faces = mesh.faces
        self.surface_rest, self.surface_normal_rest, self.surface_bone = mesh.vertices, mesh.normals, mesh.bone
        self.skin_albedo = np.asarray(shape.skin_rgb, np.float64)
        self.surface_region, nail = self._regions(mesh.part_kind)
        self.surface_palmar = np.isin(self.surface_region, PALMAR_REGIONS)
        self.vertex_albedo = self._albedo(nail)
        self.proxy = _spread(self.surface_rest, _PROXY_M)
        self._clusters()

    @property
    def n_points(self) -> int:
        return len(self.surface_rest)

    def _regions(self, part_kind: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Region (V,) of every vertex, and which vertices are nail."""
        n, bone = self.surface_normal_rest, self.surface_bone
        region = np.where(n[:, 2] < 0, REGION_NAMES.index("palm"), REGION_NAMES.index("back"))
        region[part_kind == "forearm"] = REGION_NAMES.index("wrist")
        nail = np.zeros(len(bone), bool)
        j = self.rest.joints
        for b in np.flatnonzero(np.arange(20) % 4):
            f, k = b // 4, b % 4 - 1
            sel = (bone == b) & (part_kind != "forearm")
            axes = REST_FRAMES[f]
            segment = f"{FINGERS[f]}_{SEGMENTS[FINGERS[f]][k]}"
            here = np.where(n[sel] @ axes[:, 2] < 0, REGION_NAMES.index(f"{segment}_palmar"),
                            REGION_NAMES.index(f"{segment}_dorsal"))
            if k == 2:
                q = (self.surface_rest[sel] - j[b]) @ axes
                length = float(np.linalg.norm(j[b + 1] - j[b]))
                here = np.where(n[sel] @ axes[:, 1] > _TIP_COS, REGION_NAMES.index(f"{FINGERS[f]}_tip"), here)
                w = self.rest.half_width(f, 2)[1]
                nail[sel] = (n[sel] @ axes[:, 2] > 0.3) & (q[:, 1] > 0.4 * length) & (np.abs(q[:, 0]) < 0.75 * w)
            region[sel] = here
        return region, nail

    def _albedo(self, nail: np.ndarray) -> np.ndarray:
        """Skin colour per vertex: lighter palms, darker creases, a mild mottle, nails."""
        rgb = np.tile(self.skin_albedo, (self.n_points, 1))
        rgb *= np.where(self.surface_palmar, 1.05, 0.96)[:, None]
        rgb *= 1.0 - 0.45 * np.clip(self.rest.crease_depth(self.surface_rest), 0.0, 1.0)[:, None]
        rgb *= 1.0 + 0.06 * np.random.default_rng(7).standard_normal(self.n_points)[:, None]
        rgb[nail] = self.shape.nail_rgb
        return np.clip(rgb, 0.0, 1.0).astype(np.float32)

    # -- posing ---------------------------------------------------------------------------
    def surface_points(self, angles: np.ndarray, index: np.ndarray | None = None,
                       normals: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Posed vertices and normals (...,V,3) for angles (...,26), of the vertices `index` only
        when given (None for the normals with normals=False); no contact with anything."""
        rot, trans = self.skeleton.bone_transforms(np.asarray(angles, dtype=np.float64))
        sel = slice(None) if index is None else index
        return blend(self.weights[sel], rot, trans, self.surface_rest[sel],
                     self.surface_normal_rest[sel] if normals else None)

    def posed_mesh(self, angles: np.ndarray, paint: np.ndarray | None = None, obj: SimObject | None = None,
                   object_pose: Pose | None = None) -> PosedMesh:
        """The skin at one pose (26,), flattened against the object where it would enter it,
        green where `paint` (V,) says."""
        vertices, normals = self.surface_points(angles)
        if obj is not None and object_pose is not None:
            vertices, normals = press(vertices, normals, obj, object_pose)
        albedo = self.vertex_albedo.copy()
        label = np.full(self.n_points, LABEL_HAND, np.uint8)
        if paint is not None:
            paint = np.asarray(paint, bool)
            albedo[paint] = PAINT_RGB
            label[paint] = LABEL_PAINT
        return PosedMesh(vertices, self.faces, normals, albedo, label)

    def _clusters(self) -> None:
        """Vertices grouped by bone and by a coarse grid cell, each group a sphere that moves with
        its bone: tested against an object first, they spare posing the skin far from it."""
        cells = np.floor(self.surface_rest / _CLUSTER_M).astype(np.int64)
        keys = np.c_[self.surface_bone, cells]
        _, self.cluster_of = np.unique(keys, axis=0, return_inverse=True)
        self.cluster_of = self.cluster_of.ravel()
        count = np.bincount(self.cluster_of)
        centre = np.stack([np.bincount(self.cluster_of, self.surface_rest[:, k]) for k in range(3)], 1) / count[:, None]
        self.cluster_centre = centre
        self.cluster_bone = np.zeros(len(count), np.int64)
        self.cluster_bone[self.cluster_of] = self.surface_bone
        spread = np.linalg.norm(self.surface_rest - centre[self.cluster_of], axis=1)
        self.cluster_radius = np.zeros(len(count))
        np.maximum.at(self.cluster_radius, self.cluster_of, spread)
        # blending moves a vertex off its heaviest bone's rigid motion: bound how far, over poses
        # that bend every joint to its limits
        poses = np.zeros((3, 26))
        poses[0, 6:], poses[1, 6:], poses[2, 6:] = self.skeleton.upper[6:], self.skeleton.lower[6:], 0.5
        rot, trans = self.skeleton.bone_transforms(poses)
        rigid = np.einsum("fvij,vj->fvi", rot[:, self.surface_bone], self.surface_rest) + trans[:, self.surface_bone]
        blended, _ = self.surface_points(poses, normals=False)
        self.cluster_slack = np.zeros(len(count))
        np.maximum.at(self.cluster_slack, self.cluster_of, np.linalg.norm(blended - rigid, axis=-1).max(axis=0))
        self.cluster_slack = 1.5 * self.cluster_slack + 0.001

    def near_vertices(self, angles: np.ndarray, sdf, distance: float) -> np.ndarray:
        """Indices of the vertices that may come within `distance` of the solid of `sdf` at any
        of the poses (T,26)."""
        rot, trans = self.skeleton.bone_transforms(np.asarray(angles, np.float64))
        b = self.cluster_bone
        centres = np.einsum("tcij,cj->tci", rot[:, b], self.cluster_centre) + trans[:, b]
        near = (sdf(centres) < self.cluster_radius + self.cluster_slack + distance).any(axis=0)
        return np.flatnonzero(near[self.cluster_of])

    def clearance(self, angles: np.ndarray, groups: list[np.ndarray], sdf) -> np.ndarray:
        """(G, len(groups)) the least distance from the solid of `sdf` of the skin of each group
        of bones, at angles (G,26): what grasp planning closes the fingers on."""
        out = np.full((len(angles), len(groups)), np.inf)
        for i, bones in enumerate(groups):
            idx = self.proxy[np.isin(self.surface_bone[self.proxy], bones)]
            if len(idx):
                points, _ = self.surface_points(angles, idx, normals=False)
                out[:, i] = sdf(points).min(axis=-1)
        return out

    def contact(self, angles: np.ndarray, obj: SimObject, pose: Pose,
                distance: float = TOUCH_M) -> tuple[np.ndarray, np.ndarray]:
        """(frame, vertex) pairs of the skin that touches the object at angles (T,26): within
        `distance` of its surface before the skin flattens against it."""
        frames, vertices = [], []
        sdf = lambda x: obj.sdf(x, pose)   # noqa: E731
        for start in range(0, len(angles), _CHUNK_FRAMES):
            chunk = angles[start:start + _CHUNK_FRAMES]
            idx = self.near_vertices(chunk, sdf, distance)
            if len(idx) == 0:
                continue
            points, _ = self.surface_points(chunk, idx, normals=False)
            f, v = np.nonzero(sdf(points) < distance)
            frames.append(f + start)
            vertices.append(idx[v])
        if not frames:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(frames), np.concatenate(vertices)


def press(vertices: np.ndarray, normals: np.ndarray, obj: SimObject, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Soft tissue: skin that would lie inside the object moves out onto its surface along the
    surface normal and faces it."""
    near = np.flatnonzero(np.linalg.norm(vertices - pose[1], axis=1) < obj.radius + 1e-3)
    vertices, normals = vertices.copy(), normals.copy()
    # one step along the gradient lands on the surface except near an edge, where the gradient is
    # the diagonal of two faces and the step falls short: a few more finish those
    for _ in range(_PRESS_STEPS):
        d = obj.sdf(vertices[near], pose)
        inside = d < _PRESSED_GAP_M
        if not inside.any():
            break
        near, d = near[inside], d[inside]
        out_dir = obj.normal(vertices[near], pose)
        vertices[near] += (_PRESSED_GAP_M - d)[:, None] * out_dir
        normals[near] = -out_dir
    return vertices, normals


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * ab, axis=1)


def _spread(points: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of a subset of points about `spacing` apart (one per grid cell)."""
    cells = np.floor(points / spacing).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return np.sort(first)


def capsule_fit(points: np.ndarray, bone: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Residuals (N,) of the best capsule per bone fitted to skin points (each point's distance to
    its bone's segment, one radius per bone by least squares: the mean), for the points of the
    fingers' phalanges (every bone but the five metacarpal ones)."""
    out = []
    for b in np.flatnonzero(np.arange(20) % 4):
        d = _segment_distance(points[bone == b], joints[BONES[b, 0]], joints[BONES[b, 1]])
        out.append(d - d.mean())
    return np.concatenate(out)


def load_subject(path: str | Path) -> HandShape:
    """A subject from a TOML file: `name`, optional `base` (a built-in subject whose bones it
    starts from) or `bone_lengths` (20, m), and the flesh relative to the average hand:
    `finger_thickness`, `pad_fullness`, `palm_width`, `palm_thickness`, `skin_rgb`, `nail_rgb`.
    SessionError names the file and the key of anything impossible."""
    path = Path(path)
    try:
        table = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise SessionError(f"{path}: not a readable subject file ({e})") from None
    known = {"name", "base", "bone_lengths", "finger_thickness", "pad_fullness", "palm_width", "palm_thickness",
             "skin_rgb", "nail_rgb"}
    for key in table:
        if key not in known:
            raise SessionError(f"{path}: unknown key {key!r} (known: {', '.join(sorted(known))})")
    base = table.get("base", "s01")
    if base not in SUBJECTS:
        raise SessionError(f"{path}: base: no built-in subject {base!r} (known: {', '.join(SUBJECTS)})")
    lengths = np.asarray(table.get("bone_lengths", SUBJECTS[base].bone_lengths), dtype=np.float64)
    if lengths.shape != (20,) or np.any(lengths <= 0):
        raise SessionError(f"{path}: bone_lengths: 20 positive lengths in metres expected")
    values = {}
    for key in ("finger_thickness", "pad_fullness", "palm_width", "palm_thickness"):
        value = table.get(key, getattr(SUBJECTS[base], key))
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SessionError(f"{path}: {key} = {value!r}: a number expected")
        if value < 0 or value == 0 and key != "pad_fullness":
            raise SessionError(f"{path}: {key} = {value}: a thickness or width cannot be negative or zero")
        if key != "pad_fullness" and not 0.5 <= value <= 1.6:
            raise SessionError(f"{path}: {key} = {value}: a factor of the average hand's, from 0.5 to 1.6")
        values[key] = float(value)
    if values["pad_fullness"] > MAX_PAD_FULLNESS:
        raise SessionError(f"{path}: pad_fullness = {values['pad_fullness']}: the fingertip pads would be deeper "
                           f"than the finger (at most {MAX_PAD_FULLNESS:.2f})")
    for key in ("skin_rgb", "nail_rgb"):
        rgb = np.asarray(table.get(key, getattr(SUBJECTS[base], key)), dtype=np.float64)
        if rgb.shape != (3,) or np.any((rgb < 0) | (rgb > 1)):
            raise SessionError(f"{path}: {key}: three values from 0 to 1 expected")
        values[key] = tuple(float(x) for x in rgb)
    return HandShape(str(table.get("name", path.stem)), lengths, **values)


def subject_toml(shape: HandShape) -> str:
    """A subject file (load_subject reads it back) of a shape."""
    return tomli_w.dumps({"name": shape.name, "bone_lengths": [float(x) for x in shape.bone_lengths],
                          "finger_thickness": shape.finger_thickness, "pad_fullness": shape.pad_fullness,
                          "palm_width": shape.palm_width, "palm_thickness": shape.palm_thickness,
                          "skin_rgb": list(shape.skin_rgb), "nail_rgb": list(shape.nail_rgb)})


def subject_shape(subject: str) -> HandShape:
    """A built-in subject by name, or a subject file (a path ending in .toml)."""
    if subject.endswith(".toml"):
        return load_subject(subject)
    if subject not in SUBJECTS:
        raise SessionError(f"unknown subject {subject!r}; choose one of {', '.join(SUBJECTS)} or a subject .toml file")
    return SUBJECTS[subject]


_HANDS: dict[str, HandModel] = {}


def make_hand(subject: str = "s01") -> HandModel:
    """The simulated hand of a built-in subject (SUBJECTS) or a subject file, built once per process."""
    shape = subject_shape(subject)
    key = repr((shape.name, shape.bone_lengths.tolist(), shape.finger_thickness, shape.pad_fullness,
                shape.palm_width, shape.palm_thickness, shape.skin_rgb, shape.nail_rgb))
    if key not in _HANDS:
        _HANDS[key] = HandModel(shape)
    return _HANDS[key]

