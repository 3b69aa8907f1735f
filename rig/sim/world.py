"""The simulated capture cube: walls with an AprilTag 36h11 layout, textured background, a table
(its sides optionally tagged too).

The walls and the table's sides are textured planes. Their textures live in atlases with a mip
pyramid so that the renderer can sample them with trilinear filtering: tag edges come out
anti-aliased and their corners sub-pixel accurate at any distance. The layout of tags is written as tags.json for
calibration; tag corners are in OpenCV's order (top-left, top-right, bottom-right, bottom-left
as seen facing the tag).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from manus_core.fileio import write_atomic

TAG_CELLS = 8          # a 36h11 tag is 6x6 data cells inside a one-cell black border
MIP_LEVELS = 6         # level 5 is a 32x reduction: enough for 320x180 views of the far wall
TABLE_TAG_PITCH = 1.4  # tag pitch on the table's sides, in tag sides: room for the quiet zones


@dataclass(frozen=True)
class Face:
    """A wall seen from inside: `u` points right and `v` down for a viewer facing it."""

    name: str
    normal: np.ndarray  # unit, pointing into the cube
    origin: np.ndarray  # the wall point at texture (u, v) = (0, 0): its top-left corner
    u: np.ndarray
    v: np.ndarray
    width: float        # metres along u
    height: float       # metres along v


def _faces(edge: float) -> tuple[Face, ...]:
    h = edge / 2
    specs = [  # name, inward normal, u, v  (u x v = -normal, so tags are not mirrored)
        ("x+", (-1, 0, 0), (0, -1, 0), (0, 0, -1)),
        ("x-", (1, 0, 0), (0, 1, 0), (0, 0, -1)),
        ("y+", (0, -1, 0), (1, 0, 0), (0, 0, -1)),
        ("y-", (0, 1, 0), (-1, 0, 0), (0, 0, -1)),
        ("z+", (0, 0, -1), (1, 0, 0), (0, 1, 0)),    # ceiling
        ("z-", (0, 0, 1), (1, 0, 0), (0, -1, 0)),    # floor
    ]
    faces = []
    for name, n, u, v in specs:
        n, u, v = (np.array(a, dtype=np.float64) for a in (n, u, v))
        assert np.allclose(np.cross(u, v), -n)
        origin = -n * h - u * h - v * h
        faces.append(Face(name, n, origin, u, v, edge, edge))
    return tuple(faces)


def _even_texels(texels: float) -> int:
    """Whole texels to cover a side, an even count: a border then brings the tile to a multiple of
    the mip step (an odd count never gets there)."""
    return 2 * int(np.ceil(round(texels, 6) / 2))


def _padding(n: int) -> int:
    """Border texels round a tile of n (even) texels so that it starts on a whole texel at every mip level."""
    if n % 2:
        raise ValueError(f"a tile of {n} texels: an odd count cannot be padded to the mip step")
    step = 2 ** (MIP_LEVELS - 1)
    pad = step
    while (n + 2 * pad) % step:
        pad += 1
    return pad


@dataclass(frozen=True)
class Atlas:
    """Equal-sized face textures stacked vertically, each in a mirrored border, as a mip pyramid of
    uint8 BGR. Texel (x, y) of level 0 for face f at (u, v) texels is (pad[1] + u, f * stride + pad[0] + v)."""

    levels: tuple[np.ndarray, ...]
    pad: tuple[int, int]   # rows, columns
    stride: int            # rows from one face to the next at level 0

    @classmethod
    def of(cls, tiles: list[np.ndarray]) -> "Atlas":
        rows, cols = tiles[0].shape[:2]
        pad = (_padding(rows), _padding(cols))
        level = np.concatenate([cv2.copyMakeBorder(t, pad[0], pad[0], pad[1], pad[1], cv2.BORDER_REFLECT_101)
                                for t in tiles], axis=0)
        pyramid = [level]
        for _ in range(MIP_LEVELS - 1):
            level = cv2.resize(level, (level.shape[1] // 2, level.shape[0] // 2), interpolation=cv2.INTER_AREA)
            pyramid.append(level)
        for lv in pyramid:
            lv.setflags(write=False)
        return cls(tuple(pyramid), pad, rows + 2 * pad[0])


def _smooth_noise(rng: np.random.Generator, size: int, octaves: tuple[int, ...]) -> np.ndarray:
    """Coloured multi-scale noise in [0, 1], (size, size, 3), fast: upsampled random fields."""
    out = np.zeros((size, size, 3), np.float32)
    total = 0.0
    for cells in octaves:
        field = rng.random((cells, cells, 3), dtype=np.float32)
        out += cv2.resize(field, (size, size), interpolation=cv2.INTER_CUBIC) / cells ** 0.3
        total += 1 / cells ** 0.3
    out /= total
    lo, hi = np.percentile(out, [1, 99])
    return np.clip((out - lo) / (hi - lo), 0, 1)


@dataclass(frozen=True)
class World:
    """The static part of the cube. Metres; z up; origin at the cube's centre."""

    edge: float = 1.2
    tag_size: float = 0.24
    tags_per_wall: int = 3
    table_half: float = 0.2
    table_top: float = -0.15
    texel: float = 0.002  # metres per texel at mip level 0
    seed: int = 0
    table_tags: bool = False  # tags on the table's four sides: cameras beside it see little else

    def __post_init__(self) -> None:
        cell = self.tag_size / TAG_CELLS
        if abs(cell / self.texel - round(cell / self.texel)) > 1e-6:
            # A tag cell that is a whole number of texels keeps every tag edge on a texel edge.
            object.__setattr__(self, "texel", cell / max(1, round(cell / self.texel)))

    @cached_property
    def faces(self) -> tuple[Face, ...]:
        return _faces(self.edge)

    @property
    def table_lo(self) -> np.ndarray:
        return np.array([-self.table_half, -self.table_half, -self.edge / 2])

    @property
    def table_hi(self) -> np.ndarray:
        return np.array([self.table_half, self.table_half, self.table_top])

    @cached_property
    def table_faces(self) -> tuple[Face, ...]:
        """The table's four sides as seen from outside: the normal points away from the table."""
        height = self.table_top + self.edge / 2
        down = np.array([0.0, 0.0, -1.0])
        faces = []
        for name, n in (("table x+", (1, 0, 0)), ("table x-", (-1, 0, 0)), ("table y+", (0, 1, 0)),
                         ("table y-", (0, -1, 0))):
            n = np.array(n, dtype=np.float64)
            u = np.cross(n, down)   # u x v = -n, as on the walls
            centre = n * self.table_half + np.array([0.0, 0.0, self.table_top - height / 2])
            faces.append(Face(name, n, centre - u * self.table_half - down * height / 2, u, down,
                              2 * self.table_half, height))
        return tuple(faces)

    def _square(self, face: Face, cu: float, cv_: float) -> np.ndarray:
        """(4,3) world corners (TL, TR, BR, BL) of a tag centred at (cu, cv_) on a face, its
        top-left corner snapped onto a texel edge."""
        u0 = round((cu - self.tag_size / 2) / self.texel) * self.texel
        v0 = round((cv_ - self.tag_size / 2) / self.texel) * self.texel
        s = self.tag_size
        uv = np.array([[u0, v0], [u0 + s, v0], [u0 + s, v0 + s], [u0, v0 + s]])
        return face.origin + uv[:, :1] * face.u + uv[:, 1:] * face.v

    @cached_property
    def _placed(self) -> tuple[tuple[int, int, np.ndarray], ...]:
        """(id, face index, corners) of every tag; faces are the walls, then the table's sides."""
        n = self.tags_per_wall
        pitch = self.edge / n if n else 0.0
        placed = []
        for fi, face in enumerate(self.faces):
            for row in range(n):
                for col in range(n):
                    cu, cv_ = (col + 0.5) * pitch, (row + 0.5) * pitch
                    if face.name == "z-" and abs(cu - self.edge / 2) < self.table_half + self.tag_size and \
                            abs(cv_ - self.edge / 2) < self.table_half + self.tag_size:
                        continue
                    placed.append((len(placed), fi, self._square(face, cu, cv_)))
        if self.table_tags:
            for fi, face in enumerate(self.table_faces, start=len(self.faces)):
                cols = int(face.width / (TABLE_TAG_PITCH * self.tag_size))
                rows = int(face.height / (TABLE_TAG_PITCH * self.tag_size))
                for row in range(rows):
                    for col in range(cols):
                        cu, cv_ = (col + 0.5) * face.width / cols, (row + 0.5) * face.height / rows
                        placed.append((len(placed), fi, self._square(face, cu, cv_)))
        return tuple(placed)

    @cached_property
    def tags(self) -> dict[int, np.ndarray]:
        """Tag id -> (4,3) world corners (TL, TR, BR, BL). The floor's centre is under the table."""
        return {tag_id: corners for tag_id, _, corners in self._placed}

    def tag_faces(self) -> dict[int, int]:
        """Tag id -> index of the face it is on: the walls 0-5, the table's sides 6-9."""
        return {tag_id: fi for tag_id, fi, _ in self._placed}

    def tags_json(self) -> dict:
        return {"family": "tag36h11", "size": self.tag_size,
                "tags": {str(i): c.round(9).tolist() for i, c in self.tags.items()}}

    def write_tags(self, path) -> None:
        write_atomic(path, json.dumps(self.tags_json(), indent=1).encode())

    def _texture(self, fi: int, face: Face, background: np.ndarray) -> np.ndarray:
        """A face's uint8 texture: the background with this face's tags (and quiet zones) on it."""
        img = (background * 255).astype(np.uint8)
        dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
        cell_tx = int(round(self.tag_size / TAG_CELLS / self.texel))
        side = TAG_CELLS * cell_tx
        quiet = int(1.5 * cell_tx)  # white quiet zone the detector needs
        for tag_id, f, corners in self._placed:
            if f != fi:
                continue
            rel = corners[0] - face.origin
            c0, r0 = int(round(rel @ face.u / self.texel)), int(round(rel @ face.v / self.texel))
            img[r0 - quiet:r0 + side + quiet, c0 - quiet:c0 + side + quiet] = 235
            marker = dictionary.generateImageMarker(tag_id, side)
            img[r0:r0 + side, c0:c0 + side] = np.where(marker[..., None] > 0, 235, 20)
        return img

    @cached_property
    def atlas(self) -> Atlas:
        """The wall textures; a muted background so the black-and-white tags keep their contrast."""
        rng = np.random.default_rng(self.seed)
        T = _even_texels(self.edge / self.texel)
        return Atlas.of([self._texture(fi, face, 0.25 + 0.55 * _smooth_noise(rng, T, (6, 17, 45, 120)))
                         for fi, face in enumerate(self.faces)])

    @cached_property
    def table_atlas(self) -> Atlas:
        """The table's sides: its wood (unlit albedo; the renderer shades it) with their tags."""
        face = self.table_faces[0]
        cols, rows = (_even_texels(x / self.texel) for x in (face.width, face.height))
        v, u = (np.mgrid[:rows, :cols] + 0.5) * self.texel
        tiles = []
        for fi, face in enumerate(self.table_faces, start=len(self.faces)):
            points = face.origin + u.reshape(-1, 1) * face.u + v.reshape(-1, 1) * face.v
            tiles.append(self._texture(fi, face, self.table_albedo(points).reshape(rows, cols, 3)))
        return Atlas.of(tiles)

    def table_albedo(self, points: np.ndarray) -> np.ndarray:
        """Wood-like procedural colour of the table at world points (N,3) -> (N,3) BGR in [0, 1]."""
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        grain = 0.5 + 0.5 * np.sin(90 * x + 6 * np.sin(23 * y) + 40 * z)
        rings = 0.5 + 0.5 * np.sin(31 * y + 13 * np.sin(11 * x))
        shade = 0.75 + 0.15 * grain + 0.1 * rings
        base = np.array([0.28, 0.45, 0.62])  # BGR: a warm brown
        return (shade[:, None] * base).astype(np.float32)
