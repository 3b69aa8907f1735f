"""Keypoint decoding (SimCC, heatmaps) through tiny ONNX graphs with known answers, crop geometry,
and the errors a user meets. None of these need the installed MediaPipe model."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from dataset_tools.keypoints import boxes as bx
from dataset_tools.keypoints import hand_keypoint_detector
from dataset_tools.keypoints.decoding import decode_heatmaps, decode_simcc
from dataset_tools.keypoints.palm import square_tiles
from manus_core.cameras import CameraRig
from manus_core.errors import ModelError, ModelNotInstalledError

H, W = 64, 48          # network input (height, width) of the tiny graphs
K = 21
PERMUTATION = [(5 * j) % K for j in range(K)]   # a joint order unlike MediaPipe's, bijective (5 ⟂ 21)


def _save(graph: onnx.GraphProto, path: Path) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def _image_input() -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info("image", TensorProto.FLOAT, ["N", 3, H, W])


def _const(name: str, value: np.ndarray) -> onnx.NodeProto:
    return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(np.asarray(value), name))


def dot_simcc_graph(path: Path, ratio: int = 2) -> Path:
    """SimCC that 'sees' the brightest pixel of channel 0: every joint's x logits are the column
    maxima (each repeated `ratio` times, one per bin), its y logits the row maxima."""
    nodes = [
        _const("starts", np.array([0], np.int64)), _const("ends", np.array([1], np.int64)),
        _const("axes", np.array([1], np.int64)),
        helper.make_node("Slice", ["image", "starts", "ends", "axes"], ["c0"]),          # (N,1,H,W)
        _const("ax_h", np.array([2], np.int64)), _const("ax_w", np.array([3], np.int64)),
        helper.make_node("ReduceMax", ["c0", "ax_h"], ["cols"], keepdims=0),            # (N,1,W)
        helper.make_node("ReduceMax", ["c0", "ax_w"], ["rows"], keepdims=0),            # (N,1,H)
        _const("last", np.array([3], np.int64)),
        helper.make_node("Unsqueeze", ["cols", "last"], ["cols4"]),
        helper.make_node("Unsqueeze", ["rows", "last"], ["rows4"]),
        _const("rep_x", np.array([1, K, W, ratio], np.int64)),
        _const("rep_y", np.array([1, K, H, ratio], np.int64)),
        helper.make_node("Expand", ["cols4", "rep_x"], ["x4"]),                         # (N,K,W,r)
        helper.make_node("Expand", ["rows4", "rep_y"], ["y4"]),
        _const("shape_x", np.array([0, K, W * ratio], np.int64)),
        _const("shape_y", np.array([0, K, H * ratio], np.int64)),
        helper.make_node("Reshape", ["x4", "shape_x"], ["simcc_x"]),
        helper.make_node("Reshape", ["y4", "shape_y"], ["simcc_y"]),
    ]
    outputs = [helper.make_tensor_value_info("simcc_x", TensorProto.FLOAT, ["N", K, W * ratio]),
               helper.make_tensor_value_info("simcc_y", TensorProto.FLOAT, ["N", K, H * ratio])]
    return _save(helper.make_graph(nodes, "dot_simcc", [_image_input()], outputs), path)


def constant_graph(path: Path, outputs: dict[str, np.ndarray]) -> Path:
    """Outputs fixed tensors (1,...) broadcast to the batch: out = const + 0 * sum(image)."""
    nodes = [_const("all_axes", np.array([1, 2, 3], np.int64)),
             helper.make_node("ReduceSum", ["image", "all_axes"], ["total"], keepdims=0),    # (N,)
             _const("zero", np.array(0.0, np.float32)),
             helper.make_node("Mul", ["total", "zero"], ["nil"])]
    infos = []
    for name, value in outputs.items():
        extra = np.arange(1, value.ndim, dtype=np.int64)
        nodes += [_const(f"{name}_axes", extra),
                  helper.make_node("Unsqueeze", ["nil", f"{name}_axes"], [f"{name}_nil"]),
                  _const(f"{name}_const", value.astype(np.float32)),
                  helper.make_node("Add", [f"{name}_const", f"{name}_nil"], [name])]
        infos.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, ["N", *value.shape[1:]]))
    return _save(helper.make_graph(nodes, "constant", [_image_input()], infos), path)


def spec(path: Path, model: Path, kind: str, table: dict[str, str] | None = None, **top: str) -> Path:
    """A model spec beside the model: [0, 1] RGB input, the box cropped as it is (box_scale 1)."""
    lines = [f'kind = "{kind}"', f'model = "{model.name}"', f"input_size = [{W}, {H}]",
             "mean = [0.0, 0.0, 0.0]", "std = [255.0, 255.0, 255.0]", "box_scale = 1.0"]
    lines += [f"{k} = {v}" for k, v in top.items()]
    lines += [f"[{kind}]"] + [f"{k} = {v}" for k, v in (table or {}).items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_simcc_decoding_known_bins() -> None:
    x = np.zeros((2, 3, 40))
    y = np.zeros((2, 3, 50))
    x[0, 0, 17], y[0, 0, 33] = 0.9, 0.6
    x[1, 2, 39], y[1, 2, 0] = 0.4, 0.8
    out = decode_simcc(x, y, split_ratio=2.0)
    assert out[0, 0].tolist() == [8.5, 16.5, pytest.approx(0.6)]
    assert out[1, 2].tolist() == [19.5, 0.0, pytest.approx(0.4)]


def test_heatmap_decoding_subpixel_peaks() -> None:
    h, w = 16, 12
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    peaks = np.array([[3.3, 7.0], [9.75, 2.4], [0.0, 15.0]])   # (x, y) in heatmap pixels
    hm = np.stack([1 - 0.05 * ((xx - px) ** 2 + (yy - py) ** 2) for px, py in peaks])[None]
    stride = 4
    exact = decode_heatmaps(hm, (w * stride, h * stride), refine="parabola")[0]
    # A separable quadratic peak is recovered exactly, then mapped to input pixel centres.
    np.testing.assert_allclose(exact[:, :2], (peaks + 0.5) * stride - 0.5, atol=1e-9)
    coarse = decode_heatmaps(hm, (w * stride, h * stride), refine="none")[0]
    np.testing.assert_allclose(coarse[:, :2], (np.round(peaks) + 0.5) * stride - 0.5)
    quarter = decode_heatmaps(hm, (w * stride, h * stride), refine="quarter")[0]
    assert quarter[0, 0] == pytest.approx((3.25 + 0.5) * stride - 0.5)  # 3.3: a quarter towards 4
    assert quarter[1, 1] == pytest.approx((2.25 + 0.5) * stride - 0.5)
    assert quarter[2].tolist()[:2] == [0.5 * stride - 0.5, 15.5 * stride - 0.5]  # corner: stays put


@pytest.mark.parametrize("ratio", [1, 2])
def test_simcc_model_finds_a_dot_in_full_image_pixels(tmp_path: Path, ratio: int) -> None:
    """Crop geometry + preprocessing + SimCC decoding, end to end: a bright dot drawn in a large
    image is found at its pixel, for a box that maps 1:1 and for one scaled by 3."""
    model = dot_simcc_graph(tmp_path / "dot.onnx", ratio)
    det = hand_keypoint_detector(spec(tmp_path / "dot.toml", model, "simcc", {"split_ratio": f"{ratio}.0"}))
    image = np.zeros((300, 400, 3), np.uint8)
    image[123, 257] = 255
    # Box edges are positions in pixel-centre coordinates: the first crop pixel's centre lies half a
    # crop pixel inside the edge, so edges at .5 give a crop on the image's pixel grid.
    boxes = np.array([[257 - 20.5, 123 - 30.5, 257 - 20.5 + W, 123 - 30.5 + H],  # 1:1, dot at crop (20, 30)
                      [257 - 3 * 20.5, 123 - 3 * 40.5, 257 + 3 * 27.5, 123 + 3 * 23.5]])  # x3
    kp = det.detect(image, boxes)
    assert kp.shape == (2, 21, 3)
    np.testing.assert_allclose(kp[0, :, :2], np.tile([257, 123], (21, 1)), atol=1e-6)
    # Scaled 1/3 with bilinear sampling, the dot's brightest crop pixel lies within 1.5 image pixels.
    assert np.abs(kp[1, :, :2] - [257, 123]).max() <= 1.5
    assert (kp[0, :, 2] == 1.0).all() and (kp[1, :, 2] > 0).all()


def test_keypoint_order_mapping_and_missing_joints(tmp_path: Path) -> None:
    """Constant SimCC outputs: model joint m peaks at bin (2m+1, 3m+2); the spec maps MediaPipe
    joint j to model joint PERMUTATION[j] and leaves the last joint out (-1)."""
    nx, ny = W * 2, H * 2
    sx = np.zeros((1, K, nx), np.float32)
    sy = np.zeros((1, K, ny), np.float32)
    for m in range(K):
        sx[0, m, 2 * m + 1] = 1.0
        sy[0, m, 3 * m + 2] = 0.5 + m / 100
    model = constant_graph(tmp_path / "const.onnx", {"simcc_x": sx, "simcc_y": sy})
    mapping = PERMUTATION[:-1] + [-1]
    det = hand_keypoint_detector(spec(tmp_path / "const.toml", model, "simcc", {"split_ratio": "2.0"},
                                      keypoints=str(mapping)))
    box = np.array([[99.5, 49.5, 99.5 + W, 49.5 + H]])   # 1:1 crop, crop pixel (0, 0) at image (100, 50)
    kp = det.detect(np.zeros((200, 200, 3), np.uint8), box)[0]
    m = np.array(mapping[:-1])
    np.testing.assert_allclose(kp[:-1, 0], 100 + (2 * m + 1) / 2)
    np.testing.assert_allclose(kp[:-1, 1], 50 + (3 * m + 2) / 2)
    np.testing.assert_allclose(kp[:-1, 2], 0.5 + m / 100, rtol=1e-6)
    assert np.isnan(kp[-1, :2]).all() and kp[-1, 2] == 0


def test_heatmap_model_end_to_end(tmp_path: Path) -> None:
    """Constant quadratic heatmaps at a stride of 4, decoded with parabola refinement, in a crop
    scaled by 2: the keypoints land where the peaks map to in the image."""
    h, w, stride = H // 4, W // 4, 4
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    rng = np.random.default_rng(3)
    peaks = np.column_stack([rng.uniform(1, w - 2, K), rng.uniform(1, h - 2, K)])
    hm = np.stack([0.9 - 0.02 * ((xx - px) ** 2 + (yy - py) ** 2) for px, py in peaks])[None]
    model = constant_graph(tmp_path / "hm.onnx", {"heatmaps": hm})
    det = hand_keypoint_detector(spec(tmp_path / "hm.toml", model, "heatmap", {"refine": '"parabola"'}))
    box = np.array([[10.0, 20.0, 10.0 + 2 * W, 20.0 + 2 * H]])
    kp = det.detect(np.zeros((300, 300, 3), np.uint8), box)[0]
    crop_xy = (peaks + 0.5) * stride - 0.5            # input pixel centres
    image_xy = (crop_xy + 0.5) * 2 + [10, 20]         # crop pixel centre -> image, from the box edge
    np.testing.assert_allclose(kp[:, :2], image_xy, atol=1e-4)  # float32 network outputs
    np.testing.assert_allclose(kp[:, 2], 0.9, atol=0.02)


def test_batched_over_images_equals_one_at_a_time(tmp_path: Path) -> None:
    model = dot_simcc_graph(tmp_path / "dot.onnx")
    det = hand_keypoint_detector(spec(tmp_path / "dot.toml", model, "simcc"), batch_size=3)
    rng = np.random.default_rng(0)
    images, boxes = [], []
    for i in range(4):
        im = np.zeros((120, 160, 3), np.uint8)
        pts = rng.integers(20, 100, (i + 1, 2))
        im[pts[:, 1], pts[:, 0]] = 255
        images.append(im)
        boxes.append(np.column_stack([pts - 16, pts + 16]).astype(float))
    boxes[2][0] = np.nan  # no hand here
    together = det.detect_many(images, boxes)
    for im, b, kp in zip(images, boxes, together):
        np.testing.assert_array_equal(kp, det.detect(im, b))
    assert np.isnan(together[2][0, :, :2]).all() and (together[2][0, :, 2] == 0).all()


def test_errors_name_file_and_shapes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "empty-cache"))
    with pytest.raises(ModelNotInstalledError, match="manus-capture models install mediapipe-hand"):
        hand_keypoint_detector("mediapipe-hand")

    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"\x08\x07garbage" * 100)
    with pytest.raises(ModelError, match=r"corrupt\.onnx: not a loadable ONNX model"):
        hand_keypoint_detector(spec(tmp_path / "corrupt.toml", corrupt, "simcc"))

    model = dot_simcc_graph(tmp_path / "dot.onnx")
    wrong = spec(tmp_path / "wrong.toml", model, "simcc")
    wrong.write_text(wrong.read_text().replace(f"input_size = [{W}, {H}]", "input_size = [256, 256]"))
    with pytest.raises(ModelError, match=rf"dot\.onnx: the model's input is \(N, 3, {H}, {W}\), "
                                         r"its specification gives \(N, 3, 256, 256\)"):
        hand_keypoint_detector(wrong)

    bad = tmp_path / "bad.toml"
    bad.write_text('model = "dot.onnx"\ninput_size = [48, 64]\n')
    with pytest.raises(ModelError, match=r"bad\.toml: kind: missing"):
        hand_keypoint_detector(bad)
    bad.write_text('kind = "simcc"\nmodel = "dot.onnx"\ninput_size = [48, 64]\nkeypoints = [0, 1]\n')
    with pytest.raises(ModelError, match=r"bad\.toml: keypoints: expected 21"):
        hand_keypoint_detector(bad)
    with pytest.raises(ModelError, match="needs a spec"):
        hand_keypoint_detector(model)


_SESSION_THREADS = """
import os, sys
os.sched_setaffinity(0, {int(sys.argv[2])})
from dataset_tools.keypoints.runtime import Session
session = Session(sys.argv[1], device="cpu")
allowed = set()
for task in os.listdir("/proc/self/task"):
    with open(f"/proc/self/task/{task}/status") as status:
        allowed |= {line.split()[1] for line in status if line.startswith("Cpus_allowed_list")}
