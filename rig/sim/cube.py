"""The simulated capture cube as a camera backend: one SimulatedCube per take, one SimCamera per camera.

Frames come out the way a UVC camera hands them over: JPEG bytes with the device's sequence
number and timestamp and the host's arrival time. Each camera renders the scene at its own
mid-exposure time, so the images of one frame group really differ by the cameras' phase
offsets, and a drop is a frame that was exposed but never reached the host.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from functools import lru_cache

import cv2
import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import CameraError
from manus_core.rig_config import CameraConfig, RigConfig
from rig.sim.ground_truth import write_ground_truth
from rig.sim.hand import make_hand
from rig.sim.motion import make_motion
from rig.sim.objects import make_object

from ..cameras import CameraInfo, Frame
from ..clock import VirtualClock
from .clocks import CameraClock
from .memo import SharedCache
from .render import Rendered, Renderer
from .world import World

HARDWARE_TRIGGER_LATENCY_NS = 10_000  # opto-isolated trigger input: microseconds, no host in the loop
LEAD_NS = 20_000_000                  # tick 0 comes this long after the cube is created


def look_at(position, target, up) -> np.ndarray:
    """World-to-camera rotation (OpenCV axes: x right, y down, z forward)."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"camera at {position} looks along its up vector {up}")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def intrinsics(width: int, height: int, hfov_deg: float, aspect: float = 1.0,
               principal_offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """K of a camera: fx from the horizontal field of view, fy = aspect * fx, and the principal
    point offset from the image centre ((w-1)/2, (h-1)/2) by fractions of the width and height."""
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    cx = (width - 1) / 2 + principal_offset[0] * width
    cy = (height - 1) / 2 + principal_offset[1] * height
    return np.array([[f, 0, cx], [0, aspect * f, cy], [0, 0, 1]])


def true_cameras(config: RigConfig) -> CameraRig:
    """The exact cameras of the simulated rig (its sim cameras, in rig.toml order)."""
    cams = [c for c in config.cameras if c.backend == "sim"]
    if not cams:
        raise CameraError(f"{config.source}: no camera with backend 'sim'")
    Rs = [look_at(c.sim.position, c.sim.look_at, c.sim.up) for c in cams]
    ts = [-R @ np.asarray(c.sim.position) for R, c in zip(Rs, cams)]
    Ks = [intrinsics(c.width, c.height, c.sim.hfov_deg, c.sim.aspect, c.sim.principal_offset) for c in cams]
    return CameraRig(tuple(c.id for c in cams), Ks, [c.sim.dist for c in cams], Rs, ts,
                     [[c.width, c.height] for c in cams])


class SimulatedCube:
    """The world, the subject's motion for one take kind, the clocks and the renderer."""

    def __init__(self, config: RigConfig, kind: str, duration_s: float = 2.0,
                 clock: VirtualClock | None = None, lighting: Callable[[int], float] | None = None) -> None:
        sim = config.sim
        self.config = config
        self.kind = kind
        self.duration_s = float(duration_s)
        self.world = World(edge=sim.cube_edge, tag_size=sim.tag_size, tags_per_wall=sim.tags_per_wall,
                           table_tags=sim.table_tags, seed=sim.seed)
        self.cameras = true_cameras(config)
        self.camera_configs = tuple(c for c in config.cameras if c.backend == "sim")
        self.renderer = Renderer(self.world, self.cameras, sim.supersample)
        self.hand = make_hand(sim.subject) if kind in ("hand", "grasp", "canonical") else None
        self.object = make_object(sim.object, painted=sim.paint) if kind in ("object", "grasp") else None
        # the canonical pose shows the paint of the grasp, so its motion needs the object too
        paint_source = make_object(sim.object, painted=sim.paint) if kind == "canonical" else self.object
        self.motion = make_motion(kind, self.hand, paint_source, duration_s, seed=sim.seed,
                                  table_top_z=self.world.table_top)
        self.clock = clock or VirtualClock(time_scale=sim.time_scale)
        self.t0_ns = self.clock.now_ns() + LEAD_NS
        self.lighting = lighting or (lambda t_ns: 1.0)
        self.clocks = tuple(CameraClock(c.sim, config.fps, i, sim.seed, self.t0_ns)
                            for i, c in enumerate(self.camera_configs))
        self.records: list[list[tuple[int, int, bool]]] = [[] for _ in self.camera_configs]
        self._lock = threading.Lock()
        # cameras exposed within one render instant (triggered rigs, label renders) share the scene,
        # and their reader threads interleave a few instants: keep the last ones
        self._states: SharedCache = SharedCache(32)

    @property
    def period_ns(self) -> float:
        return 1e9 / self.config.fps

    def tick_ns(self, k) -> np.ndarray:
        return self.t0_ns + np.asarray(k, np.float64) * self.period_ns

    def seconds(self, t_ns) -> np.ndarray:
        return (np.asarray(t_ns, np.float64) - self.t0_ns) / 1e9

    def render(self, cam: int, t_ns: float, labels: bool = False) -> Rendered:
        """Camera `cam`'s view of the scene at host time t_ns (its mid-exposure), sampled at the
        nearest render instant (RENDER_INSTANT_NS)."""
        instant = round((float(t_ns) - self.t0_ns) / RENDER_INSTANT_NS) * RENDER_INSTANT_NS
        state = self._states.get(instant, lambda: self.motion.state(instant / 1e9))
        return self.renderer.render(cam, hand=self.hand, hand_angles=state.hand_angles, paint=state.paint,
                                    obj=self.object, object_pose=state.object_pose,
                                    light=self.lighting(int(t_ns)), labels=labels)

    def camera(self, cam_id: str) -> "SimCamera":
        for i, c in enumerate(self.camera_configs):
            if c.id == cam_id:
                return SimCamera(self, i, c)
        raise CameraError(f"{self.config.source}: no sim camera {cam_id!r}")

    def record(self, cam: int, tick: int, exposure_ns: int, dropped: bool) -> None:
        with self._lock:
            self.records[cam].append((tick, exposure_ns, dropped))

    def write_ground_truth(self, path, label_frames=None) -> None:
        write_ground_truth(self, path, label_frames)


