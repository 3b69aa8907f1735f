"""Readers of DATASET.h5 on takes that hold only some stages' results (issue 22, item 3).

After `segment` of a take that was never annotated, `stats` failed on the whole dataset with
`take S/grasp/masks: missing frame_index`. Every reader now says per take what it holds: `stats`
lists each take with its stages; `contacts`, `evaluate` and `reconstruct hand` refuse a take that
lacks the stage they need in one line naming the take and the stage (exit code 2); results made
from another recording of the take than its annotation are named and not combined with it.
The takes are written by the stages' own writers, with small arrays (no rendering).
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from dataset_tools.segmentation.takes import Segmentation, write_masks
from manus_capture.cli import cli
from manus_capture.splat.checkpoint import save_checkpoint
from manus_capture.splat.gaussians import Gaussians
from manus_capture.splat.hand import HandGaussians
from manus_core.cameras import CameraRig
from manus_core.dataset import DatasetWriter, TakeAnnotation
from manus_core.provenance import provenance_attrs
from manus_core.skeleton import DEFAULT_BONE_LENGTHS

pytestmark = pytest.mark.faults   # the fault-injection suite (docs/faults.md)

CAMS = ("a", "b", "c")
T = 6
FRAME_NS = 10**9 + np.arange(T) * 33_333_333
RECORDING = {"frames": {c: T for c in CAMS}, "frames_csv_sha256": "1" * 64}
RE_RECORDED = {"frames": {c: T + 2 for c in CAMS}, "frames_csv_sha256": "2" * 64}


def annotation(key: str) -> TakeAnnotation:
    """What annotate writes for a take of RECORDING: a still open hand, seen by every camera."""
    n_c = len(CAMS)
    return TakeAnnotation(key, CAMS, FRAME_NS, np.tile(np.arange(T)[:, None], (1, n_c)),
                          np.zeros((T, n_c, 21, 3), np.float32), np.zeros((T, 21, 3)), np.full((T, 21), 1.5),
                          np.full((T, 21), n_c), np.zeros((T, 26)), np.zeros((T, 26)), DEFAULT_BONE_LENGTHS.copy(),
                          np.full(T, 1e-3), np.zeros(T, np.uint8),
                          {"kind": "grasp", **provenance_attrs("annotate", {"take": RECORDING})})


def masks(path, key: str, recording: dict, paint: bool = False) -> None:
    """What segment writes for a take of `recording` (a canonical take's with paint)."""
    hand = np.zeros((T, len(CAMS), 8, 8), bool)
    hand[:, :, 2:6, 2:6] = True
    result = Segmentation(CAMS, FRAME_NS, np.tile(np.arange(T)[:, None], (1, len(CAMS))), hand,
                          np.zeros_like(hand), hand[0] if paint else None, 0 if paint else None, {"warnings": []})
    write_masks(path, key, result, provenance_attrs("segment", {"take": recording}))


@pytest.fixture
def dataset(tmp_path):
    """S/annotated (annotate only), S/segmented (segment only, with paint), S/both, S/stale (masks of a
    later recording than its annotation), and checkpoints and cameras to run the readers with."""
    out = tmp_path / "D.h5"
    with DatasetWriter(out) as writer:
        for key in ("S/annotated", "S/both", "S/stale"):
            writer.add(annotation(key))
    masks(out, "S/segmented", RECORDING, paint=True)
    masks(out, "S/both", RECORDING, paint=True)
    masks(out, "S/stale", RE_RECORDED, paint=True)
    hand = HandGaussians.initialize(DEFAULT_BONE_LENGTHS, per_bone=3, resolution=16, sh_degree=0)
    save_checkpoint(tmp_path / "hand.safetensors", hand.gaussians, kind="hand", extra=hand.extra_tensors())
    # an object just off the fingertips of the open hand: some of them touch it
    tips = torch.as_tensor(hand.skeleton.rest_joints()[[8, 12, 16]], dtype=torch.float32)
    save_checkpoint(tmp_path / "object.safetensors", Gaussians.from_points(tips + 0.002, sh_degree=0, scale=0.002),
                    kind="object")
    n = len(CAMS)
    CameraRig(CAMS, np.tile(np.array([[100.0, 0, 4], [0, 100, 4], [0, 0, 1]]), (n, 1, 1)), None,
              np.tile(np.eye(3), (n, 1, 1)), np.array([[0, 0, 0.5]] * n), np.array([[8, 8]] * n)).save(
        tmp_path / "cameras.json")
    return out


def run(*args) -> tuple[int, str]:
    result = CliRunner().invoke(cli, [str(a) for a in args])
    assert "Traceback" not in result.output, result.output
    return result.exit_code, result.output


def error_line(output: str) -> str:
    """The one line an error gives (after any progress bars)."""
    lines = [line for line in output.replace("\r", "\n").splitlines() if line.startswith("Error: ")]
    assert len(lines) == 1, output
    return lines[0]


def test_stats_lists_every_take_with_what_it_holds(dataset, tmp_path):
    code, out = run("stats", dataset, "--json", tmp_path / "stats.json")
    assert code == 0, out
    rows = {line.split()[0]: line for line in out.splitlines() if line.startswith("S/")}
    assert set(rows) == {"S/annotated", "S/segmented", "S/both", "S/stale"}, out
    assert "not annotated: run annotate on it" in rows["S/segmented"] and rows["S/segmented"].endswith(" segment")
    assert rows["S/both"].split()[1] == str(T) and rows["S/both"].endswith(" annotate+segment")
    assert rows["S/annotated"].endswith(" annotate")
    assert "note: S/stale: its segment results and its annotation are of different recordings (take re-recorded: " \
           "frames of a 6 -> 8" in out
    assert f"4 takes, {3 * T} frames, hand fitted in {3 * T} (100.0%); not annotated: S/segmented" in out
    table = json.loads((tmp_path / "stats.json").read_text())
    assert table["S/segmented"] == {"stages": ["segment"]} and table["S/both"]["stages"] == ["annotate", "segment"]
    assert table["S/stale"]["segment_of_another_recording"] and (tmp_path / "D.aperture.png").is_file()
    # a take without annotation alone: listed, no plot to draw
    code, out = run("stats", dataset, "--take", "S/segmented", "--plot", tmp_path / "none.png")
    assert code == 0 and "1 takes, 0 frames" in out and not (tmp_path / "none.png").exists(), out


def test_contacts_needs_the_annotation_and_records_its_recording(dataset, tmp_path):
    models = ["--hand", tmp_path / "hand.safetensors", "--object", tmp_path / "object.safetensors"]
    before = dataset.read_bytes()
    code, out = run("contacts", dataset, "--take", "S/segmented", *models)
    assert code == 2 and "take S/segmented has no annotation, only the results of segment" in error_line(out), out
    assert dataset.read_bytes() == before
    # an annotated take: contacts are added beside its annotation and masks, with the recording
    # they were computed from; stats then lists the stage
    code, out = run("contacts", dataset, "--take", "S/both", *models, "--calib", tmp_path / "cameras.json",
                    "--renders", tmp_path / "renders")
    assert code == 0 and "contacts: S/both: 6 frames" in out, out
    code, out = run("stats", dataset, "--take", "S/both", "--json", tmp_path / "s.json")
    assert code == 0 and json.loads((tmp_path / "s.json").read_text())["S/both"]["stages"] == \
        ["annotate", "contacts", "segment"], out
    with h5py.File(dataset) as f:
        inputs = json.loads(f["S/both"].attrs["provenance_contacts"])
        assert inputs["take"] == RECORDING and inputs["tau_m"] == 0.004 and "masks/hand" in f["S/both"]


def test_evaluate_names_the_take_and_the_stage_it_lacks(dataset, tmp_path):
    common = ["--calib", tmp_path / "cameras.json", "--hand", tmp_path / "hand.safetensors",
              "--object", tmp_path / "object.safetensors"]
    for grasp, canonical, problem in [
            ("S/segmented", "S/both", "take S/segmented has no annotation"),
            ("S/annotated", "S/segmented", "take S/segmented has no annotation"),
            ("S/both", "S/annotated", "take S/annotated has no paint/masks (run segment on it first)"),
            ("S/both", "S/stale", "take S/stale: its paint masks and its annotation are of different recordings "
                                  "(take re-recorded: frames of a 6 -> 8")]:
        code, out = run("evaluate", dataset, "--grasp", grasp, "--canonical", canonical, *common)
        assert code == 2 and problem in error_line(out), out


def test_reconstruct_hand_refuses_a_take_without_annotation_or_current_masks(dataset, tmp_path):
    common = ["--take", tmp_path / "S" / "take", "--cameras", tmp_path / "cameras.json", "-o", tmp_path / "h.st"]
    for key, problem in [("S/segmented", "take S/segmented has no annotation, only the results of segment"),
                         ("S/annotated", "take S/annotated has no hand masks (run `manus-capture segment` on it)"),
                         ("S/stale", "take S/stale: its masks and its annotation are of different recordings")]:
        code, out = run("reconstruct", "hand", "--dataset", dataset, "--dataset-take", key, *common)
        assert code == 2 and problem in error_line(out), out
    assert not (tmp_path / "h.st").exists()
