"""The whole MANUS capture pipeline on the simulated rig, scored against its ground truth.

`run_demo` records a session (calibration, hand, object, grasp and canonical takes) with the
simulated cube, then runs every stage the way a lab would on real recordings: sync reports,
calibrate, annotate, segment, reconstruct (object and MANUS-Hand), refine (the poses against the
images), contacts and evaluate. Each
stage is scored against ground_truth.h5, and the camera ablation retrains the models on 5, 10,
20 and all cameras. Outputs in DIR: session/, calib/, DATASET.h5, models/, images/,
summary.json and report.html.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dataset_tools.annotate import AnnotateOptions, annotate
from dataset_tools.calibration.formats import load_cameras
from dataset_tools.calibration.rig import calibrate_rig
from dataset_tools.segmentation.takes import segment_take, write_masks
from dataset_tools.sync import sync_take
from manus_capture.builder import ModelInputs
from manus_capture.contacts import contact_image, model_contacts, write_contacts
from manus_capture.evaluate import (
    canonical_pose,
    mask_scores,
    pick_views,
    render_contacts,
    score_contacts,
    spread_cameras,
)
from manus_capture.pose_score import pose_errors, truth_at_groups
from manus_capture.refine import RefineOptions, refine_take, write_refined
from manus_capture.report import ablation_png, keypoint_overlay, mask_comparison, write_html
from manus_capture.splat.checkpoint import save_checkpoint
from manus_capture.splat.takes import truth_cameras
from manus_capture.splat.trainer import SURFACE_EPS2D
from manus_capture.surface_score import surface_errors
from manus_capture.template import capsule_template
from manus_core.dataset import read_dataset, take_key
from manus_core.errors import DemoError
from manus_core.fileio import write_atomic
from manus_core.ground_truth import GroundTruth
from manus_core.rotations import rotation_angle_deg
from manus_core.skeleton import HandSkeleton
from manus_core.take import Take
from rig.layouts import make_rig
from rig.record import RecordOptions, record_take
from rig.sim.hand import subject_shape
from rig.sim.subject import with_sim_subject

from .evaluate import MIN_PAINT_PX

SURFACE_BAND_M = 0.003    # Gaussians this close to the true hand surface are scored on its contact

TAKES = (("calibration", "00-calibration"), ("hand", "01-hand"), ("object", "02-object"),
         ("grasp", "03-grasp1"), ("canonical", "04-canonical1"))


@dataclass(frozen=True)
class DemoConfig:
    """Sizes of the demo. The defaults fit a laptop: minutes on two cores."""

    cameras: int = 24
    resolution: tuple[int, int] = (320, 180)
    fps: float = 30.0
    subject: str = "s01"
    object: str = "mug"
    # the canonical pose is the median of the canonical take's frames: at 20 fps, the 2 frames of a
    # 0.1 s take left its finger angles 4.0 deg RMS off, the 10 of 0.5 s 3.6 deg (docs/contacts.md)
    durations: dict = field(default_factory=lambda: {"calibration": 0.1, "hand": 2.0, "object": 0.1,
                                                     "grasp": 2.0, "canonical": 0.5})
    views: tuple[int, ...] = (5, 10, 20, 0)        # camera ablation; 0 = all cameras
    eval_views: int = 10
    object_iterations: int = ModelInputs.object_iterations
    hand_iterations: int = ModelInputs.hand_iterations
    hand_frames: int = 20
    refine_iterations: int = 20                     # refine's second stage (rendering MANUS-Hand)
    scale: float = 1.0
    tau: float = 0.004
    seed: int = 0
    true_calibration: bool = False                  # skip calibrate and use the simulator's cameras
    # ablation: annotate from the true joints with the simulated detector's noise instead of the
    # ONNX detector on the frames (it reads ground_truth.h5, so only when named)
    simulated_keypoints: bool = False


@dataclass
class Stage:
    name: str
    seconds: float
    metrics: dict


class Demo:
    """One demo run: its folder, its configuration and the stages done so far."""

    def __init__(self, out: Path, config: DemoConfig, say: Callable[[str], None] = print) -> None:
        self.out = Path(out)
        self.config = config
        self.say = say
        self.stages: list[Stage] = []
        self.session = self.out / "session"
        self.calib = self.out / "calib"
        self.dataset = self.out / "DATASET.h5"
        self.models = self.out / "models"
        self.images = self.out / "images"
        self.take = {kind: self.session / name for kind, name in TAKES}
        self.summary: dict = {}

    def stage(self, name: str, fn: Callable[[], dict]) -> dict:
        self.say(f"[{len(self.stages) + 1}] {name} ...")
        start = time.perf_counter()
        try:
            metrics = fn()
        except Exception as exc:
            raise DemoError(f"demo stage {name!r} failed: {exc}") from exc
        stage = Stage(name, time.perf_counter() - start, metrics)
        self.stages.append(stage)
        shown = ", ".join(f"{k} {_fmt(v)}" for k, v in metrics.items() if not isinstance(v, (dict, list)))
        self.say(f"    {shown} ({stage.seconds:.1f} s)")
        return metrics

    # ------------------------------------------------------------------ stages

    def record(self) -> dict:
        c = self.config
        rig = make_rig("cube53", cameras=c.cameras, resolution=c.resolution, fps=c.fps, sync="software-trigger",
                       seed=c.seed)
        rig = with_sim_subject(rig, obj=c.object, paint=True, subject=c.subject)
        # a new session: the bones a run before estimated (annotate reads them when the file exists)
        # must not stand in for this run's hand take
        shutil.rmtree(self.session / "subjects", ignore_errors=True)
        frames = 0
        for kind, name in TAKES:
            result = record_take(rig, self.session, name, kind, c.durations[kind], RecordOptions(
                force=True, subject=c.subject, obj=c.object, use_leds=False,
                label_frames=[1] if kind in ("object", "canonical") else []))
            if result.status != "complete":
                raise DemoError(f"take {name}: {result.status} ({result.reason})")
            frames += result.frames
        return {"takes": len(TAKES), "cameras": c.cameras, "frames": frames}

    def sync(self) -> dict:
        found, true_drops, spreads = 0, 0, []
        for kind, _ in TAKES:
            report = sync_take(self.take[kind], force=True, optical=False)
            true_drops += int(GroundTruth.of_take(self.take[kind]).frames.dropped.sum())
            found += sum(cam["frames_dropped"] for cam in report["cameras"].values())
            if report["spread_ms"]["p95"] is not None:
                spreads.append(report["spread_ms"]["p95"])
        return {"drops_found": found, "drops_true": true_drops, "spread_p95_ms": max(spreads, default=float("nan"))}

    def calibrate(self) -> dict:
        if self.config.true_calibration:
            self.calib.mkdir(parents=True, exist_ok=True)
            truth_cameras(self.take["calibration"]).save(self.calib / "cameras.json")
            return {"source": "simulator (--true-calibration)"}

        # nothing but the take and the session's tags.json, as `manus-capture calibrate rig TAKE`:
        # every camera's intrinsics and pose from the tags it sees
        result = calibrate_rig(take=self.take["calibration"], tags=self.session / "tags.json", method="tags",
                               output=self.calib, force=True)
        # scoring only: the calibration above never saw the simulator's cameras
        err = camera_errors(load_cameras(self.calib / "cameras.json"), truth_cameras(self.take["calibration"]))
        return {"fx_err_pct_median": float(np.median(err["fx_pct"])), "fx_err_pct_max": float(err["fx_pct"].max()),
                "pp_err_px_max": float(err["pp_px"].max()),
                "centre_err_mm_median": float(np.median(err["centre_mm"])),
                "centre_err_mm_max": float(err["centre_mm"].max()),
                "rotation_err_deg_max": float(err["rotation_deg"].max()), "reprojection_rms_px": result.rms_px,
                "weak_cameras": sum(bool(e.get("weak")) for e in result.extra.get("intrinsics", {}).values())}

    def annotate(self) -> dict:
        takes = [self.take[k] for k in ("hand", "grasp", "canonical")]
        keypoints = "simulated" if self.config.simulated_keypoints else "detect"
        summary = annotate(takes, self.calib, self.dataset, AnnotateOptions(keypoints=keypoints), force=True)
        if summary.failed:
            raise DemoError(f"annotate failed: {summary.failed}")
        data = read_dataset(self.dataset)
        grasp = data[take_key(self.take["grasp"])]
        truth = truth_at_groups(self.take["grasp"], grasp.frame_ns)
        tri = np.linalg.norm(grasp.keypoints3d - truth["joints3d"], axis=-1)
        fitted, angles = pose_errors(grasp.bone_lengths, grasp.joint_angles, truth)
        found = (grasp.keypoints2d[..., 2] > 0).any(axis=-1)[grasp.frame_index >= 0]
        # views_recovered: of those, the views annotate's cross-view step found (docs/annotate.md)
        return {"keypoints": keypoints, "views_with_hand": float(found.mean()),
                "views_recovered": int(grasp.attrs.get("views_recovered", 0)), "frames": len(grasp.frame_ns),
                "triangulated_mpjpe_mm": 1000 * float(np.nanmean(tri)),
                "fitted_mpjpe_mm": fitted, "finger_angle_rms_deg": angles,
                "bone_length_err_mm": 1000 * float(np.abs(grasp.bone_lengths - truth["bone_lengths"]).max())}

    def segment(self) -> dict:
        rig = load_cameras(self.calib)
        background, obj = self.take["calibration"], self.take["object"]
        metrics = {}
        # the hand and grasp takes' masks train MANUS-Hand and refine the grasp's poses
        for kind in ("object", "hand", "grasp", "canonical"):
            result = segment_take(self.take[kind], rig, background, obj if kind != "hand" else None)
            write_masks(self.dataset, take_key(self.take[kind]), result, {"segmentation_background": str(background)})
            order = result.in_order(rig.ids)
            if kind in ("hand", "grasp"):
                continue
            labels = GroundTruth.of_take(self.take[kind]).labels([0])[:, 0]
            if kind == "object":
                self.object_masks = result.object[0][order]
                metrics["object_iou"] = _iou(self.object_masks, labels == 2)
            else:
                self.paint = result.paint[order]
                self.true_paint = labels == 3
                seen = self.true_paint.reshape(len(labels), -1).sum(1) >= MIN_PAINT_PX
                metrics["hand_iou"] = _iou(result.hand[0][order], (labels == 1) | (labels == 3))
                metrics["paint_iou"] = _iou(self.paint[seen], self.true_paint[seen])
                metrics["paint_views"] = int(seen.sum())
        return metrics


    def reconstruct(self) -> dict:
        """MANUS-Hand from the hand take and object Gaussians from the object take, on every
        camera; checkpoints in models/."""

        c = self.config
        self.rig = load_cameras(self.calib)
        self.inputs = ModelInputs.prepare(self.rig, self.dataset, self.take["hand"], self.take["object"],
                                          self.take["calibration"], poses=c.hand_frames,
                                          object_masks=self.object_masks, object_iterations=c.object_iterations,
                                          hand_iterations=c.hand_iterations, scale=c.scale, seed=c.seed)
        models = self.inputs.train(np.arange(len(self.rig)), evaluate=True)
        self.hand, self.object, metrics = models.hand, models.object, models.metrics
        # the paper's claim in one number each: how near the learned hand and the template lie to
        # the true skin (scoring only: the truth is read here, never by the training)
        truth = GroundTruth.of_take(self.take["hand"])
        joints = self.hand.skeleton.rest_joints()
        for name, points in (("hand", self.hand.gaussians.means.detach().double().numpy()),
                             ("template", capsule_template(self.hand.skeleton.bone_lengths).points_rest)):
            errors = surface_errors(points, joints, truth.skin, truth.hand.rest_joints)
            metrics.update({f"{name}_surface_{part}_mm": errors[f"{part}_mm"] for part in ("fingers", "palm")})
        self.models.mkdir(parents=True, exist_ok=True)
        blur = str(SURFACE_EPS2D)  # the splat blur the surfels were trained with (ModelInputs.train)
        save_checkpoint(self.models / "hand.safetensors", self.hand.gaussians, kind="hand",
                        extra=self.hand.extra_tensors(), metadata={"source": str(self.take["hand"]), "eps2d": blur})
        save_checkpoint(self.models / "object.safetensors", self.object, kind="object",
                        metadata={"source": str(self.take["object"]), "eps2d": blur})
        return metrics

    def refine(self) -> dict:
        """The grasp and canonical takes' poses refined against their images through the hand
        model just trained (manus_capture.refine); scored against the truth."""
        c = self.config
        options = RefineOptions(iterations=c.refine_iterations, eps2d=SURFACE_EPS2D)
        metrics = {}
        for kind in ("grasp", "canonical"):
            key = take_key(self.take[kind])
            result = refine_take(self.dataset, key, self.take[kind], self.rig, self.hand, options,
                                 self.models / "hand.safetensors")
            write_refined(self.dataset, key, result, {"demo": True})
            if kind == "grasp":
                ann = read_dataset(self.dataset)[key]
                truth = truth_at_groups(self.take[kind], ann.frame_ns)
                fitted, angles = pose_errors(ann.bone_lengths, result.angles, truth)
                metrics.update(fitted_mpjpe_mm_refined=fitted, finger_angle_rms_deg_refined=angles,
                               frames_refined=result.frames_refined, frames_diverged=result.frames_diverged,
                               refine_frames_per_s=result.frames_refined / max(result.seconds, 1e-9))
        return metrics

    def contacts(self) -> dict:
        """Contacts of the grasp take (refined joint angles) against the object, into DATASET.h5;
        scored on the true contact of the simulated hand's surface."""
        from scipy.spatial import cKDTree


        key = take_key(self.take["grasp"])
        self.grasp_angles, _ = read_dataset(self.dataset).pose_angles(key)   # refined
        maps = model_contacts(self.hand, self.grasp_angles, self.object, self.config.tau)
        write_contacts(self.dataset, key, maps, {"contact_hand_model": str(self.models / "hand.safetensors"),
                                                 "contact_object_model": str(self.models / "object.safetensors")})
        self.maps = maps
        # the truth lives on the simulated hand's surface points: carry it to each Gaussian near
        # the surface (in the canonical, rest-pose space both share)
        contact = GroundTruth.of_take(self.take["grasp"]).contact
        points, truth = contact.points_rest, contact.accumulated
        dist, nearest = cKDTree(points).query(self.hand.gaussians.means.detach().numpy())
        surface = dist < SURFACE_BAND_M
        pred = maps.accumulated[surface] > 0.5
        true = truth[nearest[surface]]
        return {"hand_gaussians_in_contact": int((maps.accumulated > 0.5).sum()),
                "object_gaussians_in_contact": int((maps.object_accumulated > 0.5).sum()),
                "gaussian_contact_iou": float((pred & true).sum() / max((pred | true).sum(), 1))}

    def evaluate(self) -> dict:
        """Contact against the segmented paint in the canonical take's views; the capsule baseline;
        the camera ablation (models retrained on fewer cameras)."""

        c = self.config
        canonical = canonical_pose(read_dataset(self.dataset).pose_angles(take_key(self.take["canonical"]))[0])
        views = pick_views(self.paint, c.eval_views)
        ours, pred = score_contacts(self.hand, canonical, self.maps.accumulated, self.rig, self.paint, views)
        true_paint = mask_scores(pred, self.true_paint[views], ours.cameras)
        template = capsule_template(self.inputs.hand_frames.bone_lengths)
        base_maps = model_contacts(template, self.grasp_angles, self.object, c.tau)
        baseline, _ = score_contacts(template, canonical, base_maps.accumulated, self.rig, self.paint, views)
        self.eval_views, self.eval_pred = views, pred
        ablation = {}
        for n in c.views:
            count = len(self.rig) if n == 0 or n >= len(self.rig) else n
            if count == len(self.rig):
                ablation[count] = ours
                continue
            self.say(f"    camera ablation: {count} cameras")
            models = self.inputs.train(spread_cameras(self.rig, count))
            maps = model_contacts(models.hand, self.grasp_angles, models.object, c.tau)
            ablation[count], _ = score_contacts(models.hand, canonical, maps.accumulated, self.rig, self.paint, views)
        self.scores = {"ours": ours, "baseline": baseline, "true_paint": true_paint}
        return {"contact_iou": ours.mean_iou, "contact_f1": ours.mean_f1, "baseline_iou": baseline.mean_iou,
                "baseline_f1": baseline.mean_f1, "contact_iou_vs_true_paint": true_paint.mean_iou,
                "views": {str(k): v.mean_iou for k, v in sorted(ablation.items())}}


