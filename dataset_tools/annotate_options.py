"""The annotate stage's settings (`AnnotateOptions`): the stage (annotate.py) and where its
keypoints come from (take_keypoints.py) both take them."""

from __future__ import annotations

from dataclasses import dataclass

from manus_core.errors import AnnotateError


@dataclass(frozen=True)
class AnnotateOptions:
    """Settings of the stage. keypoints: where 2D keypoints come from: "auto" (TAKE/keypoints2d.h5
    when it exists, else the ONNX detector), "file", "detect", or "simulated": the simulated
    detector on a simulated take's ground truth, an ablation that is only ever used when named."""

    keypoints: str = "auto"
    model: str = "mediapipe-hand"
    device: str = "auto"
    palm_tiles: bool = False           # detecting: the palm detector also looks at square tiles
    cross_view: bool = True            # detecting: the views it missed, from the hand the others see
    sim_noise_px: float = 2.0
    sim_outlier_rate: float = 0.1
    sim_dropout_rate: float = 0.0
    sim_seed: int = 0
    threshold_px: float = 10.0
    min_views: int = 2
    min_joints: int = 6
    ik_poor_m: float = 0.01
    min_cutoff: float = 1.0
    beta: float = 10.0
    beta_translation: float = 300.0
    d_cutoff: float = 1.0

    def __post_init__(self) -> None:
        if self.keypoints not in ("auto", "file", "simulated", "detect"):
            raise AnnotateError(f"keypoints = {self.keypoints!r}; use auto, file, simulated or detect")

    @property
    def filter(self) -> dict:
        return {"min_cutoff": self.min_cutoff, "beta": self.beta, "beta_translation": self.beta_translation,
                "d_cutoff": self.d_cutoff}

    @property
    def settings(self) -> dict:
        """The settings the results depend on, besides the keypoint source."""
        return {"threshold_px": self.threshold_px, "min_views": self.min_views, "min_joints": self.min_joints,
                "ik_poor_m": self.ik_poor_m, **self.filter}
