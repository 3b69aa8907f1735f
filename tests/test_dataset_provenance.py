"""DATASET.h5 keeps which inputs made each stage's results, stages own their parts of a take, and
annotate reuses a take only when its inputs are the same (issue 22, items 4-6), also on a
partially calibrated rig."""

from __future__ import annotations

import hashlib
import json
import shutil

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from test_annotate import write_sim_take
from test_dataset import assert_same, make_annotation

from dataset_tools.keypoints.keypoints2d import CameraKeypoints, TakeKeypoints, write_keypoints_h5
from dataset_tools.simulated_detector import SimulatedDetector, simulated_take_keypoints
from manus_capture.cli import cli
from manus_core.dataset import DatasetWriter, add_arrays, read_dataset
from manus_core.errors import DatasetError, TakeError
from manus_core.frames_csv import HEADER, format_row
from manus_core.provenance import (
    STAGE_ARRAYS,
    cameras_used,
    differences,
    provenance_attrs,
    read_provenance,
    stage_inputs,
    take_identity,
)
from manus_core.take import Take
from rig.layouts import make_rig
from rig.sim.cube import true_cameras
from rig.sim.hand import make_hand
from rig.sim.motion import make_motion
from rig.sim.objects import make_object

pytestmark = pytest.mark.faults   # the fault-injection suite (docs/faults.md)

SEGMENT = {"masks/hand": np.ones((3, 2, 4, 4), bool), "masks/object": np.zeros((3, 2, 4, 4), bool),
           "masks/frame_ns": np.arange(3), "paint/masks": np.ones((2, 4, 4), bool)}


def write_take(folder, frames: dict[str, int]) -> Take:
    folder.mkdir(parents=True, exist_ok=True)
    rows = [format_row(cam, k, k * 1000, k * 1000 + 5, 100, 0) for cam, n in frames.items() for k in range(n)]
    (folder / "frames.csv").write_text(HEADER + "\n" + "".join(rows))
    (folder / "take.json").write_text(json.dumps({"kind": "grasp", "cameras": list(frames)}))
    return Take(folder)


def test_provenance_records_a_takes_identity_and_says_what_changed(tmp_path):
    take = write_take(tmp_path / "S" / "t", {"cam03": 23, "cam04": 23})
    identity = take_identity(take)
    assert identity == {"frames": {"cam03": 23, "cam04": 23},
                        "frames_csv_sha256": hashlib.sha256((take.path / "frames.csv").read_bytes()).hexdigest()}
    old = stage_inputs(take, calibration_sha256="aa", keypoint_source="file", settings={"threshold_px": 10.0})
    assert old["take"] == identity and differences(old, json.loads(json.dumps(old))) == []
    with h5py.File(tmp_path / "p.h5", "w") as f:
        group = f.create_group("S/t")
        assert read_provenance(group, "annotate") is None
        group.attrs.update(provenance_attrs("annotate", old))
        assert read_provenance(group, "annotate") == old and read_provenance(group, "segment") is None
        group.attrs["provenance_segment"] = "not json {"
        assert read_provenance(group, "segment") is None

    rerecorded = write_take(tmp_path / "S" / "t", {"cam03": 31, "cam04": 23})
    new = stage_inputs(rerecorded, calibration_sha256="bb", keypoint_source="detect", settings={"threshold_px": 5.0})
    assert differences(old, new) == ["take re-recorded: frames of cam03 23 -> 31", "calibration changed",
                                     "keypoint source file -> detect", "settings: threshold_px 10.0 -> 5.0"]
    # The same frame counts, other rows: still another recording.
    (take.path / "frames.csv").write_text((take.path / "frames.csv").read_text().replace(",5,100,", ",6,100,"))
    same_counts = stage_inputs(Take(take.path), calibration_sha256="bb", keypoint_source="detect",
                               settings={"threshold_px": 5.0})
    assert differences(new, same_counts) == ["take re-recorded: frames.csv changed (same frame counts)"]
    assert differences(None, new) == ["no record of the inputs that made it (written before provenance was kept)"]


def test_cameras_used_leave_uncalibrated_ones_out_or_take_the_chosen(tmp_path):
    take = write_take(tmp_path / "S" / "t", {"a": 2, "b": 2, "c": 2, "d": 2})
    assert cameras_used(take, ["d", "b", "c", "x"], "CAL") == ("b", "c", "d")
    assert cameras_used(take, ["a", "b", "c", "d"], "CAL", chosen=["c", "a"]) == ("a", "c")
    with pytest.raises(TakeError, match=r"take.json: 1 of the take's cameras \(b\) in the calibration CAL; 2 are"):
        cameras_used(take, ["b", "x"], "CAL")
    with pytest.raises(TakeError, match="--cameras names x, not cameras of the take"):
        cameras_used(take, ["a", "b"], "CAL", chosen=["a", "x"])
    with pytest.raises(TakeError, match="CAL: --cameras names c, not in the calibration"):
        cameras_used(take, ["a", "b"], "CAL", chosen=["a", "c"])