print(session._session.get_session_options().intra_op_num_threads, " ".join(sorted(allowed)))
"""


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to see a thread leave its CPU set")
@pytest.mark.parametrize("omp", [None, "2"])
def test_a_session_keeps_its_threads_on_the_processs_cpus(tmp_path: Path, omp: str | None) -> None:
    """onnxruntime left to itself starts a thread per core of the machine, each pinned to its core
    outside the process's CPU set: detect run on one core ran its network on another. A session
    takes the CPUs the process may use, or OMP_NUM_THREADS where set (a Dask worker's one), and
    none of its threads leaves the process's CPUs."""
    model = dot_simcc_graph(tmp_path / "dot.onnx")
    cpu = min(os.sched_getaffinity(0))
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    env |= {} if omp is None else {"OMP_NUM_THREADS": omp}
    out = subprocess.run([sys.executable, "-c", _SESSION_THREADS, str(model), str(cpu)], env=env,
                         cwd=Path(__file__).resolve().parents[1],
                         capture_output=True, text=True, check=True).stdout.split()
    assert out[1:] == [str(cpu)]
    assert int(out[0]) == (1 if omp is None else 2)


# -- crop geometry ---------------------------------------------------------------------------------

def test_affine_maps_pixel_centres_and_rotates() -> None:
    # A rect of 32x32 image pixels centred between pixels 15 and 16 maps 1:1 onto a 32x32 crop.
    A = bx.affine_matrices(np.array([[15.5, 15.5, 32, 32, 0.0]]), 32, 32)
    np.testing.assert_allclose(A[0], [[1, 0, 0], [0, 1, 0]], atol=1e-12)
    # Turned by +90 degrees (crop up = image right), the image point right of the centre is up.
    A = bx.affine_matrices(np.array([[50.0, 40.0, 20, 20, np.pi / 2]]), 20, 20)
    centre = bx.apply_affine(A, np.array([[[50.0, 40.0], [60.0, 40.0]]]))[0]
    np.testing.assert_allclose(centre, [[9.5, 9.5], [9.5, -0.5]], atol=1e-9)
    back = bx.apply_affine(bx.invert_affine(A), centre[None])[0]
    np.testing.assert_allclose(back, [[50, 40], [60, 40]], atol=1e-9)
    # cv2.warpAffine agrees with the map: the crop of a rotated image equals the unrotated crop.
    rng = np.random.default_rng(1)
    image = rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)
    rot = np.ascontiguousarray(np.rot90(image))      # (x, y) -> (y, 79 - x)
    a, _ = bx.crop(image, np.array([[40.0, 30.0, 24, 24, 0.0]]), 24, 24)
    b, _ = bx.crop(rot, np.array([[30.0, 79 - 40.0, 24, 24, -np.pi / 2]]), 24, 24)
    np.testing.assert_array_equal(a, b)


