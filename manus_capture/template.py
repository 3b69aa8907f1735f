"""The baseline hand: a capsule template on the skeleton, without a learned shape.

This plays the part of MANO's mean shape in the MANUS paper's comparison: it knows the subject's
bone lengths (from annotate) but not their hand's thickness, the flesh of the palm between the
metacarpals, or the wrist. One capsule per bone, radii from generic adult anthropometry scaled by
overall hand size, surface points about 2.5 mm apart rigidly attached to their bone. Each point is
a small opaque isotropic Gaussian, so contacts and renders go through exactly the code that scores
the Gaussian hand (contacts.py).
"""

from __future__ import annotations

import numpy as np
import torch

from manus_capture.splat.hand import point_segment_distance
from manus_core.skeleton import BONES, DEFAULT_BONE_LENGTHS, HandSkeleton

# Generic radii (m) per bone of the average adult hand: metacarpal, proximal, middle, distal
# phalanx (the thumb: carpal, metacarpal, proximal, distal).
TEMPLATE_RADII = np.array([
    [0.0120, 0.0120, 0.0100, 0.0090],
    [0.0110, 0.0095, 0.0085, 0.0075],
    [0.0110, 0.0095, 0.0085, 0.0075],
    [0.0105, 0.0090, 0.0080, 0.0072],
    [0.0100, 0.0085, 0.0075, 0.0068],
])
SPACING_M = 0.0025


def capsule_distances(p: np.ndarray, a: np.ndarray, b: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Signed distance (N,M) of every point (N,3) to every capsule a (M,3) -> b (M,3), radius r (M,)."""
    d = point_segment_distance(*(torch.as_tensor(np.asarray(x, np.float64)) for x in (p, a, b)))
    return d.numpy() - np.asarray(r, np.float64)


def capsule_surface(a: np.ndarray, b: np.ndarray, r: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (K,3) and outward normals about `spacing` apart on one capsule: staggered rings on
    the cylinder, a Fibonacci lattice on the two end caps."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    e = axis / length
    u = np.cross(e, [0.0, 0.0, 1.0] if abs(e[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(e, u)
    n_ring = max(1, int(round(length / spacing)))
    n_circ = max(6, int(round(2 * np.pi * r / spacing)))
    z = (np.arange(n_ring) + 0.5) * length / n_ring
    phi = 2 * np.pi * (np.arange(n_circ)[None, :] + 0.5 * (np.arange(n_ring)[:, None] % 2)) / n_circ
    n_side = (np.cos(phi)[..., None] * u + np.sin(phi)[..., None] * v).reshape(-1, 3)
    p_side = a + np.repeat(z, n_circ)[:, None] * e + r * n_side
    n_sph = max(8, int(round(4 * np.pi * r * r / spacing ** 2)))
    k = np.arange(n_sph) + 0.5
    cos_t = 1 - 2 * k / n_sph
    sin_t = np.sqrt(1 - cos_t ** 2)
    ang = np.pi * (1 + 5 ** 0.5) * k
    n_cap = (cos_t[:, None] * e + sin_t[:, None] * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v))
    low = n_cap @ e < 0
    p_cap = np.where(low[:, None], a, b) + r * n_cap
    return np.concatenate([p_side, p_cap]), np.concatenate([n_side, n_cap])


class PointHand:
    """Points rigidly attached to the bones of a skeleton, each an isotropic Gaussian of standard
    deviation `sigma`: the capsule template, or any surface sampled on the bones."""

    def __init__(self, skeleton: HandSkeleton, points_rest: np.ndarray, bone: np.ndarray, sigma: float,
                 normals_rest: np.ndarray | None = None) -> None:
        self.skeleton = skeleton
        self.points_rest = np.asarray(points_rest, dtype=np.float64)
        self.normals_rest = None if normals_rest is None else np.asarray(normals_rest, dtype=np.float64)
        self.bone = np.asarray(bone, dtype=np.int64)
        self.sigma = float(sigma)

    def __len__(self) -> int:
        return len(self.points_rest)

    def posed(self, angles: np.ndarray, normals: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Posed points (...,P,3) float64 for angles (...,26), and their normals when asked for
        (None for a hand built without them)."""
        R, t = self.skeleton.bone_transforms(np.asarray(angles, dtype=np.float64))
        Rb = R[..., self.bone, :, :]
        points = np.einsum("...pij,pj->...pi", Rb, self.points_rest) + t[..., self.bone, :]
        if not normals or self.normals_rest is None:
            return points, None
        return points, np.einsum("...pij,pj->...pi", Rb, self.normals_rest)

    def pose_batch(self, angles: torch.Tensor) -> torch.Tensor:
        """Posed points (T,P,3) for angles (T,26)."""
        return torch.as_tensor(self.posed(angles)[0], dtype=torch.float32)

    def pose(self, angles: torch.Tensor) -> dict[str, torch.Tensor]:
        """Posed centres (P,3) and isotropic covariances (P,3,3) for angles (26,)."""
        means = self.pose_batch(torch.as_tensor(angles)[None])[0]
        covars = torch.eye(3).expand(len(means), 3, 3) * self.sigma ** 2
        return {"means": means, "covars": covars}


def template_capsules(bone_lengths=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The template's capsule per bone in the rest pose: ends a (20,3), b (20,3) and radii (20,)."""
    skeleton = HandSkeleton(bone_lengths)
    scale = float(skeleton.bone_lengths.sum() / DEFAULT_BONE_LENGTHS.sum())
    joints = skeleton.rest_joints()
    a, b = joints[BONES[:, 0]], joints[BONES[:, 1]]
    radius = TEMPLATE_RADII.reshape(-1) * scale
    tip = np.arange(20) % 4 == 3
    # the fingertip keypoint is the end of the finger: the distal capsule stops short of it
    b = np.where(tip[:, None], b - radius[:, None] * (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True), b)
    return a, b, radius


def capsule_template(bone_lengths=None, spacing: float = SPACING_M) -> PointHand:
    """The template's surface for one subject's bone lengths (20,), points `spacing` apart."""
    skeleton = HandSkeleton(bone_lengths)
    a, b, radius = template_capsules(bone_lengths)
    points, normals, bones = [], [], []
    for k in range(20):
        p, n = capsule_surface(a[k], b[k], float(radius[k]), spacing)
        points.append(p)
        normals.append(n)
        bones.append(np.full(len(p), k))
    points, normals, bones = np.concatenate(points), np.concatenate(normals), np.concatenate(bones)
    # only the outer surface of the union: drop points buried in another bone's capsule
    d = capsule_distances(points, a, b, radius)
    d[np.arange(len(points)), bones] = np.inf
    keep = d.min(axis=1) > -1e-4
    return PointHand(skeleton, points[keep], bones[keep], 0.5 * spacing, normals_rest=normals[keep])
