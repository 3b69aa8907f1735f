"""Gaussian models of the hand and the object from a session's takes, on any subset of cameras.

The camera ablation of evaluate (and of the demo) rebuilds both models from 5, 10, 20 or all
cameras: everything they are trained from is gathered once (frames, masks, poses) and each
`train` call picks its cameras.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dataset_tools.segmentation.takes import segment_take
from manus_capture.splat.gaussians import Gaussians
from manus_capture.splat.hand import HandConfig, HandGaussians, evaluate_hand, train_hand
from manus_capture.splat.losses import metric_lpips
from manus_capture.splat.takes import (
    HandFrames,
    crop_views,
    empty_scene,
    hand_frames_from_dataset,
    hand_masks_from_dataset,
    hand_views_from_take,
    object_views_from_take,
    spread_frames,
)
from manus_capture.splat.trainer import FAST_LR, SURFACE_EPS2D, SURFEL_THIN_M, ObjectConfig, train_object
from manus_capture.splat.trainer import evaluate as evaluate_object
from manus_capture.template import SPACING_M, capsule_distances, capsule_surface, capsule_template, template_capsules
from manus_core.cameras import CameraRig
from manus_core.dataset import take_key
from manus_core.errors import BuildError, TakeInputError
from manus_core.skeleton import HandSkeleton

HELD_OUT_POSES = 3        # hand poses kept out of training, for the held-out PSNR
HELD_OUT_VIEWS = 6        # every 6th view of the object is kept out of training when it is scored
# Contact is measured between Gaussian centres, so both models' centres should lie on their
# surfaces: both are surfels (Gaussians.surfels), the hand's starting on the capsule template. Its
# centres move with 7.5x 3DGS's steps. On make demo's session, with the view-dependent colour
# learnt (FAST_LR): at 2.5x the fingers' centres lay 1.06 mm from the true skin, the palm's 3.10,
# the hand scored 21.32 dB on its held-out pixels and the contacts 0.250 IoU; at 7.5x 1.47 and
# 2.61 mm (the template: 1.92 and 4.48), 22.31 dB, 0.275; at 25x 2.61 mm on the fingers, 22.60 dB
# and 0.276 (docs/splat.md). (An earlier round, before the silhouette term and the wrist, measured
# that "10x" steps made them wander 2-3 mm and settle 2.9 mm inside the skin.)
HAND_MEANS_LR = 1.2e-3
# The wrist the cameras see below the palm, which the template leaves out and surfels that only
# move cannot grow (18-35 % of the hand's mask pixels went uncovered without it, docs/splat.md):
# an elliptical cylinder with a rounded end, in parts of L, the wrist-to-middle-knuckle length,
# from an adult's generic proportions (wrist about 0.63 L broad and 0.43 L deep). It runs from
# inside the palm's base back to WRIST_REACH behind the wrist joint, its end cap beyond.
WRIST_HALF_WIDTH, WRIST_HALF_DEPTH = 0.32, 0.22
WRIST_START, WRIST_REACH = 0.10, 0.60
WRIST_BONE = 8                 # the middle metacarpal: it moves with the wrist and nothing else
# its points further apart than the template's: a smooth surface that touches nothing, and each
# Gaussian costs refine and the trainer alike (at the template's spacing the hand had 48 % more
# Gaussians and refine took 1.4 times as long)
WRIST_SPACING_M = 1.4 * SPACING_M


def _wrist(bone_lengths) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The wrist section's axis (its ends) and its half-width and half-depth, in metres."""
    length = float(np.linalg.norm(HandSkeleton(bone_lengths).rest_joints()[9]))
    ends = np.array([[0.0, WRIST_START, 0.0], [0.0, -WRIST_REACH, 0.0]]) * length
    return ends[0], ends[1], WRIST_HALF_WIDTH * length, WRIST_HALF_DEPTH * length


