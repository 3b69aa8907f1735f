"""What happens in front of the simulated cameras during each kind of take.

A Motion is a smooth function of continuous time: the renderer samples it at each camera's own
exposure time, so there is no frame quantization. Poses are keyframes joined by quintic easing
(zero velocity and acceleration at every keyframe), linear in the 26 joint angles; a keyframe
repeated is a hold.

Kinds: calibration (empty cube), hand (an articulation routine through ~20 poses), object (the
object still on the table), grasp (approach, close until touching, hold, release, retreat) and
canonical (the flat open hand after the grasp, palm up towards the cameras, carrying the paint).

Grasp contact is found, not scripted: the hand descends onto the object until the palm is
PALM_GAP_M away (bisection on the descent), then each finger closes in three stages (all
flexions, then PIP+DIP, then DIP: the finger wraps) until the skin of its moving segments presses
PRESS_DEPTH_M into the object or reaches the table (bisection on a per-finger closing parameter,
all fingers in one vectorized batch). Rendered, the pressed skin flattens against the object
(hand.press). Paint: the skin that touches a painted object (hand.TOUCH_M) turns green and
stays green.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from rig.sim import shapes
from rig.sim.hand import HandModel
from rig.sim.objects import SimObject

KINDS = ("calibration", "hand", "object", "grasp", "canonical")

# a grasping finger's pulp gives 1-3 mm under a light grip; the skin flattens over that depth
PRESS_DEPTH_M = 0.0015
PALM_GAP_M = 0.0025            # palm stops a few mm from the object
_APPROACH_GAP_M = 0.002        # pre-shaped fingers keep clear of the object during the descent
_APPROACH_HEIGHT_M = 0.12      # descent length
_PAINT_SAMPLES = 1500          # path samples of the accumulated contact, independent of duration
_TABLE_HALF = 0.2              # half extent of the table top in x and y
_TABLE_CLEARANCE_M = PRESS_DEPTH_M + 0.001   # fingers that reach the table stop 1 mm above it
_GRASP_POINT = 0.7             # hand point over the object: this far from the wrist to the middle MCP

Pose = shapes.Pose
SdfFn = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class SceneState:
    """The scene at one instant: hand_angles (26,) or None, object_pose (R, t) or None, and
    paint (P,) bool on the hand surface points (None when there is no hand)."""

    hand_angles: np.ndarray | None
    object_pose: Pose | None
    paint: np.ndarray | None


class _Keyframes:
    """Values (K,D) at times (K,) joined by quintic smoothstep; constant outside the range."""

    def __init__(self, times: np.ndarray, values: np.ndarray) -> None:
        self.times = np.asarray(times, dtype=np.float64)
        self.values = np.asarray(values, dtype=np.float64)
        if np.any(np.diff(self.times) <= 0):
            raise ValueError("keyframe times must increase")

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.clip(np.asarray(t, dtype=np.float64), self.times[0], self.times[-1])
        i = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2)
        u = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        w = u * u * u * (10.0 + u * (-15.0 + 6.0 * u))
        return self.values[i] + w[..., None] * (self.values[i + 1] - self.values[i])


def _rotvec(r: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(r).as_rotvec()


def _hand_pose(rotation: np.ndarray, wrist: np.ndarray, fingers: np.ndarray) -> np.ndarray:
    return np.concatenate([_rotvec(rotation), wrist, np.asarray(fingers, dtype=np.float64).ravel()])


class Motion:
    """A take's scene as a function of time. Build with make_motion.

    Attributes: kind, duration_s, hand (HandModel or None), obj (SimObject or None),
    keyframe_times (K,) and keyframe_angles (K,26) of the hand (empty without a hand).
    """

    def __init__(self, kind: str, duration_s: float, hand: HandModel | None, obj: SimObject | None,
                 object_pose: Pose | None, keyframes: _Keyframes | None,
                 paint_source: "Motion | None" = None, grasp: tuple | None = None) -> None:
        self.kind = kind
        self.duration_s = float(duration_s)
        self.hand = hand
        self.obj = obj
        self._object_pose = object_pose
        self._keys = keyframes
        self._paint_source = paint_source
        self._grasp = grasp      # what the grasp was planned from, for its paint

    @property
    def has_hand(self) -> bool:
        return self._keys is not None

    @property
    def has_object(self) -> bool:
        return self._object_pose is not None

    @property
    def keyframe_times(self) -> np.ndarray:
        return self._keys.times if self._keys is not None else np.zeros(0)

    @property
    def keyframe_angles(self) -> np.ndarray:
        return self._keys.values if self._keys is not None else np.zeros((0, 26))

    def hand_angles(self, t: np.ndarray) -> np.ndarray | None:
        """Joint angles (T,26) at times t (T,) in seconds, or None without a hand."""
        return None if self._keys is None else self._keys(np.atleast_1d(t))

    def object_poses(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Object poses (R (T,3,3), t (T,3)) at times t (T,), or None without an object."""
        if self._object_pose is None:
            return None
        n = len(np.atleast_1d(t))
        r, p = self._object_pose
        return np.broadcast_to(r, (n, 3, 3)).copy(), np.broadcast_to(p, (n, 3)).copy()

    def state(self, t_s: float) -> SceneState:
        """The scene at time t_s (seconds from the start of the take)."""
        angles = None if self._keys is None else self._keys(np.array([t_s]))[0]
        paint = None
        if angles is not None:
            paint = np.zeros(self.hand.n_points, dtype=bool)
            if self.obj is not None and self.obj.painted:
                paint = self.contact_accumulated(t_s)
        return SceneState(angles, self._object_pose, paint)

    def _object_sdf(self) -> SdfFn:
        return lambda x: self.obj.sdf(x, self._object_pose)

    def contact_instant(self, t: np.ndarray) -> np.ndarray:
        """(T,P) bool: hand surface points that touch the object at each time."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        out = np.zeros((len(t), self.hand.n_points if self.hand else 0), dtype=bool)
        if self._keys is None or self._object_pose is None:
            return out
        frame, point = self.hand.contact(self._keys(t), self.obj, self._object_pose)
        out[frame, point] = True
        return out

    @property
    def first_contact_s(self) -> np.ndarray:
        """(P,) the first time each hand point touched the object in a grasp (inf: never)."""
        if self._grasp is None:
            return np.full(self.hand.n_points if self.hand else 0, np.inf)
        return _first_touch(*self._grasp) * self.duration_s

    def contact_accumulated(self, t_end: float | None = None) -> np.ndarray:
        """(P,) bool: hand points that have touched the object up to t_end
        (default: the whole take). A canonical take returns the paint of its grasp."""
        if self._paint_source is not None:
            return self._paint_source.contact_accumulated()
        if self.hand is None:
            return np.zeros(0, dtype=bool)
        t_end = self.duration_s if t_end is None else float(t_end)
        return (self.first_contact_s <= t_end) | self.contact_instant(np.array([t_end]))[0]


# ----------------------------------------------------------------------------- hand routine

def _fingers(thumb=(0, 0, 0, 0), index=(0, 0, 0, 0), middle=(0, 0, 0, 0), ring=(0, 0, 0, 0),
             pinky=(0, 0, 0, 0)) -> np.ndarray:
    """Finger DOFs (20,): per finger (MCP flexion, MCP abduction, PIP flexion, DIP flexion)."""
    return np.array([thumb, index, middle, ring, pinky], dtype=np.float64).ravel()


_CURLED = (1.4, 0.0, 1.5, 1.0)
_FIST_THUMB = (0.9, 0.2, 0.7, 0.6)
# The articulation routine: (name, finger DOFs), each a distinct pose.
HAND_POSES: tuple[tuple[str, np.ndarray], ...] = (
    ("open", _fingers()),
    ("fist", _fingers(_FIST_THUMB, _CURLED, _CURLED, _CURLED, _CURLED)),
    ("spread", _fingers((-0.1, -0.3, 0.0, -0.1), (-0.1, 0.38, 0, 0), (-0.1, 0.1, 0, 0),
                        (-0.1, -0.25, 0, 0), (-0.1, -0.45, 0, 0))),
    ("pinch", _fingers((0.75, 0.3, 0.35, 0.3), (0.75, 0.0, 0.65, 0.35), (0.2, 0, 0.2, 0.1),
                       (0.2, 0, 0.2, 0.1), (0.25, 0, 0.2, 0.1))),
    ("index_flex", _fingers(index=(1.3, 0, 1.4, 1.0))),
    ("middle_flex", _fingers(middle=(1.3, 0, 1.4, 1.0))),
    ("ring_flex", _fingers(ring=(1.3, 0, 1.4, 1.0))),
    ("pinky_flex", _fingers(pinky=(1.3, 0, 1.4, 1.0))),
    ("thumb_flex", _fingers(thumb=(1.2, 0.0, 0.8, 0.8))),
    ("thumb_to_pinky", _fingers((1.35, 0.3, 0.5, 0.3), pinky=(0.9, 0.0, 0.7, 0.4))),
    ("point", _fingers(_FIST_THUMB, (0, 0.1, 0, 0), _CURLED, _CURLED, _CURLED)),
    ("peace", _fingers(_FIST_THUMB, (0, 0.35, 0, 0), (0, -0.25, 0, 0), _CURLED, _CURLED)),
    ("ok", _fingers((0.8, 0.25, 0.3, 0.4), (0.95, 0.0, 0.9, 0.6), (0.05, 0, 0.05, 0),
                    (0.05, -0.1, 0.05, 0), (0.05, -0.25, 0.05, 0))),
    ("claw", _fingers((0.3, 0.1, 0.6, 0.7), (0.1, 0, 1.3, 1.1), (0.1, 0, 1.3, 1.1),
                      (0.1, 0, 1.3, 1.1), (0.1, 0, 1.3, 1.1))),
    ("hook", _fingers((0.0, -0.2, 0.0, 0.0), (1.45, 0, 0, 0), (1.45, 0, 0, 0), (1.45, 0, 0, 0),
                      (1.45, 0, 0, 0))),
    ("half_closed", _fingers((0.5, 0.15, 0.3, 0.3), (0.7, 0, 0.7, 0.5), (0.7, 0, 0.7, 0.5),
                             (0.7, 0, 0.7, 0.5), (0.7, 0, 0.7, 0.5))),
    ("thumbs_up", _fingers((-0.1, -0.2, -0.1, -0.1), _CURLED, _CURLED, _CURLED, _CURLED)),
    ("tripod", _fingers((0.9, 0.3, 0.3, 0.3), (0.8, -0.1, 0.6, 0.3), (0.8, 0.15, 0.6, 0.3),
                        (1.2, 0, 1.3, 0.9), (1.2, 0, 1.3, 0.9))),
    ("horns", _fingers(_FIST_THUMB, (0, 0.3, 0, 0), _CURLED, _CURLED, (0, -0.4, 0, 0))),
    ("hyperextend", _fingers((-0.1, -0.3, -0.1, -0.1), (-0.1, 0.2, -0.1, -0.1), (-0.1, 0, -0.1, -0.1),
                             (-0.1, -0.1, -0.1, -0.1), (-0.1, -0.3, -0.1, -0.1))),
    ("cascade", _fingers((0.3, 0.1, 0.2, 0.2), (0.2, 0, 0.3, 0.2), (0.5, 0, 0.6, 0.4),
                         (0.8, 0, 0.9, 0.6), (1.1, 0, 1.2, 0.8))),
)
_HOLD_FRACTION = 0.35   # of each pose's slot; the rest is the transition to the next pose


def _hand_routine(hand: HandModel, duration_s: float, seed: int) -> _Keyframes:
    """Every pose of HAND_POSES, held, under a varied global orientation near the cube centre.

    Fingers point up with the palm towards +y (a quarter turn about x); the hand turns slowly
    about the vertical (up to 1.2 rad either way over the routine) and tilts by up to 0.35 rad
    per pose, so the cameras see it from all sides while rotation vectors stay far from pi.
    """
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0.0, 2 * np.pi)
    base = Rotation.from_rotvec([np.pi / 2, 0.0, 0.0])
    n = len(HAND_POSES)
    slot = duration_s / n
    times, values = [], []
    for i, (_, fingers) in enumerate(HAND_POSES):
        yaw = 1.2 * np.sin(0.6 * i + phase)
        tilt = rng.uniform(-0.35, 0.35, size=2)
        rot = Rotation.from_rotvec([tilt[0], tilt[1], 0.0]) * Rotation.from_rotvec([0, 0, yaw]) * base
        wrist = np.array([rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), rng.uniform(-0.06, -0.03)])
        pose = hand.skeleton.clamp(_hand_pose(rot.as_matrix(), wrist, fingers))
        times += [i * slot, i * slot + _HOLD_FRACTION * slot]
        values += [pose, pose]
    times[-1] = duration_s
    return _Keyframes(np.array(times), np.array(values))


# ----------------------------------------------------------------------------- grasp

# Finger pre-shape and fully closed targets (MCP flexion, abduction, PIP, DIP); thumb first.
_PRESHAPE = _fingers((-0.1, -0.3, 0.0, 0.0), (-0.1, 0.08, 0.0, 0.0), (-0.1, 0.0, 0.0, 0.0),
                     (-0.1, -0.05, 0.0, 0.0), (-0.1, -0.12, 0.0, 0.0)).reshape(5, 4)
# Closing stages: (finger DOF columns that move, finger bones (1..3) checked for contact, the
# targets the moving columns head for). The MCP leads so that fingers wrap with their pads
# rather than poke with their tips; then PIP+DIP, then DIP alone close onto the surface.
_STAGES = (
    ((0, 1, 2, 3), (1, 2, 3), _fingers((1.4, 0.3, 0.6, 0.5), (1.5, 0.08, 0.9, 0.6), (1.5, 0.0, 0.9, 0.6),
                                       (1.5, -0.05, 0.9, 0.6), (1.5, -0.12, 0.9, 0.6)).reshape(5, 4)),
    ((2, 3), (2, 3), _fingers((0, 0, 1.0, 0.9), *[(0, 0, 1.5, 1.0)] * 4).reshape(5, 4)),
    ((3,), (3,), _fingers((0, 0, 0, 1.2), *[(0, 0, 0, 1.2)] * 4).reshape(5, 4)),
)
# Timeline of the grasp as fractions of the take: start high, descended, after each closing
# stage, end of hold, then the same path backwards.
_GRASP_TIMELINE = (0.0, 0.22, 0.34, 0.40, 0.45, 0.60, 0.65, 0.70, 0.80, 1.0)


def _first_crossing(f: Callable[[np.ndarray], np.ndarray], n_items: int, grid: int = 128,
                    iters: int = 30) -> np.ndarray:
    """Per item, the s in [0, 1] where f(s) first drops below 0, approached from above (f maps
    s (G, n_items) to (G, n_items)); 1 where it never does. A grid finds the first crossing,
    so a later, deeper one is never taken; bisection refines it."""
    s_grid = np.linspace(0.0, 1.0, grid + 1)
    below = f(np.repeat(s_grid[:, None], n_items, axis=1)) < 0
    first = below.argmax(axis=0)
    lo, hi = s_grid[np.maximum(first - 1, 0)], s_grid[first]
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        ok = f(mid[None])[0] >= 0
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    return np.where(~below.any(axis=0), 1.0, np.where(first == 0, 0.0, lo))


def _closing_clearance(hand: HandModel, placed: np.ndarray, start: np.ndarray, cols: tuple[int, ...],
                       bones: tuple[int, ...], target: np.ndarray, sdf: SdfFn) -> Callable[[np.ndarray], np.ndarray]:
    """Clearance (G,5) of each finger's checked segments, plus the allowed press depth, when
    its DOF columns `cols` have gone a fraction s (G,5) of the way from `start` to `target`."""
    groups = [np.array([4 * f + k for k in bones]) for f in range(5)]

    def clearance(s: np.ndarray) -> np.ndarray:
        g = s.shape[0]
        fingers = np.repeat(start[None], g, axis=0)
        for c in cols:
            fingers[:, :, c] += s * (target[:, c] - start[:, c])
        angles = np.concatenate([np.repeat(placed[None, :6], g, axis=0), fingers.reshape(g, 20)], axis=1)
        return hand.clearance(angles, groups, sdf) + PRESS_DEPTH_M

    return clearance


@functools.lru_cache(maxsize=16)
def _grasp_poses(hand: HandModel, obj: SimObject, seed: int, table_top_z: float) -> np.ndarray:
    """The grasp's keyframe poses (K,26) on _GRASP_TIMELINE, planned once per process: a canonical
    take plans its grasp again for the paint, and the timeline only scales with the duration."""
    pose = obj.resting_pose(table_top_z)
    rng = np.random.default_rng(seed)
    table_lo = np.array([-_TABLE_HALF, -_TABLE_HALF, -1.0])
    table_hi = np.array([_TABLE_HALF, _TABLE_HALF, table_top_z])

    def scene_sdf(x: np.ndarray) -> np.ndarray:
        flat = x.reshape(-1, 3)
        table = shapes.sdf_box(flat, table_lo, table_hi) - _TABLE_CLEARANCE_M
        return np.minimum(obj.sdf(flat, pose), table).reshape(x.shape[:-1])

    # Palm down over the object, fingers at a seeded heading, pitched down so the wrist clears.
    yaw = rng.uniform(-2.5, 2.5)
    pitch = rng.uniform(0.1, 0.3)
    rot = (Rotation.from_rotvec([0, 0, yaw]) * Rotation.from_rotvec([-pitch, 0, 0])).as_matrix()
    rest = hand.skeleton.rest_joints()
    # The fingers then arc over the object's far side and the thumb reaches its near side.
    grasp_point = np.array([0.5 * (rest[5, 0] + rest[17, 0]), _GRASP_POINT * rest[9, 1], 0.0])
    offset = rng.uniform(-0.006, 0.006, size=2)
    top = pose[1] + np.array([offset[0], offset[1], obj.radius + _APPROACH_HEIGHT_M])
    wrist_top = top - rot @ grasp_point
    preshape = _hand_pose(rot, wrist_top, _PRESHAPE)

    # Descent: bisection on the distance travelled down until the palm is PALM_GAP_M away
    # (or a pre-shaped finger would come closer than _APPROACH_GAP_M).
    skin, _ = hand.surface_points(preshape, hand.proxy, normals=False)
    palm = hand.surface_bone[hand.proxy] % 4 == 0
    reach = _APPROACH_HEIGHT_M + 2 * obj.radius
    down = np.array([0.0, 0.0, -1.0])

    def clearance(s: np.ndarray) -> np.ndarray:
        d = scene_sdf(skin + (s.ravel() * reach)[:, None, None] * down)
        c = np.minimum(d[:, palm].min(axis=1) - PALM_GAP_M, d[:, ~palm].min(axis=1) - _APPROACH_GAP_M)
        return c.reshape(s.shape)

    placed = preshape.copy()
    placed[3:6] += _first_crossing(clearance, 1)[0] * reach * down

    # Closing: per stage and finger, bisection on how far the moving DOFs go towards the target.
    # A finger that touches with a segment the next stage would move keeps still from then on:
    # moving that segment could only press into the surface or lift off it.
    stages = [placed]
    current = placed[6:].reshape(5, 4).copy()
    touching = np.zeros(5, dtype=np.int64)       # finger bone (1..3) in contact, 0 for none
    for cols, bones, target in _STAGES:
        clearance = _closing_clearance(hand, placed, current.copy(), cols, bones, target, scene_sdf)
        s_star = np.where(np.isin(touching, bones), 0.0, _first_crossing(clearance, 5))
        for c in cols:
            current[:, c] += s_star * (target[:, c] - current[:, c])
        pose_now = np.concatenate([placed[:6], current.ravel()])
        stages.append(pose_now)
        gap = hand.clearance(pose_now[None], [np.array([b]) for b in range(20)], scene_sdf)[0]
        for f in np.flatnonzero((s_star > 0) & (s_star < 1)):
            touching[f] = min(bones, key=lambda k: gap[4 * f + k])

    poses = np.array([preshape, *stages, stages[-1], *stages[-2::-1], preshape])
    poses.setflags(write=False)
    return poses


@functools.lru_cache(maxsize=16)
def _first_touch(hand: HandModel, obj: SimObject, seed: int, table_top_z: float) -> np.ndarray:
    """(P,) the fraction of a grasp's timeline at which each skin vertex first touches the object
    (inf: never), sampled on a fixed grid of the timeline, so that it does not depend on the
    duration chosen for the take."""
    keys = _Keyframes(np.array(_GRASP_TIMELINE), _grasp_poses(hand, obj, seed, table_top_z))
    s = np.linspace(0.0, 1.0, _PAINT_SAMPLES)
    angles = keys(s)
    # holds repeat a pose exactly: measure each distinct pose once
    moved = np.flatnonzero(np.r_[True, np.any(angles[1:] != angles[:-1], axis=1)])
    frame, point = hand.contact(angles[moved], obj, obj.resting_pose(table_top_z))
    first = np.full(hand.n_points, np.inf)
    np.minimum.at(first, point, s[moved][frame])
    first.setflags(write=False)
    return first


def _canonical_pose(hand: HandModel) -> np.ndarray:
    """Flat open hand over the table, palm up and tilted towards the -y and -x walls.

    The tilt to the side also keeps the rotation away from a half turn, where rotation vectors
    are ambiguous.
    """
    palm_normal = np.array([-0.3, -0.45, 1.0])
    palm_normal /= np.linalg.norm(palm_normal)
    fingers = np.array([0.0, 1.0, 0.0]) - palm_normal[1] * palm_normal
    fingers /= np.linalg.norm(fingers)
    z = -palm_normal
    rot = np.stack([np.cross(fingers, z), fingers, z], axis=1)
    spread = _fingers(index=(0, 0.1, 0, 0), ring=(0, -0.05, 0, 0), pinky=(0, -0.15, 0, 0))
    return hand.skeleton.clamp(_hand_pose(rot, np.array([0.0, -0.10, -0.04]), spread))


def make_motion(kind: str, hand: HandModel | None, obj: SimObject | None, duration_s: float,
                seed: int = 0, table_top_z: float = -0.15) -> Motion:
    """The motion of a take kind (one of KINDS) for a subject's hand and an object.

    calibration needs neither; hand needs the hand; object needs the object; grasp needs both;
    canonical needs the hand and, for its paint, the object of the grasp it follows (the paint
    is recomputed from the same hand, object and seed).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown motion kind {kind!r}; choose one of {', '.join(KINDS)}")
    if duration_s <= 0:
        raise ValueError(f"motion duration must be positive, got {duration_s}")
    needs_hand = kind in ("hand", "grasp", "canonical")
    if needs_hand and hand is None:
        raise ValueError(f"a {kind} motion needs a hand")
    if kind in ("object", "grasp") and obj is None:
        raise ValueError(f"a {kind} motion needs an object")
    pose = obj.resting_pose(table_top_z) if obj is not None else None
    if kind == "calibration":
        return Motion(kind, duration_s, None, None, None, None)
    if kind == "object":
        return Motion(kind, duration_s, None, obj, pose, None)
    if kind == "hand":
        return Motion(kind, duration_s, hand, None, None, _hand_routine(hand, duration_s, seed))
    if kind == "grasp":
        keys = _Keyframes(np.array(_GRASP_TIMELINE) * duration_s, _grasp_poses(hand, obj, seed, table_top_z))
        return Motion(kind, duration_s, hand, obj, pose, keys, grasp=(hand, obj, seed, table_top_z))
    still = _canonical_pose(hand)
    keys = _Keyframes(np.array([0.0, duration_s]), np.stack([still, still]))
    source = make_motion("grasp", hand, obj, duration_s, seed, table_top_z) if obj is not None else None
    return Motion(kind, duration_s, hand, obj, None, keys, paint_source=source)
