"""Segmentation: masks against the simulated cube's per-pixel truth, the FreiHAND green screen, bad input."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from dataset_tools.segmentation import (BackgroundModel, PaintKey, SegmentationError, dominant_colour_key,
                                        fill_holes, hand_object_masks, object_colour, paint_key_from_object,
                                        paint_masks, remove_small)

W, H, N = 320, 180, 6


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


@pytest.fixture(scope="module")
def sim():
    from rig.layouts import make_rig
    from rig.sim.cube import SimulatedCube, true_cameras

    config = make_rig("cube53", cameras=N, resolution=(W, H))
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, paint=True, object="mug"))

    def frames(kind, seconds, light=1.0):
        # as SimCamera._encode: gaussian noise and JPEG
        cube = SimulatedCube(config, kind, 2.0)
        images, labels = [], []
        for s in seconds:
            rendered = [cube.render(c, cube.t0_ns + s * 1e9, labels=True) for c in range(N)]
            rng = np.random.default_rng([int(s * 100), 7])
            noisy = [np.clip(r.image * 255 * light + rng.standard_normal(r.image.shape) * 2.0, 0, 255).astype(np.uint8)
                     for r in rendered]
            images.append(np.stack([cv2.imdecode(cv2.imencode(".jpg", x, [cv2.IMWRITE_JPEG_QUALITY, 90])[1], 1)
                                    for x in noisy]))
            labels.append(np.stack([r.labels for r in rendered]))
        return np.stack(images), np.stack(labels)

    empty, _ = frames("calibration", [0.1, 0.5, 0.9], light=0.8)   # the LED level differs from the takes'
    backgrounds = [BackgroundModel.fit(empty[:, c]) for c in range(N)]
    obj, _ = frames("object", [0.5])
    grasp, grasp_labels = frames("grasp", [1.0], light=0.9)
    canon, canon_labels = frames("canonical", [1.0])
    return {"rig": true_cameras(config), "backgrounds": backgrounds, "object": obj[0], "grasp": grasp[0],
            "grasp_labels": grasp_labels[0], "canon": canon[0], "canon_labels": canon_labels[0]}


def _grasp_ious(sim) -> tuple[float, float]:
    model = object_colour(sim["object"], sim["backgrounds"])
    hand, obj, report = hand_object_masks(sim["grasp"], sim["backgrounds"], sim["rig"], model)
    truth = sim["grasp_labels"]
    assert report["multiview"]["voxels"] > 0
    return iou(hand, (truth == 1) | (truth == 3)), iou(obj, truth == 2)


def test_grasp_masks_against_truth(sim):
    hand, obj = _grasp_ious(sim)
    # measured 0.87 / 0.93 at 320x180: below the issue's 0.95 (see the xfail below)
    assert hand >= 0.85 and obj >= 0.9, (hand, obj)


@pytest.mark.xfail(strict=True, reason="issue 7 target (IoU >= 0.95) not reached yet: finger tips over the "
                                       "skin-coloured table are missed")
def test_grasp_masks_issue_target(sim):
    hand, obj = _grasp_ious(sim)
    assert hand >= 0.95 and obj >= 0.95


def test_paint_masks_against_truth(sim):
    key = paint_key_from_object(sim["object"], sim["backgrounds"])
    hand, _, _ = hand_object_masks(sim["canon"], sim["backgrounds"], sim["rig"])
    truth = sim["canon_labels"]
    assert iou(hand, (truth == 1) | (truth == 3)) >= 0.9
    paint, report = paint_masks(sim["canon"], hand, key)
    assert not report["warnings"]
    seen = [c for c in range(N) if (truth[c] == 3).sum() >= 50]
    assert seen
    scores = [iou(paint[c], truth[c] == 3) for c in seen]
    # measured 0.43-0.77 per view at 320x180; the issue asks 0.9 (not reached)
    assert min(scores) >= 0.35, scores


def test_paint_colour_not_found_warns(sim):
    hand, _, _ = hand_object_masks(sim["canon"], sim["backgrounds"], sim["rig"])
    blue = PaintKey.from_swatch([255, 40, 40])
    paint, report = paint_masks(sim["canon"], hand, blue)
    assert not paint.any()
    assert "no paint colour found" in report["warnings"][0]


def test_bad_input(sim):
    with pytest.raises(SegmentationError, match="grey"):
        PaintKey.from_swatch([128, 128, 128])
    with pytest.raises(SegmentationError, match="expected frames"):
        BackgroundModel.fit(np.zeros((0, 4, 4, 3)))
    # no background at all: no view can be segmented, the object take has nothing to learn from
    with pytest.raises(SegmentationError, match="not seen"):
        object_colour(sim["object"], [None] * N)
    # a missing view (no background) gives an empty mask there, the others still carve
    bgs = list(sim["backgrounds"])
    bgs[1] = None
    hand, _, report = hand_object_masks(sim["canon"], bgs, sim["rig"])
    assert not hand[1].any() and hand[0].any()


def test_fill_and_remove():
    mask = np.zeros((20, 20), bool)
    mask[2:10, 2:10] = True
    mask[5, 5] = False
    mask[15, 15] = True
    assert fill_holes(mask)[5, 5]
    assert not remove_small(mask, 2)[15, 15] and remove_small(mask, 2)[3, 3]


def test_freihand_green_key(shared_data):
    folder = shared_data / "hand_samples" / "freihand"
    images = [cv2.imread(str(folder / f"{355 + k * 32560:08d}.jpg")).astype(np.float32) for k in range(4)]
    # the published composites replace the green screen: pixels changed in all three are background
    changed = np.all([np.abs(c - images[0]).max(axis=-1) > 25 for c in images[1:]], axis=0)
    key = dominant_colour_key(images[0])
    assert key.colour[0] > 0.4   # green share: the key found the green screen
    mask = key.key(images[0])
    mask = fill_holes(remove_small(cv2.medianBlur(mask.astype(np.uint8), 5) > 0, 30), 30)
    assert iou(mask, changed) >= 0.9
