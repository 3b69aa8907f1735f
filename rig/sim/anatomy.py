"""The simulated hand's flesh in its rest pose, as a signed distance field of anatomical parts.

Not the capsule template's class on purpose (docs/simulation.md): finger cross-sections are
ellipses, flatter on the dorsal side than on the palmar one and tapering along each phalanx;
every phalanx carries a palmar pad and each fingertip a fuller one; the palm is a rounded slab
with a hollow centre, thenar and hypothenar eminences and the distal palmar pads under the
knuckles; knuckle bumps sit on the back of the MCP and PIP joints; flexion creases are shallow
grooves. Parts join by smooth unions (polynomial smooth minimum), so joints blend.

Each part belongs to one bone (manus_core.skeleton numbering: bone b runs from PARENTS[b + 1] to
joint b + 1): skinning (skin.py) starts from the part nearest to each surface point.
Rest frame as in manus_core.skeleton: wrist at the origin, fingers along +y, palm facing -z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from manus_core.skeleton import REST_FRAMES, HandSkeleton

# Half-widths (m) of the moving segments of the average hand at their proximal end: thumb
# metacarpal, proximal, distal; fingers proximal, middle, distal phalanx. They taper by TAPER to
# their distal end. The dorsal and palmar half-heights are fractions of the width: a finger is
# wider than deep and its back flatter than its pulp.
_HALF_WIDTH = np.array([
    [0.0115, 0.0100, 0.0090],
    [0.0086, 0.0078, 0.0071],
    [0.0088, 0.0080, 0.0072],
    [0.0083, 0.0076, 0.0069],
    [0.0074, 0.0068, 0.0062],
])
TAPER = 0.9
DORSAL, PALMAR = 0.66, 0.80
# Pads: semi-height as a fraction of the palmar half-height, for a pad fullness of 1; a pad
# fullness above 1 / _TIP_PAD would make a fingertip pad deeper than its finger.
_PAD, _TIP_PAD = 0.36, 0.46
MAX_PAD_FULLNESS = 1.0 / _TIP_PAD
_CREASE_DEPTH, _CREASE_WIDTH = 0.0006, 0.0012
SMOOTH_FINGER, SMOOTH_PALM = 0.0025, 0.005


@dataclass(frozen=True)
class HandShape:
    """A subject's hand: bone lengths (20,) (m) and flesh relative to the average hand."""

    name: str
    bone_lengths: np.ndarray
    finger_thickness: float = 1.0
    pad_fullness: float = 1.0
    palm_width: float = 1.0
    palm_thickness: float = 1.0
    skin_rgb: tuple[float, float, float] = (0.86, 0.63, 0.52)
    nail_rgb: tuple[float, float, float] = (0.93, 0.76, 0.74)


def smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum: the union of two solids with a fillet of about k."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _ellipsoid(q: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Approximate signed distance (N,) of local points q (N,3) to an ellipsoid of semi-axes
    (...,3): exact on the surface and of the right sign everywhere, which meshing needs."""
    a = q / axes
    b = a / axes
    k0 = np.sqrt(np.einsum("...i,...i->...", a, a))
    k1 = np.sqrt(np.einsum("...i,...i->...", b, b))
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


@dataclass(frozen=True)
class Part:
    """One piece of flesh: its bone, its frame (origin (3,), axes (3,3) as columns) and its
    kind; `sdf` gives its signed distance at rest points."""

    bone: int
    origin: np.ndarray
    axes: np.ndarray
    kind: str                   # ellipsoid, phalanx or forearm
    size: np.ndarray            # kind-specific dimensions
    smooth: float

    def local(self, p: np.ndarray) -> np.ndarray:
        return (p - self.origin) @ self.axes

    def sdf(self, p: np.ndarray) -> np.ndarray:
        q = self.local(p)
        if self.kind == "ellipsoid":
            return _ellipsoid(q, self.size)
        if self.kind == "phalanx":
            return _phalanx(q, *self.size)
        return _forearm(q, *self.size)


def _phalanx(q: np.ndarray, length: float, w0: float, w1: float, cap: float) -> np.ndarray:
    """A tapering finger segment along local +y from 0 to `length`: elliptical cross-sections,
    half-width w, dorsal half-height DORSAL w (local +z) and palmar PALMAR w, closed by
    half-ellipsoid caps `cap` long."""
    s = np.clip(q[:, 1] / length, 0.0, 1.0)
    w = w0 + (w1 - w0) * s
    h = np.where(q[:, 2] > 0, DORSAL, PALMAR) * w
    axial = q[:, 1] - s * length
    local = np.stack([q[:, 0], axial, q[:, 2]], axis=1)
    return _ellipsoid(local, np.stack([w, np.full_like(w, cap), h], axis=1))


def _forearm(q: np.ndarray, length: float, w: float, h: float) -> np.ndarray:
    """The wrist: an elliptical cylinder from local y = 0 back to -length, both ends rounded."""
    axial = np.where(q[:, 1] > 0, q[:, 1], np.maximum(-q[:, 1] - length, 0.0))
    return _ellipsoid(np.stack([q[:, 0], axial, q[:, 2]], axis=1), np.array([w, w, h]))


class RestHand:
    """The rest-pose flesh of one HandShape: parts, the palm slab, and their union's SDF."""

    def __init__(self, shape: HandShape) -> None:
        self.shape = shape
        self.skeleton = HandSkeleton(shape.bone_lengths)
        self.joints = self.skeleton.rest_joints()
        self.scale = float(np.linalg.norm(self.joints[9]) / 0.0827)   # wrist to middle MCP
        self.parts: list[Part] = []
        self._fingers()
        self._palm()

    # -- fingers --------------------------------------------------------------------------
    def half_width(self, finger: int, k: int) -> tuple[float, float]:
        """(proximal, distal) half-width of moving segment k (0..2) of a finger."""
        w = _HALF_WIDTH[finger, k] * self.scale * self.shape.finger_thickness
        return w, w * TAPER

    def _fingers(self) -> None:
        j, pads = self.joints, self.shape.pad_fullness
        for f in range(5):
            axes = REST_FRAMES[f]
            for k in range(3):
                bone = 4 * f + k + 1
                a, b = j[bone], j[bone + 1]
                length = float(np.linalg.norm(b - a))
                w0, w1 = self.half_width(f, k)
                tip = k == 2
                cap = 0.9 * w1 if tip else 0.6 * w1
                # the fingertip keypoint is the end of the finger: the tip cap ends on it
                body = length - cap if tip else length
                self.parts.append(Part(bone, a, axes, "phalanx", np.array([body, w0, w1, cap]), SMOOTH_FINGER))
                wm = 0.5 * (w0 + w1)
                ratio = _TIP_PAD if tip else _PAD
                pad_h = ratio * pads * PALMAR * wm
                centre_s = 0.62 if tip else 0.5
                depth = PALMAR * wm - 0.35 * pad_h
                centre = a + axes @ np.array([0.0, centre_s * length, -depth])
                size = np.array([0.8 * wm, (0.36 if tip else 0.3) * length, pad_h + 0.35 * pad_h])
                self.parts.append(Part(bone, centre, axes, "ellipsoid", size, SMOOTH_FINGER))
            # knuckle bumps: the heads of the metacarpal (fingers) and the proximal phalanx
            w_prox = self.half_width(f, 0)[0]
            if f > 0:
                centre = j[4 * f + 1] + axes @ np.array([0.0, -0.002, 0.0070 * self.scale])
                self.parts.append(Part(4 * f, centre, axes, "ellipsoid",
                                       np.array([0.7 * w_prox, 0.007, 0.0035]) * np.array([1, self.scale, 1]),
                                       SMOOTH_FINGER))
            w_mid = self.half_width(f, 1)[0]
            centre = j[4 * f + 2] + axes @ np.array([0.0, -0.001, DORSAL * w_mid + 0.0004])
            self.parts.append(Part(4 * f + 1, centre, axes, "ellipsoid",
                                   np.array([0.6 * w_mid, 0.0045, 0.0015]), SMOOTH_FINGER))

    # -- palm -----------------------------------------------------------------------------
    def _palm(self) -> None:
        j, s = self.joints, self.scale
        pw, pt, pads = self.shape.palm_width, self.shape.palm_thickness, self.shape.pad_fullness
        mcp = j[[5, 9, 13, 17]]
        cx = float(mcp[:, 0].mean())
        self.palm_z = -0.0035 * s * pt                 # the slab's mid-plane
        self.palm_half = 0.0125 * s * pt               # half its thickness
        self.palm_round = 0.0065 * s * pt
        outer = np.array([[-0.027, 0.000], [0.025, 0.000], [0.035, 0.040], [-0.034, 0.050]]) * s
        outer[:, 0] = cx + (outer[:, 0] - cx) * pw
        rim = np.concatenate([
            mcp[:, :2] + [0.0, 0.005 * s],
            [mcp[3, :2] + np.array([0.007 * pw, -0.002]) * s, mcp[0, :2] + np.array([-0.008 * pw, -0.004]) * s],
            outer])
        hull = ConvexHull(rim)
        self.palm_polygon = rim[hull.vertices]       # counter-clockwise
        palmar = self.palm_z - self.palm_half
        ident = np.eye(3)
        # the hollow of the palm: carved out of the slab's palmar face
        self.hollow = Part(8, np.array([cx, 0.047 * s, palmar - 0.0042 * s]), ident, "ellipsoid",
                           np.array([0.019 * pw, 0.021, 0.0070]) * s, SMOOTH_PALM)
        # the wrist, as deep as the palm and as wide as its heel, running back along -y
        self.parts.append(Part(8, np.array([cx, 0.012 * s, self.palm_z]), ident, "forearm",
                               np.array([0.045 * s, 0.026 * s * pw, 0.0175 * s * pt]), SMOOTH_PALM))
        fl = 0.75 + 0.25 * pads
        # thenar eminence: the flesh of the thumb's metacarpal on the palm side, moving with it
        t_axes = REST_FRAMES[0]
        centre = j[1] + 0.45 * (j[2] - j[1]) + t_axes @ np.array([0.003, 0.0, -0.0055]) * s
        self.parts.append(Part(1, centre, t_axes, "ellipsoid", np.array([0.0135, 0.021, 0.0105 * fl]) * s,
                               SMOOTH_PALM))
        # hypothenar eminence along the ulnar edge of the palm
        edge = float(self.palm_polygon[:, 0].max())
        self.parts.append(Part(16, np.array([edge - 0.0095 * s, 0.033 * s, palmar + 0.0055 * s]), ident,
                               "ellipsoid", np.array([0.0105, 0.025, 0.0075 * fl]) * s, SMOOTH_PALM))
        # the distal palmar pads under the knuckles
        for f in range(1, 5):
            centre = j[4 * f + 1] + np.array([0.0, -0.010 * s, palmar + 0.0035 * s - j[4 * f + 1, 2]])
            self.parts.append(Part(4 * f, centre, ident, "ellipsoid",
                                   np.array([0.0085, 0.0085, 0.0048 * fl]) * s, SMOOTH_PALM))

    def slab(self, p: np.ndarray) -> np.ndarray:
        """The palm: the convex polygon extruded through the palm's thickness, edges rounded."""
        poly = self.palm_polygon
        a, b = poly, np.roll(poly, -1, axis=0)
        e = b - a
        rel = p[:, None, :2] - a[None]
        t = np.clip(np.einsum("nek,ek->ne", rel, e) / np.einsum("ek,ek->e", e, e), 0.0, 1.0)
        d_edge = np.linalg.norm(rel - t[..., None] * e[None], axis=2).min(axis=1)
        # counter-clockwise: inside is to the left of every edge
        inside = np.all(e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0] >= 0, axis=1)
        d2 = np.where(inside, -d_edge, d_edge) + self.palm_round
        dz = np.abs(p[:, 2] - self.palm_z) - self.palm_half + self.palm_round
        outside = np.hypot(np.maximum(d2, 0.0), np.maximum(dz, 0.0))
        return outside + np.minimum(np.maximum(d2, dz), 0.0) - self.palm_round

    def part_distances(self, p: np.ndarray) -> np.ndarray:
        """(N, parts) signed distance of every part at rest points p (N,3)."""
        out = np.empty((len(p), len(self.parts)))
        for i, part in enumerate(self.parts):
            out[:, i] = part.sdf(p)
        return out

    def sdf(self, p: np.ndarray, parts: np.ndarray | None = None) -> np.ndarray:
        """Signed distance (N,) of the hand's rest skin at points p (N,3); pass part_distances(p)
        when they are at hand."""
        parts = self.part_distances(p) if parts is None else parts
        d = self.slab(p)
        for i, part in enumerate(self.parts):
            d = smin(d, parts[:, i], part.smooth)
        # the hollow of the palm, subtracted smoothly (a smooth maximum with its inside out)
        d = -smin(-d, self.hollow.sdf(p), SMOOTH_PALM)
        return d + self._creases(p)

    def crease_depth(self, p: np.ndarray) -> np.ndarray:
        """How deep in a flexion crease each point (N,) lies, 1 at a crease's floor."""
        return self._creases(p) / _CREASE_DEPTH

    def _creases(self, p: np.ndarray) -> np.ndarray:
        """Shallow grooves across the palmar side of the PIP and DIP joints and the base of each
        finger: added distance (N,) that pushes the surface in."""
        out = np.zeros(len(p))
        for f in range(5):
            axes = REST_FRAMES[f]
            for joint, k in ((4 * f + 1, 0), (4 * f + 2, 1), (4 * f + 3, 2)):
                q = (p - self.joints[joint]) @ axes
                w = self.half_width(f, k)[0]
                across = np.exp(-(q[:, 1] / _CREASE_WIDTH) ** 2)
                palmar = np.clip(-q[:, 2] / (0.3 * w), 0.0, 1.0)
                near = np.clip(1.5 - np.hypot(q[:, 0], q[:, 2]) / (1.2 * w), 0.0, 1.0)
                out += _CREASE_DEPTH * across * palmar * near
        return out

    def bounds(self, margin: float = 0.008) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) of a box that holds the rest hand: every part's and the palm's extent."""
        reach = np.array([np.max(p.size[1:]) + (p.size[0] if p.kind == "forearm" else 0.0)
                          if p.kind != "ellipsoid" else np.max(p.size) for p in self.parts])
        origins = np.array([p.origin for p in self.parts])
        pts = np.concatenate([self.joints, origins - reach[:, None], origins + reach[:, None],
                              np.c_[self.palm_polygon, np.full(len(self.palm_polygon), self.palm_z)]])
        return pts.min(axis=0) - margin, pts.max(axis=0) + margin
