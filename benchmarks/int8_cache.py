"""The int8 landmark model for a benchmark, in a model cache of the benchmark's own.

`quantized_cache(root, takes)` links the installed MediaPipe models into ROOT/cache, runs
`manus-capture models quantize mediapipe-hand --calibration TAKE...` there and points this process
and its children at it (XDG_CACHE_HOME), so that the user's own cache, and any int8 model calibrated
on their takes, is left as it was.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from dataset_tools.keypoints.install import bundle_dir


def quantized_cache(root: Path, takes: list[Path], log: Path | None = None) -> None:
    models = root / "cache" / "manus-capture" / "models" / "mediapipe-hand"
    models.mkdir(parents=True, exist_ok=True)
    for f in bundle_dir("mediapipe-hand").iterdir():
        if f.is_file() and "int8" not in f.name and not (models / f.name).exists():
            (models / f.name).symlink_to(f)
    os.environ["XDG_CACHE_HOME"] = str(root / "cache")
    argv = [str(Path(sys.executable).parent / "manus-capture"), "models", "quantize", "mediapipe-hand"]
    for take in takes:
        argv += ["--calibration", str(take)]
    with open(log or os.devnull, "ab") as out:
        subprocess.run(argv, stdout=out, stderr=out, check=True)
