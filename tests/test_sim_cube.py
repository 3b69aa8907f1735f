"""The simulated cube as a camera backend: clocks, drops, triggers, lighting and ground truth."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from manus_core.errors import CameraError
from manus_core.ground_truth import LABEL_HAND, LABEL_OBJECT, LABEL_PAINT, LABEL_WALLS, GroundTruth
from manus_core.rig_config import SimCameraConfig
from rig.cameras import Camera
from rig.layouts import make_rig
from rig.sim.clocks import CameraClock
from rig.sim.cube import SimulatedCube, true_cameras


def small_rig(cameras=4, resolution=(96, 54), sync="free-run", **sim):
    rig = make_rig("cube53", cameras=cameras, resolution=resolution, sync=sync, seed=5)
    return dataclasses.replace(rig, sim=dataclasses.replace(rig.sim, **sim))


def with_camera_params(rig, **params):
    cams = tuple(dataclasses.replace(c, sim=dataclasses.replace(c.sim, **params)) for c in rig.cameras)
    return dataclasses.replace(rig, cameras=cams)


def test_clock_model_follows_offset_drift_and_jitter():
    p = SimCameraConfig(position=(0, 0, 0), clock_offset_ms=3.2, drift_ppm=-41.0, phase_ms=2.0,
                        timestamp_jitter_us=25.0, latency_ms=2.5, latency_jitter_ms=0.3, drop_rate=0.02)
    clock = CameraClock(p, fps=120.0, index=3, seed=11, t0_ns=10**12)
    k = np.arange(60_000)  # 500 s of frames
    exposure = clock.free_run_exposure_ns(k)
    device = clock.device_ns(exposure, k)
    slope, intercept = np.polyfit((exposure - 10**12) / 1e9, (device - exposure) / 1e3, 1)  # us, us/s
    assert slope == pytest.approx(-41.0, abs=0.2)              # drift in ppm (= us per s)
    assert intercept == pytest.approx(3200.0, abs=1.0)         # offset in us
    residual = (device - exposure) / 1e3 - (slope * (exposure - 10**12) / 1e9 + intercept)
    assert residual.std() == pytest.approx(25.0, rel=0.03)     # timestamp jitter
    # the oscillator's drift shows in the frame interval too
    assert np.diff(exposure).mean() == pytest.approx(1e9 / 120 / (1 - 41e-6), rel=1e-9)
    host = clock.host_ns(exposure, k, exposure_us=2000)
    latency = (host - exposure) / 1e6
    assert latency.min() >= 3.5 - 1e-6 and latency.mean() == pytest.approx(3.8, abs=0.01)
    assert clock.dropped(k).mean() == pytest.approx(0.02, abs=0.002)  # 3.9 sigma at n = 60000
    # frame timing is a pure function of the frame number
    assert np.array_equal(clock.device_ns(exposure[::-1], k[::-1]), device[::-1])


@pytest.mark.parametrize("seed", [0, 1])
def test_true_intrinsics_differ_from_any_nominal_camera(seed):
    """Issue 19: a calibration that estimates intrinsics must not be handed cameras that match a
    nominal model; the realized optics spread the way real cameras' do."""
    rig = make_rig("cube53", resolution=(1280, 720), seed=seed)
    cams = true_cameras(rig)
    K, (k1, k2, p1, p2, k3) = cams.K, cams.dist.T
    fx, aspect = K[:, 0, 0], K[:, 1, 1] / K[:, 0, 0]
    off_x, off_y = K[:, 0, 2] - 639.5, K[:, 1, 2] - 359.5
    assert 1.05 < fx.max() / fx.min() < 1.15                      # a few percent of focal spread
    assert np.all(np.abs(aspect - 1) <= 0.005) and np.ptp(aspect) > 0.005
    assert np.all(np.abs(off_x) <= 0.02 * 1280 + 1e-9) and np.all(np.abs(off_y) <= 0.02 * 720 + 1e-9)
    assert np.ptp(off_x) > 30 and np.ptp(off_y) > 15 and np.count_nonzero(np.hypot(off_x, off_y) < 1) <= 1
    assert -0.3 <= k1.min() < -0.25 and 0.05 < k1.max() <= 0.1
    assert np.all((k2 >= 0) & (k2 <= 0.05)) and np.all(k3 == 0)
    assert 0.001 < np.std(np.concatenate([p1, p2])) < 0.002
    # the configured values are the realized ones
    sim = rig.cameras[0].sim
    assert K[0, 1, 1] == pytest.approx(sim.aspect * K[0, 0, 0])
    assert K[0, 0, 2] == pytest.approx(639.5 + 1280 * sim.principal_offset[0])


