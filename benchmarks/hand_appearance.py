"""Where MANUS-Hand's held-out PSNR on the hand's pixels goes, on a finished demo.

    python benchmarks/hand_appearance.py DEMO [--iterations 1000] [--refined]

DEMO is the output folder of `manus-capture demo`. MANUS-Hand is trained as the demo trains it
(ModelInputs: the hand take's per-frame IK fits from annotate, segment's hand masks, every camera), once more
with the simulator's true joint angles and bone lengths in their place (an ablation: scoring
code may read the truth, the pipeline never does), and each is scored on the held-out poses:

- the PSNR on the hand's mask, as the demo reports it (`hand_psnr_mask_db`: the hand rendered over
  the empty cube, as the cameras see it), and rendered over black as before;
- the same on the poses it was trained on (every camera): a model that scores little more there
  than on the held-out poses does not fit its own images, one that scores much more does not
  carry what it learnt to new poses;
- the same split by each pixel's distance to the mask's edge: share of the mask's pixels, PSNR,
  share of the squared error, and the share the model leaves uncovered (alpha under 0.5);
- with --refined, the poses of the training and held-out rows refined against their images through
  the first model (refine without its smoothness term), the model trained again on them and
  scored on the held-out poses as annotate gave them and as refined: what the poses' error costs;
- the texture floor: the PSNR, on the pixels over 2.5 px inside the mask, of the image blurred
  by a Gaussian of 1 px against itself, what a model as sharp as that but exact in shape and
  colour would score there.

Prints markdown tables, the figures docs/splat.md quotes.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import cv2
import numpy as np
import torch

from dataset_tools.calibration.formats import load_cameras
from manus_capture.builder import ModelInputs
from manus_capture.pose_score import truth_at_groups
from manus_capture.refine import RefineOptions, fit_poses
from manus_capture.refine_views import pose_views
from manus_capture.splat.hand import HandGaussians, evaluate_hand
from manus_capture.splat.takes import HandFrames, hand_views_from_take
from manus_capture.splat.trainer import SURFACE_EPS2D
from manus_core.dataset import read_dataset, take_key

BANDS = ((0.0, 1.5), (1.5, 2.5), (2.5, 4.0), (4.0, 7.0), (7.0, np.inf))   # px from the mask's edge
INNER_PX = 2.5


def _psnr(squared: float, count: float) -> float:
    return float(-10 * np.log10(squared / max(count, 1)))


def band_scores(rendered: np.ndarray, alpha: np.ndarray, targets: np.ndarray, masks: np.ndarray) -> list[dict]:
    """Per band of BANDS over views (V,H,W,...): share of mask pixels, PSNR, share of the squared
    error, share uncovered (alpha < 0.5)."""
    dist = np.stack([cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, 3) for m in masks])
    error = ((rendered - targets) ** 2).sum(-1)
    total_px, total_err = masks.sum(), error[masks].sum()
    rows = []
    for lo, hi in BANDS:
        sel = masks & (dist > lo) & (dist <= hi)
        rows.append({"band": (lo, hi), "share": sel.sum() / total_px, "psnr": _psnr(error[sel].sum(), 3 * sel.sum()),
                     "error_share": error[sel].sum() / total_err, "uncovered": (alpha[sel] < 0.5).mean()})
    return rows


def texture_floor(images: np.ndarray, masks: np.ndarray, sigma: float = 1.0) -> float:
    """PSNR over the pixels more than INNER_PX inside the masks of the images blurred within their
    masks (normalized convolution) against the images."""
    squared = count = 0.0
    for image, mask in zip(images, masks):
        m = mask.astype(np.float32)
        blurred = cv2.GaussianBlur(image * m[..., None], (0, 0), sigma)
        blurred /= np.maximum(cv2.GaussianBlur(m, (0, 0), sigma), 1e-6)[..., None]
        inner = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3) > INNER_PX
        squared += ((blurred - image)[inner] ** 2).sum()
        count += 3 * inner.sum()
    return _psnr(squared, count)


def _score(inputs: ModelInputs, test_frames: HandFrames | None = None) -> tuple:
    """Train on every camera; held-out PSNR on the mask (over the empty scene, and over black),
    the training poses' (over the empty scene) and the band rows; the views' images and masks;
    the model. The held-out poses are test_frames' when given."""
    hand = inputs.train_hand_model(np.arange(len(inputs.rig)))
    train_poses, train_views = hand_views_from_take(inputs.hand_take, inputs.rig, inputs.hand_frames,
                                                    inputs.train_rows, masks=inputs.train_masks,
                                                    behind=inputs.behind)
    trained = evaluate_hand(hand, train_poses, train_views, eps2d=SURFACE_EPS2D)["psnr_mask"]
    poses, views = hand_views_from_take(inputs.hand_take, inputs.rig, test_frames or inputs.hand_frames,
                                        inputs.test_rows, masks=inputs.test_masks, behind=inputs.behind)
    black = torch.zeros(3)
    rendered, alphas, targets, images, masks = [], [], [], [], []
    with torch.no_grad():
        for pose, view in zip(poses, views):
            if not len(view):
                continue
            rgb, alpha = hand.render(pose, view.viewmats, view.Ks, view.width, view.height, black,
                                     eps2d=SURFACE_EPS2D)
            rendered.append(view.composite(rgb, alpha, black).clamp(0, 1).numpy())
            alphas.append(alpha[..., 0].numpy())
            targets.append(view.targets(black).numpy())
            images.append(view.images.numpy())
            masks.append(view.masks.numpy())
    rendered, alphas, targets, images, masks = (np.concatenate(x) for x in (rendered, alphas, targets, images, masks))
    demo_figure = evaluate_hand(hand, poses, views, eps2d=SURFACE_EPS2D)["psnr_mask"]
    on_black = evaluate_hand(hand, poses, [dataclasses.replace(v, backgrounds=None) for v in views],
                             eps2d=SURFACE_EPS2D)["psnr_mask"]
    return demo_figure, on_black, trained, band_scores(rendered, alphas, targets, masks), images, masks, hand


