"""Pose refinement: every frame's 26 joint angles fitted to the images through MANUS-Hand.

After triangulation, IK and the 1-euro filter the angles carry the 2D detector's noise. Here they
are refined by rendering the subject's MANUS-Hand model, posed by them, into the views of every
frame group and minimising, over all frames at once (the model is fixed),

    E_t = w_photo L1(render, image on the hand mask) + w_mask L1(alpha, hand mask)
          + w_keypoints robust keypoint reprojection + w_smooth |second difference of the angles|^2
          + w_prior |angles - unrefined angles|^2

- The image terms compare only pixels off the object (which hides what is behind it), in windows
  around the hand; each frame's are normalized by its number of such pixels, so a frame seen by
  more cameras weighs no more.
- The keypoint term is Cauchy's robust loss log(1 + r^2 / s^2), as the detector's outliers are
  wrong by tens of pixels.
- The smoothness term ties a frame to its neighbours, in units of `smooth_deg` (angles) and
  `smooth_mm` (the wrist's translation).
- The prior keeps the unrefined angles as one more measurement (units `prior_deg`, `prior_mm`).
  Without it, the keypoint energy minimised to convergence on the demo's grasp took the fitted
  joints from 2.16 to 2.02 mm, with it to 1.42 mm (docs/refine.md).

Two stages: L-BFGS on the terms without images (cheap, deterministic), then Adam steps on all
terms, each rendering a few random views of every frame.

A frame whose E_t ends more than `diverged` (1.25) times higher than it started (or not finite)
keeps its unrefined angles and is counted as diverged. The refined angles go to DATASET.h5 as
`joint_angles_refined` beside the unrefined ones, with the per-frame loss (`refine/loss`,
`refine/loss_initial`, `refine/diverged`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from manus_capture.refine_views import PoseViews, pose_views
from manus_capture.splat.hand import HandGaussians
from manus_core.cameras import CameraRig
from manus_core.dataset import add_arrays, read_dataset
from manus_core.errors import RefineInputError
from manus_core.progress import Progress, silent
from manus_core.provenance import provenance_attrs

BONE_TOLERANCE_M = 0.5e-3   # a model whose bone lengths differ more from the take's is another subject's
_TRANSLATION = slice(3, 6)


@dataclass(frozen=True)
class RefineOptions:
    """Weights and steps of the refinement (module doc)."""

    keypoint_iterations: int = 150  # first stage: keypoints and smoothness only
    iterations: int = 20            # second stage: every term
    views_per_frame: int | None = 3  # views rendered per frame and step of the second stage (None: all)
    lr: float = 0.01                # Adam step: radians, and centimetres for the translation
    photometric: float = 0.3
    mask: float = 1.0
    keypoints: float = 0.1
    smoothness: float = 0.01
    prior: float = 0.01
    prior_deg: float = 10.0
    prior_mm: float = 5.0
    keypoint_scale_px: float = 3.0
    smooth_deg: float = 3.0
    smooth_mm: float = 3.0
    margin: int = 6                 # pixels around the hand's box in each window
    scale: float = 1.0              # image reduction before the windows are cut
    views_per_chunk: int = 96       # views rendered together (bounds memory)
    eps2d: float = 0.3              # the splat blur the model was trained with (checkpoint metadata)
    seed: int = 0
    backend: str = "auto"           # rasterize(): gsplat where installed and on CUDA
    # a frame whose E_t ends above this many times its start diverged; not 1: the smoothness term
    # couples neighbours, and a frame may give up a little of its own fit for theirs
    diverged: float = 1.25


@dataclass(frozen=True)
class RefineResult:
    """angles (T,26): refined where `refined`, else the input; loss_initial and loss (T,): E_t
    before and after (NaN where not refined); diverged (T,): refinement made E_t worse (see
    RefineOptions.diverged) and the input was kept."""

    angles: np.ndarray
    loss_initial: np.ndarray
    loss: np.ndarray
    refined: np.ndarray
    diverged: np.ndarray
    views: int
    seconds: float

    @property
    def frames_refined(self) -> int:
        return int(self.refined.sum())

    @property
    def frames_diverged(self) -> int:
        return int(self.diverged.sum())


def _step_units(dtype) -> torch.Tensor:
    """Per DOF, what one unit of the optimized offset is: a radian, or a centimetre of translation."""
    units = torch.ones(26, dtype=dtype)
    units[_TRANSLATION] = 0.01
    return units


class _Terms:
    """The per-frame terms of E for the frames being refined (rows 0..F-1)."""

    def __init__(self, model: HandGaussians, views: PoseViews, rows: np.ndarray, options: RefineOptions) -> None:
        self.model, self.views, self.options = model, views, options
        F = len(rows)
        slot = np.full(max(int(rows.max()), int(views.frame.max(initial=0))) + 1, -1)
        slot[rows] = np.arange(F)
        self.view_ids = np.flatnonzero(slot[views.frame] >= 0)
        self.view_frame = torch.as_tensor(slot[views.frame[self.view_ids]])
        self.pixels = views.valid[self.view_ids].sum((1, 2)).float()
        # the views stay in host memory, a chunk at a time goes to the model's device
        self.device = model.gaussians.means.device
        self.kp = views.keypoints[torch.as_tensor(rows)].to(self.device)          # (F,C,21,3)
        self.cam_viewmats, self.cam_Ks = views.cam_viewmats.to(self.device), views.cam_Ks.to(self.device)
        self.F = F

    def sample(self, per_frame: int | None, generator: torch.Generator) -> torch.Tensor:
        """Positions into view_ids: `per_frame` random views of every frame (all with None),
        ordered by frame."""
        n = len(self.view_ids)
        if per_frame is None:
            return torch.arange(n)
        order = torch.argsort(self.view_frame * 2.0 + torch.rand(n, generator=generator))   # by frame, shuffled
        frame = self.view_frame[order]
        first = torch.searchsorted(frame, frame, right=False)
        return torch.sort(order[torch.arange(n) - first < per_frame]).values

    def keypoints(self, angles: torch.Tensor) -> torch.Tensor:
        """(F,) mean Cauchy loss of the keypoint reprojection."""
        joints = self.model.skeleton.forward(angles)                 # (F,21,3)
        V, K = self.cam_viewmats, self.cam_Ks
        xc = torch.einsum("cij,fnj->fcni", V[:, :3, :3], joints) + V[None, :, None, :3, 3]
        uvw = torch.einsum("cij,fcnj->fcni", K, xc)
        uv = uvw[..., :2] / uvw[..., 2:].clamp_min(1e-6)
        w = self.kp[..., 2]
        r2 = ((uv - torch.nan_to_num(self.kp[..., :2])) ** 2).sum(-1) / self.options.keypoint_scale_px ** 2
        return (w * torch.log1p(r2)).sum((1, 2)) / w.sum((1, 2)).clamp_min(1e-6)

    def smoothness(self, angles: torch.Tensor) -> torch.Tensor:
        """(F,) squared second differences (in units of smooth_deg / smooth_mm), on the middle frame."""
        out = torch.zeros(self.F, dtype=angles.dtype, device=angles.device)
        if self.F < 3:
            return out
        sigma = torch.full((26,), np.radians(self.options.smooth_deg), dtype=angles.dtype, device=angles.device)
        sigma[_TRANSLATION] = self.options.smooth_mm / 1000
        d2 = (angles[:-2] - 2 * angles[1:-1] + angles[2:]) / sigma
        return out.index_add(0, torch.arange(1, self.F - 1, device=angles.device), (d2 ** 2).mean(1))

    def prior(self, angles: torch.Tensor, init: torch.Tensor) -> torch.Tensor:
        """(F,) squared distance from the unrefined angles, in units of prior_deg / prior_mm."""
        sigma = torch.full((26,), np.radians(self.options.prior_deg), dtype=angles.dtype, device=angles.device)
        sigma[_TRANSLATION] = self.options.prior_mm / 1000
        return (((angles - init) / sigma) ** 2).mean(1)

    def images(self, angles: torch.Tensor, chosen: torch.Tensor, backward: bool) -> torch.Tensor:
        """(F,) weighted image terms over the views `chosen` (positions into view_ids, by frame),
        each frame's normalized by its chosen views' pixels; with `backward`, each chunk's sum is
        backpropagated as it is computed, so memory holds one chunk's graph at a time."""
        o, v = self.options, self.views
        width, height = v.size
        dev = self.device
        frames = self.view_frame[chosen].to(dev)
        norm = 1 / torch.zeros(self.F, device=dev).index_add(0, frames, self.pixels[chosen].to(dev)).clamp_min(1)
        out = torch.zeros(self.F, device=dev)
        for start in range(0, len(chosen), o.views_per_chunk):
            pos = chosen[start:start + o.views_per_chunk]
            ids, frame = self.view_ids[pos.numpy()], frames[start:start + o.views_per_chunk]
            used, local = torch.unique(frame, return_inverse=True)
            posed = self.model.pose(angles[used])
            posed = {k: posed[k][local] for k in ("means", "covars", "A")}
            rgb, alpha = self.model.render_posed(posed, v.viewmats[ids].to(dev), v.Ks[ids].to(dev), width, height,
                                                 eps2d=o.eps2d, backend=o.backend)
            hand = v.hand[ids].to(dev).float()
            valid = v.valid[ids].to(dev).float()
            target = v.images[ids].to(dev).float() / 255 * hand[..., None]
            photo = ((rgb - target).abs().sum(-1) * valid).sum((1, 2)) / 3
            mask = ((alpha[..., 0] - hand).abs() * valid).sum((1, 2))
            chunk = torch.zeros(self.F, device=dev).index_add(0, frame, o.photometric * photo + o.mask * mask) * norm
            if backward:
                chunk.sum().backward()
            out += chunk.detach()
        return out