def wrist_section(bone_lengths=None, spacing: float = WRIST_SPACING_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (K,3), outward normals and their bone (all WRIST_BONE) on the wrist section of the
    rest hand (wrist at the origin, fingers along +y), about `spacing` apart."""
    a, b, w, h = _wrist(bone_lengths)
    # a round capsule of radius h stretched along x to half-width w: normals by the inverse stretch
    points, normals = capsule_surface(a, b, h, spacing * h / w)
    stretch = np.array([w / h, 1.0, 1.0])
    normals = normals / stretch
    return points * stretch, normals / np.linalg.norm(normals, axis=1, keepdims=True), np.full(len(points), WRIST_BONE)


def in_wrist(points: np.ndarray, bone_lengths=None) -> np.ndarray:
    """Whether rest-pose points (N,3) lie inside wrist_section's solid."""
    a, b, w, h = _wrist(bone_lengths)
    return capsule_distances(points * [h / w, 1.0, 1.0], a[None], b[None], np.array([h]))[:, 0] < 0


def surface_hand(bone_lengths, sh_degree: int = 1) -> HandGaussians:
    """A MANUS-Hand model of surfels on the capsule template of the subject's bone lengths and a
    wrist section (wrist_section): the outer surface of their union."""
    template = capsule_template(bone_lengths)
    points, normals, bones = wrist_section(bone_lengths)
    outside = capsule_distances(points, *template_capsules(bone_lengths)).min(1) > 0
    kept = ~in_wrist(template.points_rest, bone_lengths)
    return HandGaussians.on_surface(bone_lengths, np.concatenate([template.points_rest[kept], points[outside]]),
                                    np.concatenate([template.normals_rest[kept], normals[outside]]),
                                    np.concatenate([template.bone[kept], bones[outside]]), SURFEL_THIN_M,
                                    sh_degree=sh_degree)


def surface_hand_config(iterations: int, **changes) -> HandConfig:
    """HandConfig.surfels with the centre steps of HAND_MEANS_LR."""
    lr = dataclasses.replace(FAST_LR, means=HAND_MEANS_LR, means_final=HAND_MEANS_LR / 100)
    return HandConfig.surfels(iterations, **{"lr": lr, **changes})


@dataclass(frozen=True)
class TrainedModels:
    """MANUS-Hand and the object's Gaussians trained on one set of cameras; `metrics` holds the
    held-out-pose PSNR of the hand and the training-view PSNR of the object when asked for."""

    hand: HandGaussians
    object: Gaussians
    metrics: dict


@dataclass
class ModelInputs:
    """The calibrated rig, the hand take with annotate's poses and hand masks, the object take
    with its masks, and the training settings."""

    rig: CameraRig
    hand_take: Path
    object_take: Path
    hand_frames: HandFrames
    train_rows: np.ndarray
    test_rows: np.ndarray
    train_masks: np.ndarray       # (P,C,H,W) hand masks of train_rows, rig order
    test_masks: np.ndarray        # (Q,C,H,W) of test_rows
    object_masks: np.ndarray      # (C,H,W), rig order
    behind: dict[str, np.ndarray] | None = None   # the empty cube per camera (empty_scene)
    object_iterations: int = 400
    hand_iterations: int = 1000
    scale: float = 1.0
    seed: int = 0

    @classmethod
    def prepare(cls, rig, dataset: Path, hand_take: Path, object_take: Path, background_take: Path,
                poses: int = 20, object_masks: np.ndarray | None = None, **settings) -> "ModelInputs":
        """Choose `poses` training poses of the hand spread over the take; their hand masks are those
        `segment` stored in the dataset, else the hand take is segmented against the empty cube
        (and the object take too unless its masks are given).

        The poses are frame groups spread over the take (spread_frames), not only its holds.
        """
        frames = hand_frames_from_dataset(dataset, take_key(hand_take))
        rows = spread_frames(frames.angles, poses + HELD_OUT_POSES)
        if len(rows) < HELD_OUT_POSES + 2:
            raise BuildError(f"{hand_take}: only {len(rows)} frames with a fitted hand in {dataset}")
        test = rows[1::max(len(rows) // HELD_OUT_POSES, 1)][:HELD_OUT_POSES]
        train = np.setdiff1d(rows, test)
        try:
            train_masks, test_masks = (hand_masks_from_dataset(dataset, take_key(hand_take), r, rig.ids)
                                       for r in (train, test))
        except TakeInputError:
            seg = segment_take(hand_take, rig, background_take, None)
            hand_masks = seg.hand[:, seg.in_order(rig.ids)]
            train_masks, test_masks = hand_masks[train], hand_masks[test]
        if object_masks is None:
            seg = segment_take(object_take, rig, background_take, object_take)
            object_masks = seg.object[0][seg.in_order(rig.ids)]
        return cls(rig, Path(hand_take), Path(object_take), frames, train, test, train_masks, test_masks,
                   object_masks, empty_scene(background_take, rig.ids), **settings)

    def train_hand_model(self, cams: np.ndarray) -> HandGaussians:
        """MANUS-Hand trained on the cameras `cams` (indices into rig): surfels on the template and
        the wrist (surface_hand), hand_iterations steps on windows around the masks."""
        cams = np.asarray(cams)
        sub = self.rig.subset([self.rig.ids[i] for i in cams])
        poses, hand_views = hand_views_from_take(self.hand_take, sub, self.hand_frames, self.train_rows,
                                                 masks=self.train_masks[:, cams], scale=self.scale,
                                                 behind=self.behind)
        hand = surface_hand(self.hand_frames.bone_lengths)
        train_hand(hand, poses, [crop_views(v) for v in hand_views],
                   surface_hand_config(self.hand_iterations, seed=self.seed))
        return hand

    def train(self, cams: np.ndarray, evaluate: bool = False) -> TrainedModels:
        """Both models trained on the cameras `cams` (indices into rig); with `evaluate`, their
        metrics too."""
        cams = np.asarray(cams)
        sub = self.rig.subset([self.rig.ids[i] for i in cams])
        torch.manual_seed(self.seed)
        # CPU settings (ObjectConfig.surfels, HandConfig.surfels): hundreds of steps on windows
        # around the masks, scored on the whole views
        views = object_views_from_take(self.object_take, sub, masks=self.object_masks[cams], scale=self.scale,
                                       behind=self.behind)
        # with `evaluate`, every HELD_OUT_VIEWS-th view of the object is kept out of its training
        # (with fewer views, the last; with one, none, and the object's scores are NaN)
        held = np.arange(len(views)) % HELD_OUT_VIEWS == min(HELD_OUT_VIEWS // 2, len(views) - 1)
        held &= evaluate and len(views) > 1
        obj = train_object(crop_views(views.subset(np.flatnonzero(~held))),
                           ObjectConfig.surfels(self.object_iterations, seed=self.seed)).gaussians
        hand = self.train_hand_model(cams)
        metrics = {}
        if evaluate:
            test_poses, test_views = hand_views_from_take(self.hand_take, sub, self.hand_frames, self.test_rows,
                                                          masks=self.test_masks[:, cams],
                                                          scale=self.scale, behind=self.behind)
            # scored over the empty cube, as the cameras see the subjects, and over black as before
            # (silhouette pixels then keep the wall's share against the model's black)
            plain = [dataclasses.replace(v, backgrounds=None) for v in test_views]
            # LPIPS as the MANUS paper's table gives it, when its network is installed
            lpips = metric_lpips()
            hand_scores = evaluate_hand(hand, test_poses, test_views, eps2d=SURFACE_EPS2D, lpips=lpips)
            hand_black = evaluate_hand(hand, test_poses, plain, eps2d=SURFACE_EPS2D)
            object_scores = object_black = {"psnr": np.nan, "psnr_mask": np.nan, "ssim": np.nan}
            if held.any():
                held_views = views.subset(np.flatnonzero(held))
                object_scores = evaluate_object(obj, held_views, eps2d=SURFACE_EPS2D, lpips=lpips)
                object_black = evaluate_object(obj, dataclasses.replace(held_views, backgrounds=None),
                                               eps2d=SURFACE_EPS2D)
            metrics = {"hand_psnr_heldout_poses_db": hand_scores["psnr"],
                       "hand_psnr_mask_db": hand_scores["psnr_mask"], "hand_ssim": hand_scores["ssim"],
                       "hand_psnr_mask_black_db": hand_black["psnr_mask"],
                       "object_psnr_heldout_views_db": object_scores["psnr"],
                       "object_psnr_mask_db": object_scores["psnr_mask"], "object_ssim": object_scores["ssim"],
                       "object_psnr_mask_black_db": object_black["psnr_mask"],
                       "hand_lpips": hand_scores.get("lpips"), "object_lpips": object_scores.get("lpips"),
                       "hand_gaussians": len(hand), "object_gaussians": len(obj)}
        return TrainedModels(hand, obj, metrics)