# A camera integrates its image over an exposure of milliseconds; the renderer samples one instant
# of it, rounded to this grid so that cameras triggered together (80-250 us apart) share one posed
# hand and one ray-casting tree instead of building one each. At the cube's fastest motion
# (0.3 m/s) the hand moves 0.04 mm in half a step: 0.06 px at 1280x720, far inside the exposure.
RENDER_INSTANT_NS = 250_000


@lru_cache(maxsize=4)
def _noise_bank(seed: int, size: int) -> np.ndarray:
    """Standard normal sensor noise for frames of `size` values, to be read at offsets: any two
    frames' windows are apart by one of 2^18 offsets, so one pixel's noise in successive frames is
    independent."""
    bank = np.random.default_rng([seed, size, 98]).standard_normal(size + (1 << 18), dtype=np.float32)
    bank.flags.writeable = False
    return bank


class SimCamera:
    """A simulated camera implementing rig.cameras.Camera."""

    def __init__(self, cube: SimulatedCube, index: int, config: CameraConfig) -> None:
        self.cube, self.index, self.config = cube, index, config
        self.clock_model: CameraClock = cube.clocks[index]
        self._k = 0
        self._started = False
        self._opened = False
        self._triggers: deque[int] = deque()
        self._trigger_ready = threading.Condition()
        sim = cube.config.sim
        self._noise_sigma = sim.noise_sigma
        # the cube's cameras hand out JPEG as the recorder would store them
        self._jpeg_params = cube.config.storage.jpeg_params()
        self._seed = sim.seed

    def open(self) -> None:
        self._opened = True

    def configure(self) -> None:
        if not self._opened:
            raise CameraError(f"camera {self.config.id}: configure() before open()")

    def start(self) -> None:
        if not self._opened:
            raise CameraError(f"camera {self.config.id}: start() before open()")
        self._started = True

    def stop(self) -> None:
        self._started = False
        with self._trigger_ready:
            self._trigger_ready.notify_all()

    def close(self) -> None:
        self.stop()
        self._opened = False

    def info(self) -> CameraInfo:
        c = self.config
        return CameraInfo(c.id, "sim", "manus-capture simulated camera", c.device, c.width, c.height, c.fps,
                          "MJPG", can_trigger=True)

    def trigger(self) -> None:
        """A software trigger: the camera exposes after its trigger latency."""
        with self._trigger_ready:
            self._triggers.append(self.cube.clock.now_ns())
            self._trigger_ready.notify()

    def _next_exposure(self, timeout_s: float) -> tuple[int, float] | None:
        """(tick index, mid-exposure ns) of the next frame the sensor exposes."""
        k = self._k
        mode = self.cube.config.sync
        if mode == "free-run":
            return k, float(self.clock_model.free_run_exposure_ns(k))
        if mode == "hardware-trigger":
            return k, float(self.cube.tick_ns(k)) + HARDWARE_TRIGGER_LATENCY_NS
        with self._trigger_ready:
            if not self._triggers:
                self._trigger_ready.wait(timeout_s)
            if not self._triggers:
                return None
            sent = self._triggers.popleft()
        # the tick a trigger belongs to is the nearest nominal tick to when it was sent
        tick = int(round((sent - self.cube.t0_ns) / self.cube.period_ns))
        return tick, float(self.clock_model.triggered_exposure_ns(sent, k))

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        if not self._started:
            raise CameraError(f"camera {self.config.id}: read() before start()")
        while True:
            nxt = self._next_exposure(timeout_s)
            if nxt is None:
                return None
            tick, exposure = nxt
            k = self._k
            self._k += 1
            dropped = bool(self.clock_model.dropped(k))
            self.cube.record(self.index, tick, int(round(exposure)), dropped)
            if not dropped:
                break
        host = int(self.clock_model.host_ns(exposure, k, self.config.exposure_us))
        clock = self.cube.clock
        if clock.time_scale > 0:
            clock.sleep_until_ns(host)
        else:
            clock.advance_to(host)
        device = int(self.clock_model.device_ns(exposure, k))
        image = self.cube.render(self.index, exposure).image
        return Frame(self._encode(image, k), k, device, host, self.config.width, self.config.height, "jpeg")

    def _encode(self, image: np.ndarray, k: int) -> bytes:
        # the frame's noise is a window of the cube's noise at a seeded offset: drawing a frame's
        # worth of normals cost 1.5 ms of the 1.9 ms that a 320x180 frame took to encode
        bank = _noise_bank(self._seed, image.size)
        start = np.random.default_rng([self._seed, self.index, k, 99]).integers(0, len(bank) - image.size + 1)
        noise = bank[start:start + image.size].reshape(image.shape)
        noisy = image * 255.0 + noise * np.float32(self._noise_sigma)
        ok, buf = cv2.imencode(".jpg", np.clip(noisy, 0, 255).astype(np.uint8), self._jpeg_params)
        if not ok:
            raise CameraError(f"camera {self.config.id}: JPEG encoding failed")
        return buf.tobytes()
