"""Camera layouts: where the cameras of a rig sit. `cube53` is the MANUS-Grasps capture cube.

To add a layout, write a function returning (ids, positions (N,3), up vectors (N,3)) and register it
in LAYOUTS (docs/simulation.md walks through it).
"""

from __future__ import annotations

import numpy as np

from manus_core.rig_config import CameraConfig, LedConfig, RigConfig, SimCameraConfig, SimConfig, StorageConfig

CENTRE_AIM = (0.0, 0.0, -0.05)     # just above the table top: where the hand works
OVER_TABLE_AIM = (0.0, 0.0, 0.3)   # floor cameras beside the table look up past it


def cube53(edge: float = 1.2, inset: float = 0.05,
           spread: float = 0.4) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """6 faces x a 3x3 grid, less the floor's centre where the table stands: 53 cameras.

    Cameras sit `inset` metres inside each wall on a grid of pitch `spread`, aimed at the centre;
    the four floor cameras at the middle of the floor's edges would look into the table's side,
    so they are aimed up over it (they then see the walls' tags and the space above the table).
    Returns ids, positions, up vectors and aim points.
    """
    ids, pos, ups, aims = [], [], [], []
    h = edge / 2 - inset
    grid = (-spread, 0.0, spread)
    for axis in range(3):
        for sign in (1, -1):
            face = f"{'xyz'[axis]}{'+' if sign > 0 else '-'}"
            others = [a for a in range(3) if a != axis]
            for i, a in enumerate(grid):
                for j, b in enumerate(grid):
                    if face == "z-" and a == 0 and b == 0:
                        continue
                    p = np.zeros(3)
                    p[axis] = sign * h
                    p[others[0]], p[others[1]] = a, b
                    ids.append(f"{face}{i}{j}")
                    pos.append(p)
                    ups.append((0.0, 1.0, 0.0) if axis == 2 else (0.0, 0.0, 1.0))
                    beside_table = face == "z-" and (a == 0) != (b == 0)
                    aims.append(OVER_TABLE_AIM if beside_table else CENTRE_AIM)
    return ids, np.array(pos), np.array(ups), np.array(aims)


LAYOUTS = {"cube53": cube53}


def spread_subset(positions: np.ndarray, n: int) -> np.ndarray:
    """Indices of n cameras spread over all faces: one near each face's centre first, then
    farthest-point sampling over the rest."""
    n = min(n, len(positions))
    dirs = positions / np.linalg.norm(positions, axis=1, keepdims=True)
    axes = np.concatenate([np.eye(3), -np.eye(3)])[[0, 3, 1, 4, 2, 5]]
    chosen: list[int] = []
    for axis in axes:
        i = int(np.argmax(dirs @ axis))
        if i not in chosen:
            chosen.append(i)
    chosen = chosen[:n]
    d = np.min(np.linalg.norm(positions[:, None] - positions[chosen][None], axis=2), axis=1)
    while len(chosen) < n:
        nxt = int(np.argmax(d))
        chosen.append(nxt)
        d = np.minimum(d, np.linalg.norm(positions - positions[nxt], axis=1))
    return np.sort(np.array(chosen))


def r(x: float) -> float:
    """Round a generated value so rig.toml stays readable and reloads exactly."""
    return round(float(x), 4)


# The optics draw from a stream of their own, so that adding them (issue 19) left every value the
# main stream gives (positions, clocks, field of view, drops) as it was for the same seed.
OPTICS_STREAM = 19
K1_RANGE = (-0.3, 0.1)              # strong barrel to mild pincushion, as lenses of real rigs come
K2_RANGE = (0.0, 0.05)              # redrawn until the lens is invertible (lens_is_invertible)
TANGENTIAL_SIGMA = 0.0015           # p1, p2: a slightly tilted sensor
PRINCIPAL_OFFSET = 0.02             # off the image centre, up to this fraction of each side
ASPECT_RANGE = (0.995, 1.005)       # fy / fx
MIN_SLOPE = 0.1                     # of the radial map, d r_distorted / d r
MAX_INCIDENCE_DEG = 89.0            # the widest angle off the axis at which a point lies in view


def lens_is_invertible(k1: float, k2: float) -> bool:
    """Whether r -> r (1 + k1 r^2 + k2 r^4) rises (slope >= MIN_SLOPE) out to MAX_INCIDENCE_DEG.

    Rising only up to the image's corners is not enough: CameraRig.project applies the polynomial
    to any point in front of the camera, and past a fold a point far outside the field of view
    (the next wall, beside the camera) would project back into the image, where the renderer,
    which casts rays from the pixels, never shows it. The margin keeps the undistortion of the
    image's corners well conditioned.
    """
    rho2 = np.linspace(0.0, np.tan(np.radians(MAX_INCIDENCE_DEG)), 20001) ** 2
    return bool(np.all(1 + rho2 * (3 * k1 + 5 * k2 * rho2) >= MIN_SLOPE))


