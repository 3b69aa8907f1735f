"""Training on crops (takes.crop_views) gives the same image, and the same gradients, as training
on the whole images where the two overlap: the crop's shifted principal point must put every
pixel of the window exactly where the whole image has it."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from manus_capture.splat.hand import HandGaussians, evaluate_hand, random_poses
from manus_capture.splat.synthetic import look_at
from manus_capture.splat.takes import crop_views
from manus_capture.splat.trainer import Views

W, H = 128, 96
CAMERAS = 4
BACKGROUND = torch.zeros(3)


def with_random_colours(model: HandGaussians, seed: int) -> HandGaussians:
    """Random view-dependent colours, opacities and elongated shapes: a flat-coloured hand would hide
    a pixel shift everywhere but at its outline."""
    g = torch.Generator().manual_seed(seed)
    params = model.gaussians.params
    with torch.no_grad():
        params["sh0"].copy_(torch.randn(params["sh0"].shape, generator=g) * 0.8)
        params["shN"].copy_(torch.randn(params["shN"].shape, generator=g) * 0.3)
        params["opacities"].copy_(torch.randn(params["opacities"].shape, generator=g) + 1.0)
        # larger than the initialization's (they overlap) and not round, so rotations matter
        params["scales"].add_(0.3 + 0.5 * torch.randn(params["scales"].shape, generator=g))
    return model


def make_scene() -> dict:
    """A posed hand seen by 4 cameras (skewed, off-centre intrinsics; the hand off the image
    centre by a different amount in each), its renders as targets with masks alpha > 0.5, the
    views cut by crop_views, and a second, different hand model to train."""
    truth = with_random_colours(HandGaussians.initialize(per_bone=20, sh_degree=1, seed=1), 0)
    model = with_random_colours(HandGaussians.initialize(per_bone=20, sh_degree=1, seed=2), 1)
    angles = random_poses(1, truth.skeleton, torch.Generator().manual_seed(4), rotation=0.6, translation=0.0)[0]
    centre = truth.skeleton.forward(angles).mean(0)
    viewmats, Ks = [], []
    for c in range(CAMERAS):
        a = c * 2 * math.pi / CAMERAS + 0.3
        eye = centre + 0.45 * torch.tensor([math.cos(a), math.sin(a), 0.5])
        # aim beside the hand so that its window sits at a different place in every view
        aim = centre + 0.03 * torch.tensor([math.sin(3 * a), math.cos(2 * a), 0.0])
        viewmats.append(look_at(eye, aim))
        f = 150.0 + 10 * c
        Ks.append(torch.tensor([[f, 0.4, W / 2 - 3.3 + c], [0, 0.97 * f, H / 2 + 1.7 - c], [0, 0, 1]]))
    viewmats, Ks = torch.stack(viewmats), torch.stack(Ks)
    with torch.no_grad():
        images, alpha = truth.render(angles, viewmats, Ks, W, H, BACKGROUND)
    whole = Views(images, Ks, viewmats, alpha[..., 0] > 0.5)
    crops = crop_views(whole, margin=4)
    # where each window lies in its whole image, read off the principal point's shift
    offsets = (whole.Ks[:, :2, 2] - crops.Ks[:, :2, 2]).round().long()
    return {"truth": truth, "model": model, "angles": angles, "whole": whole, "crops": crops, "offsets": offsets}


@pytest.fixture(scope="module")
def scene() -> dict:
    return make_scene()


def window(images: torch.Tensor, offsets: torch.Tensor, w: int, h: int) -> torch.Tensor:
    """The (V,h,w,...) windows of images (V,H,W,...) whose top-left pixels are offsets (V,2) x, y."""
    return torch.stack([im[int(y):int(y) + h, int(x):int(x) + w] for im, (x, y) in zip(images, offsets)])


def test_crops_are_windows_with_their_principal_points(scene):
    whole, crops, offsets = scene["whole"], scene["crops"], scene["offsets"]
    # the crops are real cuts, at different places, so a shift has something to get wrong
    assert crops.width < W and crops.height < H
    assert len({tuple(o) for o in offsets.tolist()}) == CAMERAS
    assert bool((offsets > 0).all())
    # the shift is whole pixels; the intrinsics are otherwise untouched
    assert torch.allclose(whole.Ks[:, :2, 2] - crops.Ks[:, :2, 2], offsets.float(), atol=1e-4)
    assert torch.equal(whole.Ks[:, :2, :2], crops.Ks[:, :2, :2]) and torch.equal(whole.viewmats, crops.viewmats)
    assert torch.equal(crops.images, window(whole.images, offsets, crops.width, crops.height))
    assert torch.equal(crops.masks, window(whole.masks, offsets, crops.width, crops.height))
    # every mask pixel is inside its window: training on the crops sees the whole hand
    assert int(crops.masks.sum()) == int(whole.masks.sum()) > 0.05 * whole.masks.numel()


@torch.no_grad()
def test_render_of_a_crop_equals_the_window_of_the_whole_render(scene):
    whole, crops, offsets, angles = scene["whole"], scene["crops"], scene["offsets"], scene["angles"]
    w, h = crops.width, crops.height
    # The true hand rendered through the crops' intrinsics is the images crop_views cut: this
    # ties the principal point's shift to the cut without the offsets read off it.
    rgb, alpha = scene["truth"].render(angles, crops.viewmats, crops.Ks, w, h, BACKGROUND)
    assert float((rgb - crops.images).abs().max()) < 1e-5
    assert torch.equal(alpha[..., 0] > 0.5, crops.masks)
    # Any model: the crop's render is the window of the whole render, colour and alpha.
    model = scene["model"]
    rgb_whole, alpha_whole = model.render(angles, whole.viewmats, whole.Ks, W, H, BACKGROUND)
    rgb_crop, alpha_crop = model.render(angles, crops.viewmats, crops.Ks, w, h, BACKGROUND)
    assert float((rgb_crop - window(rgb_whole, offsets, w, h)).abs().max()) < 1e-5
    assert float((alpha_crop - window(alpha_whole, offsets, w, h)).abs().max()) < 1e-5
    # and the comparison would see a window one pixel off, in x or in y
    for shift in ([1, 0], [0, 1]):
        off = window(rgb_whole, offsets + torch.tensor(shift), w, h)
        assert float((rgb_crop - off).abs().max()) > 1e-2


def summed_losses(model: HandGaussians, angles: torch.Tensor, views: Views, targets: torch.Tensor,
                  weight: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
    """Sum over pixels of L1 colour + L1 alpha-vs-mask (the surfels' silhouette term), each
    pixel counted `weight` times (default once); returns the loss and rasterize()'s meta."""
    rgb, alpha, meta = model.render(angles, views.viewmats, views.Ks, views.width, views.height, BACKGROUND,
                                    return_meta=True)
    meta["means2d"].retain_grad()  # what a densification strategy reads
    per_pixel = (rgb - targets).abs().sum(-1) + (alpha[..., 0] - views.masks.float()).abs()
    if weight is not None:
        per_pixel = per_pixel * weight
    return per_pixel.sum(), meta


def gradients(model: HandGaussians, loss: torch.Tensor, meta: dict) -> dict[str, torch.Tensor]:
    model.zero_grad(set_to_none=True)
    loss.backward()
    # gaussians.params.means -> means
    grads = {name.rsplit(".", 1)[-1]: p.grad.clone() for name, p in model.named_parameters()
             if p.grad is not None}
    grads["means2d"] = meta["means2d"].grad.clone()
    return grads


def relative_difference(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    """Largest difference of any gradient, relative to the largest magnitude of that gradient."""
    assert a.keys() == b.keys()
    return max(float((a[k] - b[k]).abs().max() / b[k].abs().max().clamp_min(1e-12)) for k in a)


def test_gradient_on_crops_equals_the_masked_whole_image_gradient(scene):
    """A summed per-pixel loss on the crops has the gradient of the same loss on the whole
    images with the pixels outside the windows masked out: a training step on crops sees the
    same signal (the trainers' mean losses differ from it by the constant ratio of pixel counts)."""
    whole, crops, offsets, angles = scene["whole"], scene["crops"], scene["offsets"], scene["angles"]
    model = scene["model"]
    w, h = crops.width, crops.height
    grad_crop = gradients(model, *summed_losses(model, angles, crops, crops.targets(BACKGROUND)))

    def whole_gradient(offs: torch.Tensor) -> dict[str, torch.Tensor]:
        inside = torch.zeros(CAMERAS, H, W)
        for v, (x, y) in enumerate(offs.tolist()):
            inside[v, y:y + h, x:x + w] = 1
        return gradients(model, *summed_losses(model, angles, whole, whole.targets(BACKGROUND), inside))

    grad_whole = whole_gradient(offsets)
    for name in ("means", "quats", "scales", "opacities", "sh0", "shN", "means2d"):
        assert float(grad_whole[name].abs().max()) > 0, name
    # float32, summed in another order over other tiles: agreement to rounding (measured 1.3e-6)
    assert relative_difference(grad_crop, grad_whole) < 1e-5
    # a window one pixel off would be seen
    for shift in ([1, 0], [0, 1]):
        assert relative_difference(grad_crop, whole_gradient(offsets + torch.tensor(shift))) > 1e-2


@torch.no_grad()
def test_backgrounds_are_cut_with_the_views_and_renders_go_over_them(scene):
    """What a camera sees at a silhouette is partly the subject and partly the scene behind it.
    Views with backgrounds (the empty scene) put the renders over them: the exact model then
    scores as exact on its mask's pixels, where over black it cannot."""
    whole, offsets, angles, truth = scene["whole"], scene["offsets"], scene["angles"], scene["truth"]
    g = torch.Generator().manual_seed(7)
    # a textured scene behind the hand, brighter than the hand's own colours on average
    behind = 0.5 + 0.4 * torch.nn.functional.interpolate(torch.rand(CAMERAS, 3, H // 8, W // 8, generator=g),
                                                         size=(H, W), mode="bilinear").permute(0, 2, 3, 1)
    rgb, alpha = truth.render(angles, whole.viewmats, whole.Ks, W, H, BACKGROUND)
    seen = Views(rgb + (1 - alpha) * behind, whole.Ks, whole.viewmats, whole.masks, None, behind)
    crops = crop_views(seen, margin=4)
    assert torch.equal(crops.backgrounds, window(behind, offsets, crops.width, crops.height))
    assert torch.equal(crops.images, window(seen.images, offsets, crops.width, crops.height))
    # the targets: the image on and near the mask, the empty scene beyond
    far = torch.nn.functional.max_pool2d(crops.masks[:, None].float(), 5, 1, 2)[:, 0] == 0
    targets = crops.targets(BACKGROUND)
    assert torch.equal(targets[far], crops.backgrounds[far]) and torch.equal(targets[~far], crops.images[~far])
    assert 0 < int(far.sum()) < far.numel()
    over = evaluate_hand(truth, angles[None], [crops])
    on_black = evaluate_hand(truth, angles[None], [dataclasses.replace(crops, backgrounds=None)])
    # exact up to float32 rounding (measured 143 dB); over black the mask's edge pixels keep the
    # scene's share (measured 18.5 dB)
    assert over["psnr_mask"] > 60 and on_black["psnr_mask"] < 35, (over, on_black)
