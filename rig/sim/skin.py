"""The simulated hand's skin: a triangle mesh of the rest flesh (anatomy.py), skinned to the bones.

The mesh is the zero level set of the rest SDF, meshed once per subject by marching cubes
(scikit-image). Each vertex starts on the bone of its nearest part (the palm slab on the
metacarpal of the nearest finger, all of which move with the palm); across every joint a window
along the child bone hands the vertex over from parent to child, and a few rounds of averaging
over the mesh's edges smooth every seam (the thenar against the palm, the webs between fingers).
Linear blend skinning then poses it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.ndimage import map_coordinates
from skimage.measure import marching_cubes

from manus_core.skeleton import REST_FRAMES

from .anatomy import RestHand

SPACING_M = 0.002         # marching-cubes grid: about 15k vertices for the average hand
_CHUNK = 1 << 17
_COARSE = 4
_SMOOTH_ROUNDS = 6
INFLUENCES = 4


@dataclass(frozen=True, eq=False)
class SkinnedMesh:
    """Rest vertices (V,3), faces (T,3) int32 (counter-clockwise from outside), rest normals (V,3),
    skinning weights (V,20) float32 (rows sum to 1), bone (V,) the heaviest bone of each vertex and
    part_kind (V,) the kind of flesh it lies on (anatomy.Part.kind, or "slab" for the palm)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    weights: np.ndarray
    bone: np.ndarray
    part_kind: np.ndarray


def _evaluate(rest: RestHand, lo: np.ndarray, spacing: float, shape: tuple[int, int, int]) -> np.ndarray:
    grid = lo + np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3) * spacing
    return np.concatenate([rest.sdf(grid[i:i + _CHUNK]) for i in range(0, len(grid), _CHUNK)]).reshape(shape)


def mesh_rest(rest: RestHand, spacing: float = SPACING_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (V,3), faces (T,3) int32, normals (V,3)) of the rest skin."""
    lo, hi = rest.bounds()
    shape = tuple(int(np.ceil((hi[k] - lo[k]) / spacing)) + 1 for k in range(3))
    # the field everywhere from a grid _COARSE times coarser, and exactly only near the surface:
    # the flesh is a thin shell in its box, and a full fine grid took 8 s
    coarse_shape = tuple(-(-n // _COARSE) + 1 for n in shape)
    coarse = _evaluate(rest, lo, spacing * _COARSE, coarse_shape)
    idx = np.stack(np.meshgrid(*[np.arange(n) / _COARSE for n in shape], indexing="ij"))
    volume = map_coordinates(coarse, idx, order=1)
    near = np.flatnonzero(np.abs(volume) < _COARSE * spacing)
    points = lo + np.stack(np.unravel_index(near, shape), axis=1) * spacing
    volume.ravel()[near] = np.concatenate([rest.sdf(points[i:i + _CHUNK]) for i in range(0, len(points), _CHUNK)])
    verts, faces, normals, _ = marching_cubes(volume, 0.0, spacing=(spacing,) * 3)
    verts = verts + lo
    normals = -normals     # scikit-image's point down the field; the skin's point out of the flesh
    faces = faces.astype(np.int32)
    tri = verts[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    if np.einsum("ij,ij->", face_n, normals[faces].sum(axis=1)) < 0:
        faces = faces[:, ::-1].copy()
    return verts, faces, normals


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


# (parent bone, child bone, joint) of every joint the skin bends at
_JOINTS = [(0, 1, 1), (1, 2, 2), (2, 3, 3)] + [(4 * f + k, 4 * f + k + 1, 4 * f + k + 1)
                                                for f in range(1, 5) for k in range(3)]


def nearest_parts(rest: RestHand, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(bone (V,), kind (V,)) of the part of the flesh nearest to each rest vertex; the palm slab
    is no part: its points go to the metacarpal of the finger nearest across."""
    parts = rest.part_distances(vertices)
    nearest = parts.argmin(axis=1)
    bone = np.array([p.bone for p in rest.parts])[nearest]
    kind = np.array([p.kind for p in rest.parts])[nearest]
    slab = rest.slab(vertices) < parts.min(axis=1)
    kind[slab] = "slab"
    mcp_x = rest.joints[[5, 9, 13, 17], 0]
    bone[slab] = 4 * (1 + np.abs(vertices[slab, 0, None] - mcp_x[None]).argmin(axis=1))
    return bone, kind