def test_lens_distortion_never_folds_back_into_the_image():
    """Along every ray from the axis towards an image corner, out to 89 degrees off the axis, the
    distorted point moves outwards: each pixel sees one direction, and no point outside the field
    of view (the next wall, beside the camera) projects into the image."""
    for seed in range(4):
        cams = true_cameras(make_rig("cube53", resolution=(1280, 720), seed=seed))
        for c in range(len(cams)):
            w, h = cams.size[c]
            corners = np.array([[0, 0], [w, 0], [0, h], [w, h]], float) - cams.K[c, :2, 2]
            directions = corners / np.linalg.norm(corners, axis=1, keepdims=True)
            rho = np.linspace(0, np.tan(np.radians(89)), 5000)
            xy = rho[None, :, None] * directions[:, None, :]                    # (4, R, 2)
            xd = cams.subset([cams.ids[c]]).distort(xy.reshape(1, -1, 2))[0].reshape(xy.shape)
            along = np.einsum("crk,ck->cr", xd, directions)
            assert np.all(np.diff(along, axis=1) > 0), (cams.ids[c], cams.dist[c])
            reach = along[:, -1] * cams.K[c, 0, 0]
            assert np.all(reach > np.linalg.norm(corners, axis=1)), cams.ids[c]


def test_the_optics_leave_every_other_drawn_value_as_it_was():
    """The optics draw from a stream of their own: the clocks, poses and fields of view of a seed
    are those rigs made before them had (tests and saved rigs rely on them)."""
    rig = make_rig("cube53", seed=0)
    first, last = rig.cameras[0].sim, rig.cameras[-1].sim
    assert (first.hfov_deg, first.clock_offset_ms, first.phase_ms) == (75.8218, -4.8347, 7.6063)
    assert (last.hfov_deg, last.clock_offset_ms, last.phase_ms) == (75.1697, -3.2992, 4.4658)