def test_reannotating_keeps_the_other_stages_results_and_the_other_takes(tmp_path):
    """Item 4: a new annotation of a take (as `annotate --force` writes it) replaced the whole take
    group, and force dropped every other take of the file too."""
    out = tmp_path / "DATASET.h5"
    first = make_annotation("S/t", seed=1)
    first.attrs["cameras_left_out"] = ["cam9"]
    with DatasetWriter(out) as w:
        w.add(first)
        w.add(make_annotation("S/u", seed=2))
    add_arrays(out, "S/t", SEGMENT, {"mask_cameras": ["cam0", "cam1"], "provenance_segment": "{}"}, stage="segment")
    add_arrays(out, "S/t", {"contacts/instant": np.zeros((3, 5), np.float16)}, {"contact_tau_m": 0.004},
               stage="contacts")
    second = make_annotation("S/t", seed=3)
    with DatasetWriter(out, force=True) as w:
        w.add(second)
    ds = read_dataset(out)
    assert ds.takes == ["S/t", "S/u"] and ds.stages("S/t") == {"annotate", "segment", "contacts"}
    assert_same(second, ds["S/t"])
    attrs = ds["S/t"].attrs
    assert "cameras_left_out" not in attrs            # annotate's own attributes are replaced, not merged
    assert attrs["mask_cameras"] == ["cam0", "cam1"] and attrs["contact_tau_m"] == 0.004
    assert ds.provenance("S/t", "segment") == {}
    with h5py.File(out, "r") as f:
        for name, value in SEGMENT.items():
            np.testing.assert_array_equal(f["S/t"][name][()], value)
        assert f["S/t/contacts/instant"].shape == (3, 5)


def test_a_take_with_only_segment_output_is_listed_and_annotated(tmp_path):
    """Item 5: the masks' own frame_ns made `S/t/masks` look like a take; annotating S/t then
    crashed copying into the existing group and left the parts folder behind."""
    out = tmp_path / "DATASET.h5"
    add_arrays(out, "S/t", SEGMENT, stage="segment")
    ds = read_dataset(out)
    assert ds.takes == ["S/t"] and ds.stages("S/t") == {"segment"} and ds.annotated == []
    with pytest.raises(DatasetError, match=r"DATASET.h5: take S/t has no annotation, only the results of segment"):
        ds["S/t"]
    w = DatasetWriter(out)
    assert w.done == set() and w.inputs("S/t") is None
    ann = make_annotation("S/t")
    ann.attrs.update(provenance_attrs("annotate", {"settings": {"x": 1}}))
    w.add(ann)
    assert w.done == {"S/t"} and w.inputs("S/t") == {"settings": {"x": 1}}
    assert w.finalize() == ["S/t"]
    assert not (tmp_path / ".DATASET.h5.parts").exists()
    ds = read_dataset(out)
    assert ds.stages("S/t") == {"annotate", "segment"} and ds.annotated == ["S/t"]
    assert_same(ann, ds["S/t"])
    assert DatasetWriter(out).inputs("S/t") == {"settings": {"x": 1}}
    with h5py.File(out, "r") as f:
        np.testing.assert_array_equal(f["S/t/masks/hand"][()], SEGMENT["masks/hand"])


def test_a_stage_may_not_write_another_stages_arrays(tmp_path):
    out = tmp_path / "DATASET.h5"
    with DatasetWriter(out) as w:
        w.add(make_annotation("S/t"))
    before = out.read_bytes()
    with pytest.raises(DatasetError, match="take S/t: segment may not write joint_angles"):
        add_arrays(out, "S/t", {"masks/hand": np.ones((1, 1, 2, 2), bool), "joint_angles": np.zeros((30, 26))},
                   stage="segment")
    assert out.read_bytes() == before
    assert set(STAGE_ARRAYS["annotate"]) == set(vars(make_annotation("S/x"))) - {"key", "cameras", "attrs"}


# --- annotate on a tiny simulated take ---------------------------------------------------------------

@pytest.fixture
def tiny(tmp_path):
    """One grasp take of 23 frames on 6 cameras (no rendering) and its calibration."""
    rig = true_cameras(make_rig("cube53", cameras=6, resolution=(320, 180)))
    rig.save(tmp_path / "calib" / "cameras.json")
    hand = make_hand("s03")

    def record(frames: int):
        if (tmp_path / "S" / "t").exists():
            shutil.rmtree(tmp_path / "S" / "t")
        motion = make_motion("grasp", hand, make_object("box"), 1.0)
        write_sim_take(tmp_path / "S" / "t", rig, hand, motion, 30.0, frames, "grasp", seed=frames)

    record(23)
    return {"root": tmp_path, "rig": rig, "take": tmp_path / "S" / "t", "record": record}