def skin_weights(rest: RestHand, vertices: np.ndarray, faces: np.ndarray, bone: np.ndarray) -> np.ndarray:
    """(V,20) float32 linear-blend weights of the rest vertices, starting from their parts' bones."""
    weights = np.zeros((len(vertices), 20))
    weights[np.arange(len(vertices)), bone] = 1.0
    for parent, child, joint in _JOINTS:
        f, k = child // 4, child % 4 - 1
        window = 0.7 * rest.half_width(f, k)[0]
        along = (vertices - rest.joints[joint]) @ REST_FRAMES[f][:, 1]
        sel = np.isin(bone, (parent, child)) & (np.abs(along) < window)
        w = _smoothstep((along[sel] + window) / (2 * window))
        weights[sel] = 0.0
        weights[sel, child], weights[sel, parent] = w, 1.0 - w
    # average over the mesh's edges: seams between parts of different bones become gradients
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    n = len(vertices)
    rows, cols = np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]]
    adj = sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    adj = adj + sparse.identity(n, format="csr")
    adj = sparse.diags(1.0 / np.asarray(adj.sum(axis=1)).ravel()) @ adj
    for _ in range(_SMOOTH_ROUNDS):
        weights = adj @ weights
    # keep the strongest influences only, as skinning on hardware does
    weak = np.argsort(weights, axis=1)[:, :-INFLUENCES]
    np.put_along_axis(weights, weak, 0.0, axis=1)
    return (weights / weights.sum(axis=1, keepdims=True)).astype(np.float32)


_MESHES: dict[str, SkinnedMesh] = {}


def skinned_mesh(rest: RestHand, spacing: float = SPACING_M) -> SkinnedMesh:
    """The skinned rest mesh of a hand; built once per shape and spacing in a process."""
    shape = rest.shape
    key = repr((shape.bone_lengths.tolist(), shape.finger_thickness, shape.pad_fullness, shape.palm_width,
                shape.palm_thickness, spacing))
    if key not in _MESHES:
        vertices, faces, normals = mesh_rest(rest, spacing)
        bone, kind = nearest_parts(rest, vertices)
        weights = skin_weights(rest, vertices, faces, bone)
        _MESHES[key] = SkinnedMesh(vertices, faces, normals, weights, weights.argmax(axis=1), kind)
    return _MESHES[key]


def blend(weights: np.ndarray, rot: np.ndarray, trans: np.ndarray, points: np.ndarray,
          normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Linear blend skinning: posed points (...,V,3) (and normals, renormalized) for bone motions
    rot (...,20,3,3), trans (...,20,3) of bone_transforms."""
    # each bone's motion as its three rotation columns and its translation: blending is then one
    # 2-D matrix product (V,20) @ (20, poses x 12), which BLAS does; numpy's broadcast matmul or a
    # plain einsum of the same took 15-40x longer
    lead = rot.shape[:-3]
    columns = np.swapaxes(rot, -1, -2).reshape(-1, 20, 9)
    affine = np.concatenate([columns, trans.reshape(-1, 20, 3)], axis=-1).astype(np.float32)   # (L,20,12)
    flat = weights @ affine.transpose(1, 0, 2).reshape(20, -1)                                # (V, L*12)
    blended = flat.reshape(len(weights), -1, 12).transpose(1, 0, 2).reshape(*lead, len(weights), 12)
    p = points.astype(np.float32)
    posed = (blended[..., 0:3] * p[:, 0:1] + blended[..., 3:6] * p[:, 1:2] + blended[..., 6:9] * p[:, 2:3]
             + blended[..., 9:12])
    if normals is None:
        return posed.astype(np.float64), None
    n = normals.astype(np.float32)
    n = blended[..., 0:3] * n[:, 0:1] + blended[..., 3:6] * n[:, 1:2] + blended[..., 6:9] * n[:, 2:3]
    return posed.astype(np.float64), n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