def fit_poses(model: HandGaussians, angles: np.ndarray, views: PoseViews, options: RefineOptions = RefineOptions(),
              progress: Progress = silent) -> RefineResult:
    """Refine angles (T,26) against `views` (module doc); rows with NaN angles are left as they are
    (the smoothness term then joins the fitted rows on either side of them). The model is not
    changed: its parameters' requires_grad is off during the fit and restored after.

    Two stages: at most `keypoint_iterations` L-BFGS iterations on the keypoint and smoothness terms
    alone (cheap: no rendering), then `iterations` Adam steps on all terms, each rendering
    `views_per_frame` random views of every frame. E_t before and after is measured on one fixed
    draw of views."""
    start_time = time.perf_counter()
    angles = np.asarray(angles, np.float64)
    rows = np.flatnonzero(np.isfinite(angles).all(1))
    if not len(rows):
        none = np.zeros(len(angles), bool)
        return RefineResult(angles.copy(), np.full(len(angles), np.nan), np.full(len(angles), np.nan), none, none,
                            0, 0.0)
    trainable = {name: p.requires_grad for name, p in model.named_parameters()}
    model.requires_grad_(False)
    try:
        return _fit(model, angles, rows, views, options, progress, start_time)
    finally:
        for name, p in model.named_parameters():
            p.requires_grad_(trainable[name])