def run_annotate(tiny, *args: str):
    result = CliRunner().invoke(cli, ["annotate", str(tiny["take"]), "-o", str(tiny["root"] / "D.h5"), *args])
    assert "Traceback" not in result.output and not (tiny["root"] / ".D.h5.parts").exists()
    return result


def test_annotate_redoes_a_take_whose_inputs_changed_and_says_why(tiny):
    """Items 4-6 through the CLI: a take holding only masks is annotated; a second run keeps it;
    --force, a re-recorded take, another calibration and another keypoint source redo it (saying
    why); the masks survive every run."""
    root, out, calib = tiny["root"], tiny["root"] / "D.h5", str(tiny["root"] / "calib")
    add_arrays(out, "S/t", SEGMENT, stage="segment")
    sim = ["--calib", calib, "--keypoints", "simulated"]
    result = run_annotate(tiny, *sim)
    assert result.exit_code == 0, result.output
    assert "1 takes annotated, 0 kept from before" in result.output
    result = run_annotate(tiny, *sim)
    assert "kept (same inputs): S/t" in result.output and "0 takes annotated, 1 kept" in result.output
    result = run_annotate(tiny, *sim, "--force")
    assert "redone S/t: --force" in result.output and "1 takes annotated" in result.output

    tiny["record"](31)                                      # record --force with a longer take
    cam = tiny["rig"].ids[0]
    result = run_annotate(tiny, *sim)
    assert result.exit_code == 0, result.output
    assert f"redone S/t: take re-recorded: frames of {cam} 23 -> 31" in result.output
    assert len(read_dataset(out)["S/t"].frame_ns) == 31

    moved = tiny["rig"].to_json()
    moved["cameras"][0]["t"][0] += 0.001
    (root / "calib2").mkdir()
    (root / "calib2" / "cameras.json").write_text(json.dumps(moved))
    result = run_annotate(tiny, "--calib", str(root / "calib2"), "--keypoints", "simulated")
    assert "redone S/t: calibration changed" in result.output

    take = Take(tiny["take"])
    counts = np.array([take.frame_count(c) for c in take.cameras])
    per_frame = np.where(np.arange(counts.max())[:, None] < counts, np.arange(counts.max())[:, None], -1)
    kp = simulated_take_keypoints(take, per_frame, SimulatedDetector(seed=2)).astype(np.float32)
    write_keypoints_h5(tiny["take"] / "keypoints2d.h5", TakeKeypoints(
        {cam: CameraKeypoints(kp[:n, c], np.zeros((n, 4), np.float32), np.zeros(n, np.float32))
         for c, (cam, n) in enumerate(zip(take.cameras, counts))}, "simulated", "-", "test"))
    result = run_annotate(tiny, "--calib", str(root / "calib2"), "--keypoints", "file")
    assert "redone S/t: keypoint source simulated -> file" in result.output
    assert read_dataset(out)["S/t"].attrs["keypoint_source"].startswith("file:")
    ds = read_dataset(out)
    assert ds.stages("S/t") == {"annotate", "segment"}
    with h5py.File(out, "r") as f:
        np.testing.assert_array_equal(f["S/t/masks/hand"][()], SEGMENT["masks/hand"])


def test_a_partial_calibration_leaves_the_uncalibrated_cameras_out(tiny):
    rig, root = tiny["rig"], tiny["root"]
    rig.subset(rig.ids[2:]).save(root / "partial" / "cameras.json")
    result = run_annotate(tiny, "--calib", str(root / "partial"), "--keypoints", "simulated")
    assert result.exit_code == 0, result.output
    partial = root / "partial"
    assert f"S/t: left out camera(s) {rig.ids[0]}, {rig.ids[1]} (not in the calibration {partial})" in result.output
    ann = read_dataset(root / "D.h5")["S/t"]
    assert ann.cameras == rig.ids[2:] and ann.attrs["cameras_left_out"] == list(rig.ids[:2])
    assert ann.frame_index.shape[1] == ann.keypoints2d.shape[1] == 4
    chosen = ",".join(rig.ids[3:])
    result = run_annotate(tiny, "--calib", str(root / "calib"), "--keypoints", "simulated", "--cameras", chosen)
    assert result.exit_code == 0, result.output
    assert f"left out camera(s) {', '.join(rig.ids[:3])} (not chosen by --cameras)" in result.output
    assert (f"redone S/t: cameras {json.dumps(list(rig.ids[2:]))} -> {json.dumps(list(rig.ids[3:]))}; "
            "calibration changed") in result.output
    assert read_dataset(root / "D.h5")["S/t"].cameras == rig.ids[3:]
    rig.subset(rig.ids[:1]).save(root / "one" / "cameras.json")
    result = run_annotate(tiny, "--calib", str(root / "one"), "--keypoints", "simulated")
    assert result.exit_code == 2
    assert f"take.json: 1 of the take's cameras ({rig.ids[0]}) in the calibration {root / 'one'}; 2 are needed" \
        in result.output