def _hand(angle: float, centre=(200.0, 150.0), size: float = 40.0) -> np.ndarray:
    """An idealized upright hand (wrist at the bottom), turned by `angle` (clockwise on screen)."""
    kp = np.zeros((21, 2))
    kp[0] = (0, 1.0)
    for f, x in enumerate(np.linspace(-0.6, 0.6, 5)):
        for j in range(4):
            kp[1 + 4 * f + j] = (x * (1 + 0.1 * j), -0.2 - 0.35 * j)
    c, s = np.cos(angle), np.sin(angle)
    return kp @ np.array([[c, s], [-s, c]]) * size + centre


@pytest.mark.parametrize("angle", [0.0, 0.7, -2.0, np.pi])
def test_rects_from_keypoints_follow_the_hand_axis(angle: float) -> None:
    kp = _hand(angle)
    assert np.exp(1j * bx.hand_angle(kp[None])[0]) == pytest.approx(np.exp(1j * angle))
    rect = bx.rects_from_keypoints(kp[None])[0]
    upright = bx.rects_from_keypoints(_hand(0.0)[None])[0]
    assert rect[2] == pytest.approx(upright[2]) and rect[2] == rect[3]
    # The rect's centre turns with the hand about the hand's own centre.
    A = bx.affine_matrices(rect[None], 224, 224)
    local = bx.apply_affine(A, kp[None])[0]
    local_up = bx.apply_affine(bx.affine_matrices(upright[None], 224, 224), _hand(0.0)[None])[0]
    np.testing.assert_allclose(local, local_up, atol=1e-6)