def _fit(model: HandGaussians, angles: np.ndarray, rows: np.ndarray, views: PoseViews, options: RefineOptions,
         progress: Progress, start_time: float) -> RefineResult:
    T = len(angles)
    out_loss0, out_loss = np.full(T, np.nan), np.full(T, np.nan)
    refined, diverged = np.zeros(T, bool), np.zeros(T, bool)
    terms = _Terms(model, views, rows, options)
    use_images = (options.photometric > 0 or options.mask > 0) and len(terms.view_ids) > 0
    generator = torch.Generator().manual_seed(options.seed)
    scored = terms.sample(options.views_per_frame, generator)
    init = torch.as_tensor(angles[rows], dtype=torch.float32, device=terms.device)
    units = _step_units(init.dtype).to(terms.device)
    lower = torch.as_tensor(np.nan_to_num(model.skeleton.lower, neginf=-1e9), dtype=init.dtype, device=terms.device)
    upper = torch.as_tensor(np.nan_to_num(model.skeleton.upper, posinf=1e9), dtype=init.dtype, device=terms.device)
    offset = torch.zeros_like(init, requires_grad=True)

    def unrendered(current: torch.Tensor) -> torch.Tensor:
        """(F,) the terms that need no rendering."""
        return (options.keypoints * terms.keypoints(current) + options.smoothness * terms.smoothness(current)
                + options.prior * terms.prior(current, init))

    def energy(current: torch.Tensor, chosen: torch.Tensor | None, backward: bool) -> torch.Tensor:
        image = torch.zeros(terms.F, device=terms.device) if chosen is None else terms.images(current, chosen, backward)
        other = unrendered(current)
        if backward:
            other.sum().backward()
        return image + other.detach()

    with torch.no_grad():
        loss0 = energy(init, scored if use_images else None, backward=False)

    def clamp() -> None:
        with torch.no_grad():
            offset.copy_((torch.minimum(torch.maximum(init + offset * units, lower), upper) - init) / units)

    total = options.keypoint_iterations + (options.iterations if use_images else 0)
    progress("refine", 0, total)
    # stage 1, keypoints and smoothness: a smooth, deterministic energy, where L-BFGS converges in a
    # fraction of the steps Adam needs (150 Adam steps left 3.1 deg of a 6.8 deg perturbation that
    # exact keypoints pin down; L-BFGS, 0.35 deg)
    if options.keypoint_iterations:
        lbfgs = torch.optim.LBFGS([offset], lr=1, max_iter=options.keypoint_iterations, history_size=20,
                                  line_search_fn="strong_wolfe", tolerance_grad=1e-9, tolerance_change=1e-12)

        def closure() -> torch.Tensor:
            lbfgs.zero_grad()
            e = unrendered(init + offset * units).sum()
            e.backward()
            return e

        lbfgs.step(closure)
        clamp()
    progress("refine", options.keypoint_iterations, total)
    # stage 2, every term, on a few random views of every frame per step: Adam
    steps = options.iterations if use_images else 0
    optimizer = torch.optim.Adam([offset], lr=options.lr)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, 0.1 ** (1 / max(steps, 1)))  # tenfold down
    for step in range(steps):
        optimizer.zero_grad()
        current = init + offset * units
        # the terms backpropagate (chunk by chunk) into a leaf; carried on to the offset
        leaf = current.detach().requires_grad_(True)
        energy(leaf, terms.sample(options.views_per_frame, generator), backward=True)
        current.backward(leaf.grad)
        optimizer.step()
        scheduler.step()
        clamp()
        progress("refine", options.keypoint_iterations + step + 1, total)
    with torch.no_grad():
        final = init + offset * units
        loss1 = energy(final, scored if use_images else None, backward=False)
    bad = (~torch.isfinite(loss1) | (loss1 > options.diverged * loss0) | ~torch.isfinite(final).all(1)).cpu().numpy()
    result = angles.copy()
    result[rows[~bad]] = final.double().cpu().numpy()[~bad]
    out_loss0[rows], out_loss[rows] = loss0.cpu().numpy(), loss1.cpu().numpy()
    refined[rows[~bad]] = True
    diverged[rows[bad]] = True
    return RefineResult(result, out_loss0, out_loss, refined, diverged, len(terms.view_ids),
                        time.perf_counter() - start_time)