def test_camera_stream_drops_are_gaps_and_all_in_ground_truth(tmp_path):
    rig = with_camera_params(small_rig(), drop_rate=0.08)
    cube = SimulatedCube(rig, "calibration", duration_s=1.0)
    cams = [cube.camera(c.id) for c in rig.cameras]
    assert all(isinstance(c, Camera) for c in cams)
    seqs = []
    for cam in cams:
        cam.open(); cam.configure(); cam.start()
        frames = [cam.read() for _ in range(60)]
        seqs.append(np.array([f.seq for f in frames]))
        host = np.array([f.t_host_ns for f in frames])
        assert np.all(np.diff(host) > 0)
        image = cv2.imdecode(np.frombuffer(frames[0].data, np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == (54, 96, 3) and frames[0].encoding == "jpeg"
        cam.stop(); cam.close()
    cube.write_ground_truth(tmp_path / "ground_truth.h5")
    gt = GroundTruth(tmp_path / "ground_truth.h5")
    dropped, exposure = gt.frames.dropped, gt.frames.exposure_mid_ns
    assert list(gt.cameras.ids) == [c.id for c in rig.cameras]
    n_drops = 0
    for c, seq in enumerate(seqs):
        received = np.zeros(seq.max() + 1, bool)
        received[seq] = True
        assert np.array_equal(~received, dropped[c, :seq.max() + 1])  # every gap is a recorded drop
        n_drops += (~received).sum()
        assert np.all(exposure[c, :seq.max() + 1] > 0)
    assert n_drops > 5  # at 8% over ~260 frames


def test_triggered_cameras_expose_together_free_running_ones_do_not():
    spreads = {}
    for mode in ("free-run", "software-trigger", "hardware-trigger"):
        rig = small_rig(cameras=6, resolution=(32, 18), sync=mode)
        cube = SimulatedCube(rig, "calibration", duration_s=1.0)
        cams = [cube.camera(c.id) for c in rig.cameras]
        for cam in cams:
            cam.open(); cam.start()
        for k in range(12):
            if mode == "software-trigger":
                cube.clock.sleep_until_ns(int(cube.tick_ns(k)))
                for cam in cams:
                    cam.trigger()
            for cam in cams:
                cam.read(timeout_s=0.01)  # None only where the frame of this trigger was dropped
        exposure = np.array([[e for _, e, _ in recs][:10] for recs in cube.records], float)
        spreads[mode] = np.ptp(exposure, axis=0).max() / 1e6
    assert spreads["hardware-trigger"] < 0.01
    assert spreads["software-trigger"] < 0.5     # trigger latency differences, a fraction of a ms
    assert spreads["free-run"] > 1.0            # random phases over an 8.3 ms period


def test_software_trigger_without_trigger_times_out():
    rig = small_rig(cameras=1, resolution=(32, 18), sync="software-trigger")
    cam = SimulatedCube(rig, "calibration").camera(rig.cameras[0].id)
    with pytest.raises(CameraError):
        cam.read()
    cam.open(); cam.start()
    assert cam.read(timeout_s=0.01) is None


def test_led_flash_shows_in_the_images():
    rig = small_rig(cameras=1, resolution=(64, 36))
    flash_from = 0.1
    cube = SimulatedCube(rig, "calibration", lighting=lambda t_ns: 1.0)
    cube.lighting = lambda t_ns: 1.0 if (t_ns - cube.t0_ns) / 1e9 >= flash_from else 0.3
    cam = cube.camera(rig.cameras[0].id)
    cam.open(); cam.start()
    frames = [cam.read() for _ in range(24)]
    level = np.array([cv2.imdecode(np.frombuffer(f.data, np.uint8), 0).mean() for f in frames])
    exposure = np.array([e for _, e, d in cube.records[0] if not d], float)[:24]
    lit = (exposure - cube.t0_ns) / 1e9 >= flash_from
    assert lit.any() and (~lit).any()
    assert level[lit].min() > 1.5 * level[~lit].max()


def test_sensor_noise_is_new_in_every_frame():
    """A still scene stored at JPEG quality 100, 4:4:4: each frame's difference from the frames' mean
    is the sensor noise, of the configured sigma (rounding and JPEG add under 1 grey level in
    quadrature), and unrelated from one frame to the next: frames reading one window of noise would
    correlate fully."""
    sigma, n = 4.0, 16
    rig = small_rig(cameras=1, resolution=(96, 54), noise_sigma=sigma)
    rig = dataclasses.replace(rig, storage=dataclasses.replace(rig.storage, jpeg_quality=100, jpeg_chroma="444"))
    cam = SimulatedCube(rig, "calibration").camera(rig.cameras[0].id)
    cam.open(); cam.start()
    frames = np.array([cv2.imdecode(np.frombuffer(cam.read().data, np.uint8), 1) for _ in range(n)], float)
    residual = frames - frames.mean(axis=0)
    assert 0.95 * sigma < residual.std() * np.sqrt(n / (n - 1)) < 1.1 * sigma
    r = residual.reshape(n, -1)
    # residuals about a common mean correlate by -1/(n-1); beyond that, 15k independent values
    # stray by about 0.01
    step = np.array([np.corrcoef(r[i], r[i + 1])[0, 1] for i in range(n - 1)]) + 1 / (n - 1)
    assert np.abs(step).max() < 0.05


def read_every_camera(cube, rig, frames: int) -> None:
    """Stream `frames` frames from each camera of the cube (what write_ground_truth then records)."""
    for c in rig.cameras:
        cam = cube.camera(c.id)
        cam.open(); cam.start()
        for _ in range(frames):
            cam.read()


@pytest.fixture(scope="module")
def grasp_truth(tmp_path_factory):
    rig = small_rig(cameras=6, resolution=(160, 90), paint=True, object="mug")
    # a short take keeps the suite fast; the motion's phases scale with the duration
    cube = SimulatedCube(rig, "grasp", duration_s=0.25)
    read_every_camera(cube, rig, 30)
    path = tmp_path_factory.mktemp("grasp") / "ground_truth.h5"
    hold = int(0.125 * rig.fps)  # the grasp holds the object at mid-take
    cube.write_ground_truth(path, label_frames=[hold])
    return rig, path


def test_grasp_ground_truth_is_complete(grasp_truth):
    rig, path = grasp_truth
    cams = true_cameras(rig)
    gt = GroundTruth(path)
    F = gt.frames.exposure_mid_ns.shape[1]
    assert F >= 30
    assert gt.hand.joints3d.shape == (F, 21, 3) and gt.hand.joint_angles.shape == (F, 26)
    assert gt.hand.bone_lengths.shape == (20,)
    assert np.allclose(gt.cameras.K, cams.K) and np.allclose(gt.cameras.t, cams.t)
    assert np.array_equal(gt.cameras.dist, cams.dist)
    P = gt.contact.points_rest.shape[0]
    assert gt.contact.instant.shape == (F, P)
    accumulated = gt.contact.accumulated
    assert 0 < accumulated.sum() < P // 4
    assert np.array_equal(accumulated, gt.contact.instant.any(axis=0) | accumulated)
    labels = gt.labels()
    assert labels.shape == (len(cams), 1, 90, 160)
    seen = np.bincount(labels.ravel(), minlength=5)
    assert seen[LABEL_HAND] > 100 and seen[LABEL_OBJECT] > 100 and seen[LABEL_WALLS] > 0
    # the hand's true joints project inside its labelled pixels in most views
    hold = gt.label_frames[0]
    uv = cams.project(gt.hand.joints3d[hold])
    inside = []
    for c in range(len(cams)):
        x, y = np.round(uv[c]).astype(int).T
        ok = (x >= 0) & (x < 160) & (y >= 0) & (y < 90)
        inside.append(np.isin(labels[c, 0][y[ok], x[ok]], [LABEL_HAND, LABEL_PAINT, LABEL_OBJECT]).mean())
    assert np.median(inside) > 0.8


def test_canonical_take_shows_the_paint(tmp_path):
    rig = small_rig(cameras=6, resolution=(160, 90), paint=True, object="mug")
    cube = SimulatedCube(rig, "canonical", duration_s=0.5)
    read_every_camera(cube, rig, 3)
    cube.write_ground_truth(tmp_path / "gt.h5", label_frames=[1])
    gt = GroundTruth(tmp_path / "gt.h5")
    labels = gt.labels()
    assert gt.contact.accumulated.sum() > 0
    assert (labels == LABEL_PAINT).sum() > 20
    assert (labels == LABEL_OBJECT).sum() == 0
