"""Target detection against upstream ground truth and exact synthetic corners."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from dataset_tools.calibration.boards import board_from_dict
from dataset_tools.calibration.detect import BoardDetector, TagDetector


def upstream_truth(txt) -> np.ndarray:
    """AprilTag library corners (T,4,2) converted to OpenCV's corner order.

    Upstream lists corners counter-clockwise from the tag's bottom-left; OpenCV clockwise from the
    top-left: reversed, then rolled by two."""
    quads = np.array([[float(x) for x in re.findall(r"[-\d.]+", line)][1:] for line in txt.read_text().splitlines()
                      if line.strip()]).reshape(-1, 4, 2)
    return np.roll(quads[:, ::-1], 2, axis=1)


def test_apriltag_corners_match_upstream(shared_data):
    root = shared_data / "apriltag_detection"
    detector = TagDetector(refine="apriltag")
    found, total, worst = 0, 0, 0.0
    for image in sorted(root.glob("*.jpg")):
        truth = upstream_truth(image.with_suffix(".txt"))
        total += len(truth)
        ids, quads, info = detector.detect_tags(cv2.imread(str(image), cv2.IMREAD_GRAYSCALE))
        assert set(ids.tolist()) <= {0}  # upstream's images hold tag 0 only
        for q in truth:
            d = np.linalg.norm(quads.mean(axis=1) - q.mean(axis=0), axis=1)
            if len(d) and d.min() < 3:
                found += 1
                worst = max(worst, float(np.linalg.norm(quads[d.argmin()] - q, axis=1).max()))
    assert total == 47
    assert found >= 46
    assert worst < 0.2


def render_tag(tag_id: int, corner: tuple[float, float], side: float, shape=(240, 320)) -> np.ndarray:
    """A tag whose outer black border spans exactly [x0, x0+side] x [y0, y0+side] in OpenCV's
    convention (pixel centres on integers), each pixel the exact area average of what it sees."""
    cells = np.full((10, 10), 235.0)  # white quiet zone around the 8x8 tag
    marker = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11).generateImageMarker(tag_id, 8)
    cells[1:9, 1:9] = np.where(marker > 0, 235, 20)
    cell = side / 8

    def overlap(start: float, n: int) -> np.ndarray:  # (10, n): share of pixel i inside cell k
        lo = start - cell + cell * np.arange(10)[:, None]
        px = np.arange(n)[None, :]
        return np.clip(np.minimum(lo + cell, px + 0.5) - np.maximum(lo, px - 0.5), 0, 1)

    oy, ox = overlap(corner[1], shape[0]), overlap(corner[0], shape[1])
    covered = oy.sum(axis=0)[:, None] * ox.sum(axis=0)[None, :]
    image = oy.T @ cells @ ox + 128.0 * (1 - covered)
    return image.round().astype(np.uint8)


@pytest.mark.parametrize("corner, side", [((100.0, 80.0), 64.0), ((100.3, 80.7), 57.2), ((41.6, 33.2), 22.4)])
def test_edge_refined_tag_corners_are_exact_in_opencv_convention(corner, side):
    image = render_tag(7, corner, side)
    truth = np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) * side + corner
    ids, quads, _ = TagDetector().detect_tags(image)
    assert ids.tolist() == [7]
    assert np.abs(quads[0] - truth).max() < 0.05
    # the AprilTag quad fit alone is off by a sizeable part of a pixel: the reason for edges
    _, raw, _ = TagDetector(refine="apriltag").detect_tags(image)
    assert np.abs(raw[0] - truth).max() > 0.25


def test_inverted_tags_need_the_inverted_flag():
    image = 255 - render_tag(3, (90.0, 70.0), 60.0)
    assert len(TagDetector().detect_tags(image)[0]) == 0
    assert TagDetector(inverted=True).detect_tags(image)[0].tolist() == [3]


def test_chessboard_detection_ids_and_quality(shared_data):
    board = board_from_dict({"type": "chessboard", "cols": 9, "rows": 6, "square": 0.025})
    gray = cv2.imread(str(shared_data / "opencv_stereo_chessboard" / "left01.jpg"), cv2.IMREAD_GRAYSCALE)
    det = BoardDetector(board).detect(gray)
    assert det.ids.tolist() == list(range(54))
    assert det.info["fraction"] == 1.0 and 25 < det.info["spacing_px"] < 45
    # neighbours along a row are one square apart in the image too (no scrambled order)
    step = np.linalg.norm(np.diff(det.xy.reshape(6, 9, 2), axis=1), axis=2)
    assert step.max() < 2 * np.median(step)