def draw_optics(rng: np.random.Generator) -> dict:
    """One camera's true intrinsics beyond the field of view, as SimCameraConfig fields.

    No camera matches a nominal model (centred principal point, square pixels, no distortion):
    a calibration that estimates intrinsics is tested against cameras that differ from any.
    """
    aspect = r(rng.uniform(*ASPECT_RANGE))
    offset = (r(rng.uniform(-PRINCIPAL_OFFSET, PRINCIPAL_OFFSET)), r(rng.uniform(-PRINCIPAL_OFFSET, PRINCIPAL_OFFSET)))
    k1 = r(rng.uniform(*K1_RANGE))
    for _ in range(1000):   # k2 within reach for every k1 of K1_RANGE: about 1 in 10 at k1 = -0.3
        k2 = r(rng.uniform(*K2_RANGE))
        if lens_is_invertible(k1, k2):
            break
    else:
        raise AssertionError(f"no k2 in {K2_RANGE} makes k1 = {k1} invertible")
    p1, p2 = (r(rng.normal(0, TANGENTIAL_SIGMA)) for _ in range(2))
    return {"aspect": aspect, "principal_offset": offset, "dist": (k1, k2, p1, p2, 0.0)}


def make_rig(layout: str = "cube53", cameras: int | None = None, resolution: tuple[int, int] = (1280, 720),
             fps: float = 120.0, backend: str = "sim", seed: int = 0, sync: str = "free-run",
             name: str | None = None) -> RigConfig:
    """A rig configuration for a layout. The sim backend gets realistic, seeded imperfections:
    clock offsets of a few ms, drifts of tens of ppm, jitter, trigger latency, a small drop rate,
    and per camera optics (draw_optics): a focal length spread of a few percent, the principal
    point off centre, non-square pixels, radial and tangential distortion. Every value is written
    out so that it can be edited."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r} (known: {', '.join(LAYOUTS)})")
    ids, pos, ups, aims = LAYOUTS[layout]()
    if cameras is not None:
        if cameras < 1:
            raise ValueError("--cameras must be at least 1")
        keep = spread_subset(pos, cameras)
        ids, pos, ups, aims = [ids[i] for i in keep], pos[keep], ups[keep], aims[keep]
    rng = np.random.default_rng(seed)
    optics_rng = np.random.default_rng([seed, OPTICS_STREAM])
    period_ms = 1000.0 / fps
    width, height = resolution
    cams = []
    for k, (cam_id, p, up, aim) in enumerate(zip(ids, pos, ups, aims)):
        sim = None
        if backend == "sim":
            hfov = r(rng.uniform(72, 78))
            # the main stream's old distortion draws, still made and unused so that the clocks and
            # drops after them keep their values for a seed (tests and saved rigs rely on them)
            rng.normal(0, (0.03, 0.01))
            sim = SimCameraConfig(
                position=tuple(r(x) for x in p), look_at=tuple(float(x) for x in aim), up=tuple(float(x) for x in up),
                hfov_deg=hfov, **draw_optics(optics_rng),
                clock_offset_ms=r(rng.uniform(-5, 5)), drift_ppm=r(rng.normal(0, 25)),
                phase_ms=r(rng.uniform(0, period_ms)), timestamp_jitter_us=20.0,
                trigger_latency_us=r(rng.uniform(80, 250)), trigger_jitter_us=30.0,
                latency_ms=r(rng.uniform(1.5, 3.0)), latency_jitter_ms=0.3, drop_rate=0.002)
        device = f"sim:{k}" if backend == "sim" else ("/dev/v4l/by-id/CHANGE-ME" if backend == "v4l2" else "CHANGE-ME")
        # GigE/USB3 Vision cameras hand out raw pixels; UVC and the simulated cube hand out MJPEG
        pixel_format = "Mono8" if backend == "aravis" else "MJPG"
        cams.append(CameraConfig(id=cam_id, backend=backend, device=device, width=width, height=height,
                                 fps=fps, pixel_format=pixel_format, sim=sim))
    return RigConfig(name=name or f"{layout}-{len(cams)}", cameras=tuple(cams), layout=layout, fps=fps,
                     sync=sync, leds=LedConfig(port="sim" if backend == "sim" else "/dev/ttyACM0",
                                               protocol="sim" if backend == "sim" else "ascii"),
                     storage=StorageConfig(), sim=SimConfig(seed=seed) if backend == "sim" else None)