def test_boxes_from_masks_keypoints_and_rig() -> None:
    masks = np.zeros((3, 20, 30), bool)
    masks[0, 5:9, 10:25] = True
    masks[2, 0, 0] = True
    np.testing.assert_array_equal(bx.boxes_from_masks(masks)[[0, 2]], [[10, 5, 24, 8], [0, 0, 0, 0]])
    assert np.isnan(bx.boxes_from_masks(masks)[1]).all()

    kp = np.zeros((2, 21, 3))
    kp[0, :, :2] = np.arange(42).reshape(21, 2)
    kp[0, :, 2] = 1
    kp[0, 20, 2] = 0  # not detected: not in the box
    np.testing.assert_array_equal(bx.boxes_from_keypoints(kp)[0], [0, 1, 38, 39])
    assert np.isnan(bx.boxes_from_keypoints(kp)[1]).all()

    # Two cameras 1 m in front of / behind a 10 cm hand at the origin.
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    R = np.stack([np.eye(3), np.diag([1.0, -1, -1])])
    rig = CameraRig(("front", "back"), np.stack([K, K]), None, R, np.array([[0, 0, 1.0], [0, 0, 1.0]]),
                    np.array([[640, 480], [640, 480]]))
    joints = np.column_stack([np.linspace(-0.05, 0.05, 21), np.linspace(-0.02, 0.03, 21), np.zeros(21)])
    boxes, angles = bx.boxes_from_joints(rig, joints)
    np.testing.assert_allclose(boxes[0], [320 - 25, 240 - 10, 320 + 25, 240 + 15])
    np.testing.assert_allclose(boxes[1], [320 - 25, 240 - 15, 320 + 25, 240 + 10])
    # The joints run from the wrist (-x, -y) towards +x, +y: "up" is to the lower right in the front
    # view (y down), to the upper right in the back view (image y flipped).
    np.testing.assert_allclose(angles, [np.arctan2(0.1, -0.05), np.arctan2(0.1, 0.05)], atol=1e-9)
    moved = joints + [0, 0, -1.5]  # behind the front camera (at z = -1, looking at +z)
    frames, frame_angles = bx.boxes_from_joints(rig, np.stack([joints, moved]))
    assert frames.shape == (2, 2, 4) and frame_angles.shape == (2, 2)
    assert np.isnan(frames[1, 0]).all() and np.isnan(frame_angles[1, 0]) and np.isfinite(frames[1, 1]).all()


def test_crop_keeps_dtype_and_fills_borders() -> None:
    image = np.full((10, 10, 3), 200, np.uint8)
    crops, _ = bx.crop(image, np.array([[4.5, 4.5, 40, 40, 0.3]]), 16, 16)
    assert crops.dtype == np.uint8 and crops.shape == (1, 16, 16, 3)
    assert (crops == 200).all()  # replicated border: no black frame around small images


def test_square_tiles_cover_the_frame_with_half_a_side_of_overlap() -> None:
    for width, height, count in ((320, 180, 3), (1280, 720, 3), (640, 480, 2), (180, 320, 3), (200, 200, 1)):
        corners = square_tiles(width, height)
        side = min(width, height)
        assert len(corners) == count, (width, height, corners)
        ends = corners + side
        assert (corners >= 0).all() and (ends[:, 0] <= width).all() and (ends[:, 1] <= height).all()
        assert ends[:, 0].max() == width and ends[:, 1].max() == height
        along = corners[:, 0] if width >= height else corners[:, 1]
        assert (np.diff(along) <= side / 2).all(), corners
