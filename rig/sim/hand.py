"""The simulated hand: subjects, a capsule surface on the 26-DOF skeleton, and paintable skin points.

The rendered surface is a union of capsules: one per moving finger bone (tapering from the
proximal to the distal phalanx) and a set of palm capsules that close the palm to ~2.5 cm
thickness. Every capsule is rigidly attached to one bone and follows it through
HandSkeleton.bone_transforms. A dense point set on the outer surface of that union (points
inside another capsule are dropped) carries paint and contact, each point attached to a bone
with a normal and a region label (palm, back of the hand, wrist, per finger segment
palmar/dorsal, fingertips).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from manus_core.skeleton import DEFAULT_BONE_LENGTHS, FINGERS, REST_FRAMES, HandSkeleton
from rig.sim import shapes
from rig.sim.objects import PAINT_RGB

# Built-in subjects: bone lengths (20,) in the order of manus_core.skeleton.
_PALM = np.array([1, 0, 0, 0] * 5, dtype=float)        # metacarpal segments
_THUMB = np.array([0, 1, 1, 1] + [0] * 16, dtype=float)  # moving thumb segments
_FINGER = 1.0 - _PALM - _THUMB                            # moving finger segments
SUBJECTS: dict[str, np.ndarray] = {
    # Average adult hand.
    "s01": DEFAULT_BONE_LENGTHS.copy(),
    # Smaller hand with relatively long fingers and a short thumb.
    "s02": DEFAULT_BONE_LENGTHS * (0.88 * _PALM + 0.93 * _FINGER + 0.86 * _THUMB),
    # Larger hand with a long palm, short fingers and a long thumb.
    "s03": DEFAULT_BONE_LENGTHS * (1.12 * _PALM + 1.02 * _FINGER + 1.10 * _THUMB),
}
# Thickness of the flesh (every capsule's radius) against the average hand of the same size: hands
# of one length differ in girth (finger circumference varies by about 10 % between adults), which
# bone lengths do not tell; a template that knows only the bones misses it.
SUBJECT_GIRTH: dict[str, float] = {"s01": 1.0, "s02": 0.92, "s03": 1.12}

SEGMENTS = {f: ("metacarpal", "proximal", "distal") if f == "thumb" else ("proximal", "middle", "distal")
            for f in FINGERS}
REGION_NAMES = ("palm", "back", "wrist") + tuple(
    name for f in FINGERS
    for name in [f"{f}_{s}_{side}" for s in SEGMENTS[f] for side in ("palmar", "dorsal")] + [f"{f}_tip"])
# The grasping side of the hand: the palm, the finger pads and the fingertips.
PALMAR_REGIONS = tuple(i for i, n in enumerate(REGION_NAMES)
                       if n == "palm" or n.endswith("_palmar") or n.endswith("_tip"))
_TIP_COS = np.cos(np.radians(40.0))   # fingertip: the end cap within 40 deg of the finger axis

SKIN_RGB = np.array([0.86, 0.63, 0.52])
# Capsule radii of the moving segments (m) for the average hand: thumb metacarpal (thenar),
# proximal, distal; other fingers proximal, middle, distal phalanx.
_FINGER_RADII = np.array([
    [0.0125, 0.0105, 0.0095],
    [0.0100, 0.0088, 0.0078],
    [0.0102, 0.0090, 0.0080],
    [0.0095, 0.0084, 0.0074],
    [0.0086, 0.0076, 0.0068],
])


class HandModel:
    """Capsule surface and paintable skin points of one subject's hand.

    Attributes: skeleton, subject, capsule_bone (M,), capsule_finger (M,) (-1 for palm and
    wrist), capsule_rest_a / capsule_rest_b (M,3), capsule_radius (M,), surface_rest (P,3),
    surface_normal_rest (P,3), surface_bone (P,), surface_capsule (P,), surface_region (P,),
    surface_palmar (P,) bool, skin_albedo (3,).
    """

    def __init__(self, skeleton: HandSkeleton, subject: str = "custom", spacing: float = 0.0025,
                 girth: float = 1.0) -> None:
        self.skeleton = skeleton
        self.subject = subject
        self.spacing = spacing
        self.girth = girth
        self.skin_albedo = SKIN_RGB.copy()
        self._build_capsules()
        self._build_surface()

    def _build_capsules(self) -> None:
        j = self.skeleton.rest_joints()
        # Thickness follows overall hand size so that a small hand is not a fat one, times the
        # subject's own girth.
        scale = float(self.skeleton.bone_lengths.sum() / DEFAULT_BONE_LENGTHS.sum())
        thick = scale * self.girth
        rows: list[tuple[int, int, np.ndarray, np.ndarray, float, str]] = []
        for f in range(5):
            for k in range(3):
                bone, r = 4 * f + k + 1, _FINGER_RADII[f, k] * thick
                a, b = j[bone], j[bone + 1]
                if k == 2:  # the tip keypoint is the end of the finger: the capsule stops there
                    b = b - r * (b - a) / np.linalg.norm(b - a)
                rows.append((bone, f, a, b, r, "finger"))
        mcp = j[[5, 9, 13, 17]]
        heel_r = np.array([0.8 * mcp[0, 0], 0.015 * scale, 0.0])
        heel_u = np.array([0.75 * mcp[3, 0], 0.015 * scale, 0.0])
        heel_c = 0.5 * (heel_r + heel_u)
        mid_r, mid_u = 0.5 * (heel_r + mcp[0]), 0.5 * (heel_u + mcp[3])
        palm = [  # (a, b, radius) rigid with the palm (bone 8 moves with the global pose)
            (heel_r, mcp[0], 0.0120), (heel_c, mcp[1], 0.0122), (heel_c, mcp[2], 0.0120),
            (heel_u, mcp[3], 0.0112), (mcp[0], mcp[3], 0.0110), (heel_r, heel_u, 0.0125),
            (mid_r, mid_u, 0.0122),
        ]
        for a, b, r in palm:
            rows.append((8, -1, a, b, r * thick, "palm"))
        rows.append((0, -1, np.array([-0.005, 0.01, 0.0]) * scale, j[1], 0.0130 * thick, "palm"))
        # The wrist is thicker than the palm on the dorsal side, not the palmar one.
        rows.append((8, -1, np.array([0.0, 0.0, 0.004]) * scale, np.array([0.0, -0.04, 0.004]) * scale,
                     0.017 * thick, "wrist"))
        self.capsule_bone = np.array([r[0] for r in rows])
        self.capsule_finger = np.array([r[1] for r in rows])
        self.capsule_rest_a = np.array([r[2] for r in rows], dtype=float)
        self.capsule_rest_b = np.array([r[3] for r in rows], dtype=float)
        self.capsule_radius = np.array([r[4] for r in rows], dtype=float)
        self._capsule_kind = [r[5] for r in rows]

    def _build_surface(self) -> None:
        pts, nrm, cap = [], [], []
        for m, (a, b, r) in enumerate(zip(self.capsule_rest_a, self.capsule_rest_b, self.capsule_radius)):
            p, n = shapes.capsule_surface(a, b, r, self.spacing)
            pts.append(p)
            nrm.append(n)
            cap.append(np.full(len(p), m))
        pts, nrm, cap = np.concatenate(pts), np.concatenate(nrm), np.concatenate(cap)
        # Drop points buried in another capsule: what is left is the outer surface of the union.
        d = shapes.capsule_distances(pts, self.capsule_rest_a, self.capsule_rest_b, self.capsule_radius)
        d[np.arange(len(pts)), cap] = np.inf
        keep = d.min(axis=1) > -1e-4
        self.surface_rest, self.surface_normal_rest, self.surface_capsule = pts[keep], nrm[keep], cap[keep]
        self.surface_bone = self.capsule_bone[self.surface_capsule]
        self.surface_region = self._regions()
        self.surface_palmar = np.isin(self.surface_region, PALMAR_REGIONS)

    def _regions(self) -> np.ndarray:
        region = np.empty(len(self.surface_rest), dtype=np.int64)
        kinds = np.array(self._capsule_kind)[self.surface_capsule]
        n = self.surface_normal_rest
        region[kinds == "wrist"] = REGION_NAMES.index("wrist")
        on_palm = kinds == "palm"
        region[on_palm] = np.where(n[on_palm, 2] < 0, REGION_NAMES.index("palm"), REGION_NAMES.index("back"))
        axis = self.capsule_rest_b - self.capsule_rest_a
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        for i in np.flatnonzero(kinds == "finger"):
            bone = self.surface_bone[i]
            f, k = bone // 4, bone % 4 - 1
            # The pad of a finger faces its rest frame's -z (for the thumb: across the palm).
            side = "palmar" if n[i] @ REST_FRAMES[f][:, 2] < 0 else "dorsal"
            name = f"{FINGERS[f]}_{SEGMENTS[FINGERS[f]][k]}_{side}"
            if k == 2 and n[i] @ axis[self.surface_capsule[i]] > _TIP_COS:
                name = f"{FINGERS[f]}_tip"
            region[i] = REGION_NAMES.index(name)
        return region

    @property
    def n_points(self) -> int:
        return len(self.surface_rest)

    def capsules(self, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World capsules for a pose: (a (...,M,3), b (...,M,3), r (M,)) for angles (...,26)."""
        rot, trans = self.skeleton.bone_transforms(np.asarray(angles, dtype=np.float64))
        rb, tb = rot[..., self.capsule_bone, :, :], trans[..., self.capsule_bone, :]
        a = np.einsum("...mij,mj->...mi", rb, self.capsule_rest_a) + tb
        b = np.einsum("...mij,mj->...mi", rb, self.capsule_rest_b) + tb
        return a, b, self.capsule_radius

    def surface_points(self, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World surface points and normals (...,P,3) for angles (...,26)."""
        rot, trans = self.skeleton.bone_transforms(np.asarray(angles, dtype=np.float64))
        rb = rot[..., self.surface_bone, :, :]
        points = np.einsum("...pij,pj->...pi", rb, self.surface_rest) + trans[..., self.surface_bone, :]
        return points, np.einsum("...pij,pj->...pi", rb, self.surface_normal_rest)

    def albedo(self, points_world: np.ndarray, angles: np.ndarray, paint: np.ndarray | None = None) -> np.ndarray:
        """Albedo (N,3) float32 at world points on the hand: skin, or paint green where the
        nearest surface point carries paint."""
        rgb = np.tile(self.skin_albedo.astype(np.float32), (len(points_world), 1))
        if paint is None or not np.any(paint) or len(points_world) == 0:
            return rgb
        surface, _ = self.surface_points(angles)
        _, nearest = cKDTree(surface).query(np.asarray(points_world, dtype=np.float64))
        rgb[np.asarray(paint, dtype=bool)[nearest]] = PAINT_RGB.astype(np.float32)
        return rgb


def make_hand(subject: str = "s01", spacing: float = 0.0025) -> HandModel:
    """The simulated hand of a built-in subject (SUBJECTS); ValueError names the choices otherwise."""
    if subject not in SUBJECTS:
        raise ValueError(f"unknown subject {subject!r}; choose one of {', '.join(SUBJECTS)}")
    return HandModel(HandSkeleton(SUBJECTS[subject]), subject=subject, spacing=spacing, girth=SUBJECT_GIRTH[subject])