def refined_frames(inputs: ModelInputs, hand: HandGaussians, dataset: Path) -> HandFrames:
    """The training and held-out rows' poses refined against their images through `hand`: refine's
    defaults without the smoothness term, which the hand take runs through its poses too fast for
    (docs/splat.md, "Training poses")."""
    rows = np.concatenate([inputs.train_rows, inputs.test_rows])
    angles = np.full_like(inputs.hand_frames.angles, np.nan)
    angles[rows] = inputs.hand_frames.angles[rows]
    ann = read_dataset(dataset)[take_key(inputs.hand_take)]
    views = pose_views(inputs.hand_take, dataset, ann, inputs.rig, angles)
    result = fit_poses(hand, angles, views, RefineOptions(smoothness=0.0, eps2d=SURFACE_EPS2D))
    refined = inputs.hand_frames.angles.copy()
    refined[rows] = result.angles[rows]
    return dataclasses.replace(inputs.hand_frames, angles=refined)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("demo", type=Path)
    parser.add_argument("--iterations", type=int, default=1000, help="hand training steps (the demo's default)")
    parser.add_argument("--refined", action="store_true",
                        help="two more rows: the poses refined against the images through the first row's model")
    args = parser.parse_args()
    session = args.demo / "session"
    hand_take, object_take, background = (next(session.glob(f"*-{kind}*"))
                                          for kind in ("hand", "object", "calibration"))
    dataset = args.demo / "DATASET.h5"
    inputs = ModelInputs.prepare(load_cameras(args.demo / "calib"), dataset, hand_take, object_take, background,
                                 hand_iterations=args.iterations)
    truth = truth_at_groups(hand_take, read_dataset(dataset)[take_key(hand_take)].frame_ns)
    true_frames = dataclasses.replace(inputs.hand_frames, angles=truth["joint_angles"],
                                      bone_lengths=truth["bone_lengths"])
    print("| poses | hand PSNR on the mask (dB) | over black | training poses | "
          + " | ".join(f"{lo:g}-{hi:g} px" for lo, hi in BANDS) + " |")
    print("|---|---|---|---|" + "---|" * len(BANDS))

    def row(name: str, frames: HandFrames, test_frames: HandFrames | None = None) -> tuple:
        psnr, on_black, trained, bands, images, masks, hand = _score(dataclasses.replace(inputs, hand_frames=frames),
                                                                     test_frames)
        cells = " | ".join(f"{b['psnr']:.1f} dB, {100 * b['share']:.0f} % of pixels, {100 * b['error_share']:.0f} % of "
                           f"error, {100 * b['uncovered']:.0f} % uncovered" for b in bands)
        print(f"| {name} | {psnr:.2f} | {on_black:.2f} | {trained:.2f} | {cells} |", flush=True)
        return images, masks, hand

    images, masks, hand = row("annotate", inputs.hand_frames)
    row("true (ablation)", true_frames)
    if args.refined:
        refined = refined_frames(inputs, hand, dataset)
        row("refined, trained on; held out at annotate's", refined, inputs.hand_frames)
        row("refined, trained on and held out", refined)
    print(f"\ntexture floor: the held-out images blurred by 1 px against themselves, over {INNER_PX:g} px inside "
          f"the mask: {texture_floor(images, masks):.1f} dB")


if __name__ == "__main__":
    main()