def camera_errors(rig, truth) -> dict:
    """Per camera of `rig` against `truth`: focal length error (%, the worse of fx and fy),
    principal point error (px), centre error (mm) and rotation error (degrees)."""
    ref = truth.subset(rig.ids)
    focal = np.abs(rig.K[:, [0, 1], [0, 1]] / ref.K[:, [0, 1], [0, 1]] - 1).max(axis=1)
    return {"fx_pct": 100 * focal, "pp_px": np.abs(rig.K[:, :2, 2] - ref.K[:, :2, 2]).max(axis=1),
            "centre_mm": 1000 * np.linalg.norm(rig.centers - ref.centers, axis=1),
            "rotation_deg": rotation_angle_deg(rig.R, ref.R)}


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    """Pooled IoU of two boolean mask stacks."""
    return float((a & b).sum() / max((a | b).sum(), 1))


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def _png(path: Path, image: np.ndarray, zoom: int = 2) -> None:
    import cv2

    big = cv2.resize(image, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
    write_atomic(path, cv2.imencode(".png", big)[1].tobytes())


def pictures(demo: Demo, count: int = 3) -> list[tuple[str, str]]:
    """The report's PNGs in DIR/images: keypoints, contacts, paint comparison, ablation, sync, cameras."""
    import shutil



    demo.images.mkdir(parents=True, exist_ok=True)
    out: list[tuple[str, str]] = []
    grasp = read_dataset(demo.dataset)[take_key(demo.take["grasp"])]
    take = Take(demo.take["grasp"])
    hold = int(np.argmax(demo.maps.instant.sum(axis=1)))
    # the views that show the paint best see the hand's palm side, which does the grasping
    cams = [grasp.cameras.index(demo.rig.ids[v]) for v in demo.eval_views[:count]]
    projected = demo.rig.project(HandSkeleton(grasp.bone_lengths).forward(demo.grasp_angles[hold]))
    value, alpha = render_contacts(demo.hand, demo.grasp_angles[hold], demo.maps.accumulated, demo.rig)
    for c in cams:
        cam = grasp.cameras[c]
        image = take.read_frame(cam, int(max(grasp.frame_index[hold, c], 0)))
        rig_c = demo.rig.index(cam)
        _png(demo.images / f"keypoints_{cam}.png", keypoint_overlay(image, grasp.keypoints2d[hold, c], projected[rig_c]))
        out.append((f"images/keypoints_{cam}.png", f"grasp, camera {cam}: 2D keypoints (yellow) and the "
                                                   "fitted and refined 26-DOF hand projected (magenta)"))
        _png(demo.images / f"contact_{cam}.png", contact_image(value[rig_c], alpha[rig_c], image))
        out.append((f"images/contact_{cam}.png", f"grasp, camera {cam}: accumulated contact on the Gaussian hand "
                                                 "(yellow to red) at the firmest hold"))
    canonical = Take(demo.take["canonical"])
    for j, v in enumerate(demo.eval_views[:count]):
        cam = demo.rig.ids[v]
        image = canonical.read_frame(cam, min(1, canonical.frame_count(cam) - 1))
        _png(demo.images / f"paint_{cam}.png", mask_comparison(image, demo.eval_pred[j], demo.paint[v]))
        out.append((f"images/paint_{cam}.png", f"canonical pose, camera {cam}: paint (green), predicted contact "
                                               "(red), both (yellow)"))
    write_atomic(demo.images / "ablation.png", ablation_png(demo.summary["views"], demo.summary["baseline_iou"]))
    out.append(("images/ablation.png", "camera ablation: contact IoU of models built from fewer cameras"))
    for src, name, caption in ((demo.take["grasp"] / "sync_timeline.png", "sync_timeline.png",
                                "grasp take: frame timing of every camera (sync report)"),
                               (demo.calib / "cameras.png", "cameras.png", "calibrated camera layout, coloured by error")):
        if src.exists():
            shutil.copyfile(src, demo.images / name)
            out.append((f"images/{name}", caption))
    return out


def run_demo(out: Path, config: DemoConfig = DemoConfig(), say: Callable[[str], None] = print,
             force: bool = False) -> dict:
    """Run every stage into `out` and return the summary (also DIR/summary.json and report.html)."""

    out = Path(out)
    # an unknown subject or an impossible subject file fails here, before anything is written
    subject_shape(config.subject)
    if (out / "summary.json").exists() and not force:
        raise DemoError(f"{out}: holds a finished demo (summary.json); use --force to run it again")
    demo = Demo(out, config, say)
    for name, fn in (("record", demo.record), ("sync", demo.sync), ("calibrate", demo.calibrate),
                     ("annotate", demo.annotate), ("segment", demo.segment), ("reconstruct", demo.reconstruct),
                     ("refine", demo.refine), ("contacts", demo.contacts), ("evaluate", demo.evaluate)):
        demo.stage(name, fn)
    metrics = {s.name: s.metrics for s in demo.stages}
    evaluation = metrics["evaluate"]
    stages = [{"name": s.name, "seconds": round(s.seconds, 2), "metrics": s.metrics} for s in demo.stages]
    demo.summary = {**{k: evaluation[k] for k in ("contact_iou", "contact_f1", "baseline_iou", "baseline_f1",
                                                   "views")},
                    **{k: metrics["reconstruct"][k] for k in ("hand_psnr_mask_db", "hand_ssim", "hand_lpips",
                                                              "object_psnr_mask_db", "object_ssim", "object_lpips")},
                    "finger_angle_rms_deg": metrics["annotate"]["finger_angle_rms_deg"],
                    "finger_angle_rms_deg_refined": metrics["refine"]["finger_angle_rms_deg_refined"],
                    "fitted_mpjpe_mm": metrics["annotate"]["fitted_mpjpe_mm"],
                    "fitted_mpjpe_mm_refined": metrics["refine"]["fitted_mpjpe_mm_refined"],
                    "refine_frames_diverged": metrics["refine"]["frames_diverged"],
                    "scores": {k: v.to_json() for k, v in demo.scores.items()},
                    "config": dataclasses.asdict(config),
                    "stages": stages, "seconds": round(sum(s.seconds for s in demo.stages), 1)}
    figures = pictures(demo)
    write_html(out / "report.html", "manus-capture demo: simulated grasp capture", demo.summary, stages, figures)
    write_atomic(out / "summary.json", json.dumps(demo.summary, indent=2, default=float).encode())
    return demo.summary