def check_subject(model: HandGaussians, bone_lengths: np.ndarray, model_path: Path | str, dataset: Path | str,
                  key: str) -> None:
    """RefineInputError when the model's bone lengths are not the take's (another subject's model)."""
    theirs = np.asarray(model.skeleton.bone_lengths, np.float64)
    diff = np.abs(theirs - np.asarray(bone_lengths, np.float64)).max()
    if diff > BONE_TOLERANCE_M:
        raise RefineInputError(f"{model_path}: a hand model of another subject than take {key} of {dataset} "
                               f"(bone lengths differ by up to {1000 * diff:.1f} mm)")


def refine_take(dataset: Path, key: str, take_path: Path, rig: CameraRig, model: HandGaussians,
                options: RefineOptions = RefineOptions(), model_path: Path | str = "the hand model",
                progress: Progress = silent) -> RefineResult:
    """Refine the filtered joint angles of take `key` of DATASET.h5 (recorded in take_path)
    against its images and the masks segment stored; see fit_poses."""
    ann = read_dataset(dataset)[key]
    check_subject(model, ann.bone_lengths, model_path, dataset, key)
    views = pose_views(take_path, dataset, ann, rig, ann.joint_angles, options.margin, options.scale, progress)
    return fit_poses(model, ann.joint_angles, views, options, progress)


def write_refined(dataset: Path, key: str, result: RefineResult, inputs: dict) -> None:
    """joint_angles_refined and refine/{loss, loss_initial, diverged} into take `key`, atomically,
    with the inputs that made them (provenance_refine)."""
    add_arrays(dataset, key, {"joint_angles_refined": result.angles, "refine/loss": result.loss,
                              "refine/loss_initial": result.loss_initial, "refine/diverged": result.diverged},
               {"refine_frames": result.frames_refined, "refine_diverged": result.frames_diverged,
                **provenance_attrs("refine", inputs)}, stage="refine")
