"""Triangle meshes of the simulated scene as the ray caster takes them.

The hand is a skinned mesh posed per instant and the objects are rigid meshes moved by their pose;
both reach the renderer as a PosedMesh in world coordinates with what shading needs per vertex.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class PosedMesh:
    """A mesh in world coordinates: vertices (V,3) float64, faces (T,3) int32 (counter-clockwise
    seen from outside), unit normals (V,3), albedo (V,3) float32 RGB in [0, 1] and label (V,) uint8
    (manus_core.ground_truth's LABEL_* of what the vertex is: skin or paint)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    label: np.ndarray


# the icosahedron: 12 vertices (0, +-1, +-phi) cyclically, 20 faces counter-clockwise from outside
_PHI = (1 + 5 ** 0.5) / 2
_ICOSAHEDRON_VERTICES = np.array([
    [-1, _PHI, 0], [1, _PHI, 0], [-1, -_PHI, 0], [1, -_PHI, 0], [0, -1, _PHI], [0, 1, _PHI],
    [0, -1, -_PHI], [0, 1, -_PHI], [_PHI, 0, -1], [_PHI, 0, 1], [-_PHI, 0, -1], [-_PHI, 0, 1]])
_ICOSAHEDRON_FACES = np.array([
    [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
    [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
    [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit sphere as vertices (V,3) float64 and faces (T,3) int32 (20 * 4^subdivisions,
    counter-clockwise seen from outside): the icosahedron's triangles split in four, again and
    again, each new vertex pushed out onto the sphere. Its triangles are near-equal in size, so
    the facets' distance from the sphere is near-uniform, unlike a latitude-longitude grid's."""
    vertices = _ICOSAHEDRON_VERTICES / np.linalg.norm(_ICOSAHEDRON_VERTICES, axis=1, keepdims=True)
    faces = _ICOSAHEDRON_FACES
    for _ in range(subdivisions):
        edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]], axis=2).reshape(-1, 2)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        middle = vertices[unique].sum(axis=1)
        vertices = np.concatenate([vertices, middle / np.linalg.norm(middle, axis=1, keepdims=True)])
        ab, bc, ca = (len(vertices) - len(unique) + inverse.reshape(-1, 3)).T
        a, b, c = faces.T
        faces = np.concatenate([np.stack(f, axis=1) for f in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return vertices, faces.astype(np.int32)
