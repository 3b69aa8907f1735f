"""Pose refinement (manus_capture.refine) on views rendered from a known hand: perturbed poses come
back to within a number of degrees of the truth, through the keypoints, through the images alone,
and a frame that refinement cannot improve keeps its input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from manus_capture.refine import RefineOptions, check_subject, fit_poses
from manus_capture.refine_views import PoseViews
from manus_capture.splat.hand import HandGaussians
from manus_capture.splat.synthetic import look_at
from manus_core.errors import RefineInputError

W, H = 96, 96
CAMERAS = 6
FRAMES = 6


def finger_rms_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.sqrt(np.mean((a[:, 6:] - b[:, 6:]) ** 2))))


@pytest.fixture(scope="module")
def scene():
    """A hand model with a coloured, textured surface, a smooth 6-frame motion within the joint
    limits, 6 cameras around it at 96x96."""
    torch.manual_seed(0)
    model = HandGaussians.initialize(per_bone=40, sh_degree=0, seed=3)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        model.gaussians.params["sh0"].copy_(torch.randn(model.gaussians.params["sh0"].shape, generator=g) * 0.6)
        model.gaussians.params["opacities"].fill_(3.0)
    sk = model.skeleton
    t = np.linspace(0, 1, FRAMES)[:, None]
    mid = (np.nan_to_num(sk.lower, neginf=0.0) + np.nan_to_num(sk.upper, posinf=0.0)) / 2
    mid[:6] = 0
    truth = mid * (0.3 + 0.4 * t)                       # fingers closing together
    truth[:, 0] = 0.2 * t[:, 0]                         # a slow turn of the wrist
    centre = torch.as_tensor(sk.forward(truth[0]).mean(0), dtype=torch.float32)
    viewmats = torch.stack([look_at(centre + 0.45 * torch.tensor([math.cos(a), math.sin(a), 0.6]), centre)
                            for a in np.linspace(0, 2 * math.pi, CAMERAS, endpoint=False)])
    Ks = torch.tensor([[180.0, 0, W / 2], [0, 180.0, H / 2], [0, 0, 1]]).expand(CAMERAS, 3, 3)
    return {"model": model, "truth": truth, "viewmats": viewmats, "Ks": Ks}


def views_of(scene: dict, keypoint_noise_px: float) -> PoseViews:
    """The scene's renders; keypoints with Gaussian noise and 10 % outliers (30 px off)."""
    return PoseViews.rendered(scene["model"], scene["truth"], scene["viewmats"], scene["Ks"], W, H,
                              keypoint_noise_px, outlier_rate=0.1)


def perturbed(scene: dict, deg: float, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    start = scene["truth"].copy()
    start[:, 6:] += np.radians(deg) * rng.standard_normal(start[:, 6:].shape)
    start[:, 3:6] += 0.003 * rng.standard_normal((FRAMES, 3))
    return start


def test_refinement_brings_perturbed_poses_back(scene):
    """Finger angles 6.8 deg RMS off (and the wrist 3 mm) come back to under 2.5 deg, the issue's
    goal, with 0.5 px keypoint noise and 10 % outliers (at 96x96 a finger's last bone is about
    8 px long). Measured: 6.8 -> 1.8 deg."""
    start = perturbed(scene, 8.0)
    before = finger_rms_deg(start, scene["truth"])
    result = fit_poses(scene["model"], start, views_of(scene, 0.5),
                       RefineOptions(iterations=10, views_per_frame=2, eps2d=0.3))
    after = finger_rms_deg(result.angles, scene["truth"])
    assert before > 6.5 and after < 2.5, (before, after)
    assert result.frames_refined == FRAMES and result.frames_diverged == 0
    assert np.all(result.loss < result.loss_initial)


def test_the_images_alone_refine_the_pose(scene):
    """Without keypoints and smoothness (weights 0), the photometric and mask terms alone take 4.9
    deg RMS of perturbation down to under 4.2 deg: the renders carry the pose, if less sharply
    than keypoints do. Measured: 4.9 -> 3.4 deg (60 steps, 4 views per frame)."""
    start = perturbed(scene, 5.0, seed=2)
    result = fit_poses(scene["model"], start, views_of(scene, 0.0),
                       RefineOptions(keypoint_iterations=0, iterations=60, views_per_frame=4, keypoints=0.0,
                                     smoothness=0.0, eps2d=0.3))
    before, after = finger_rms_deg(start, scene["truth"]), finger_rms_deg(result.angles, scene["truth"])
    assert before > 4.5 and after < 4.2, (before, after)


def test_a_frame_refinement_cannot_improve_keeps_its_input(scene):
    """A frame already at the truth with exact keypoints and images has nothing to gain: whatever
    the steps do, it may not end worse than it started; frames without a fitted hand stay NaN."""
    start = scene["truth"].copy()
    start[2] = np.nan
    result = fit_poses(scene["model"], start, views_of(scene, 0.0),
                       RefineOptions(keypoint_iterations=5, iterations=3, views_per_frame=2, lr=0.05, eps2d=0.3))
    assert np.isnan(result.angles[2]).all() and not result.refined[2] and not result.diverged[2]
    kept = result.diverged
    np.testing.assert_array_equal(result.angles[kept], start[kept])
    assert np.all(result.loss[result.refined] <= result.loss_initial[result.refined])
    assert result.frames_refined + result.frames_diverged == FRAMES - 1


def test_a_model_of_another_subject_is_refused(scene):
    lengths = scene["model"].skeleton.bone_lengths
    check_subject(scene["model"], lengths + 0.0002, "hand.safetensors", "D.h5", "S/grasp")
    with pytest.raises(RefineInputError, match=r"hand\.safetensors.*another subject.*S/grasp of D\.h5"):
        check_subject(scene["model"], lengths * 1.1, "hand.safetensors", "D.h5", "S/grasp")
