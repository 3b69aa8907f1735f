"""Stages on a real Dask cluster: `dask scheduler` and two `dask worker` processes over loopback
TCP, driven through the command line, against a run on this process alone."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_annotate import inline_result, session  # noqa: F401  (fixtures)
from test_annotate_detect import CAMERAS, TICKS, installed, rendered  # noqa: F401  (fixtures)
from test_segment_cli import grasp_session  # noqa: F401  (a fixture)

from dataset_tools.keypoints.keypoints2d import read_keypoints_h5

DASK = Path(sys.executable).with_name("dask")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """(scheduler address, the worker nannies' processes) of a scheduler and two one-thread workers."""
    from distributed import Client

    folder = tmp_path_factory.mktemp("dask")
    info = folder / "scheduler.json"
    log = open(folder / "cluster.log", "wb")
    common = ["--no-dashboard", "--scheduler-file", str(info)]
    procs = [subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", "0", *common],
                              cwd=folder, stdout=log, stderr=log)]
    deadline = time.monotonic() + 60
    while not info.exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    workers = [subprocess.Popen([str(DASK), "worker", "--host", "127.0.0.1", "--nthreads", "1",
                                 "--local-directory", str(folder / f"w{i}"), *common],
                                cwd=folder, stdout=log, stderr=log) for i in range(2)]
    procs += workers
    try:
        with Client(scheduler_file=str(info), timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
        yield json.loads(info.read_text())["address"], client_pids(info)
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(timeout=30)
        log.close()


def client_pids(info: Path) -> dict[str, int]:
    """Worker address -> the pid of its worker process (the nanny's child)."""
    from distributed import Client

    with Client(scheduler_file=str(info), timeout=30) as client:
        return client.run(os.getpid)


def detect(take: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "manus_capture.cli", "detect", str(take), "--device", "cpu",
                             "--chunk", "1", "--redetect-every", "1", "--frames-per-task", "1", *extra, "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def same_keypoints(a: Path, b: Path) -> None:
    ka, kb = read_keypoints_h5(a), read_keypoints_h5(b)
    assert set(ka.cameras) == set(kb.cameras) == set(CAMERAS)
    for cam in CAMERAS:
        assert ka.cameras[cam].keypoints.shape == (len(TICKS), 21, 3)
        np.testing.assert_allclose(kb.cameras[cam].keypoints, ka.cameras[cam].keypoints, atol=1e-3, err_msg=cam)


def test_detect_on_the_cluster_matches_a_local_run_and_survives_a_killed_worker(installed, rendered,  # noqa: F811
                                                                                 cluster, tmp_path):
    address, pids = cluster
    take = rendered["take"]
    local = detect(take, tmp_path / "local.h5")
    assert local.wait(timeout=300) == 0, local.stdout.read().decode()
    run = detect(take, tmp_path / "dask.h5", "--scheduler", address)
    assert run.wait(timeout=300) == 0, run.stdout.read().decode()
    same_keypoints(tmp_path / "local.h5", tmp_path / "dask.h5")

    # a worker killed while it holds a task: Dask gives the task to the other (or the restarted) worker
    from distributed import Client

    run = detect(take, tmp_path / "killed.h5", "--scheduler", address)
    killed = None
    with Client(address, timeout=30) as client:
        deadline = time.monotonic() + 120
        while killed is None and run.poll() is None and time.monotonic() < deadline:
            busy = [w for w, keys in client.processing().items() if keys]
            if busy:
                killed = pids[busy[0]]
                os.kill(killed, signal.SIGKILL)
            time.sleep(0.02)
    assert killed is not None, "the run ended before a worker could be killed"
    assert run.wait(timeout=300) == 0, run.stdout.read().decode()
    same_keypoints(tmp_path / "local.h5", tmp_path / "killed.h5")


def test_annotate_on_the_cluster_matches_a_local_run(session, cluster, tmp_path):  # noqa: F811
    from click.testing import CliRunner
    from test_annotate import dataset_arrays

    from manus_capture.cli import cli

    address, _ = cluster
    args = ["annotate", *map(str, session["takes"]), "--calib", str(session["root"] / "calib"), "--keypoints",
            "simulated"]
    for name, extra in (("local", []), ("dask", ["--scheduler", address])):
        res = CliRunner().invoke(cli, [*args, *extra, "-o", str(tmp_path / f"{name}.h5")])
        assert res.exit_code == 0, res.output
    local, dask = dataset_arrays(tmp_path / "local.h5"), dataset_arrays(tmp_path / "dask.h5")
    assert local.keys() == dask.keys() == {"S1/hand_01", "S1/grasp_01"}
    for key in local:
        for name, value in local[key].items():
            # a worker's BLAS may split a sum differently (test_annotate: 1e-16 relative)
            np.testing.assert_allclose(dask[key][name], value, rtol=1e-9, atol=1e-12, err_msg=f"{key} {name}")


def test_segment_on_the_cluster_matches_a_local_run(grasp_session, cluster, tmp_path):  # noqa: F811
    """One task per frame group: the masks from the cluster's two workers are the local run's."""
    import h5py
    from click.testing import CliRunner

    from manus_capture.cli import cli
    from manus_core.dataset import take_key

    address, _ = cluster
    take = grasp_session / "S" / "grasp"
    masks = {}
    for name, extra in (("local", []), ("dask", ["--scheduler", address])):
        out = tmp_path / f"{name}.h5"
        res = CliRunner().invoke(cli, ["segment", str(take), "--calib", str(grasp_session / "cameras.json"),
                                       "--background", str(grasp_session / "S" / "empty"), "--groups-per-task", "1",
                                       *extra, "-o", str(out)])
        assert res.exit_code == 0, res.output
        with h5py.File(out) as f:
            masks[name] = {n: f[take_key(take)][n][()] for n in ("masks/hand", "masks/object")}
    assert len(masks["local"]["masks/hand"]) >= 3 and masks["local"]["masks/hand"].any()
    for n, value in masks["local"].items():
        np.testing.assert_array_equal(masks["dask"][n], value, err_msg=n)


@pytest.fixture(scope="module")
def contact_inputs(session, inline_result, tmp_path_factory):  # noqa: F811
    """The session's DATASET.h5 with paint masks (every pixel) on its hand take, a MANUS-Hand
    checkpoint (untrained surfels on the template of the fitted bones) and an object checkpoint
    of points on the box the grasp take holds: the grasp has contacts, and they can be scored."""
    import torch
    from test_contacts import surface_samples

    from manus_capture.builder import surface_hand
    from manus_capture.splat.checkpoint import save_checkpoint
    from manus_capture.splat.gaussians import Gaussians
    from manus_core.dataset import add_arrays, read_dataset
    from rig.sim.motion import make_motion
    from rig.sim.objects import make_object

    folder = tmp_path_factory.mktemp("contacts")
    dataset = folder / "DATASET.h5"
    dataset.write_bytes(inline_result[0].read_bytes())
    data = read_dataset(dataset)
    hand = surface_hand(data["S1/grasp_01"].bone_lengths)
    save_checkpoint(folder / "hand.safetensors", hand.gaussians, kind="hand", extra=hand.extra_tensors())
    box = make_object("box")   # where the session's grasp take holds it (test_annotate.session)
    (R,), (t,) = make_motion("grasp", session["hand"], box, 1.0).object_poses(np.zeros(1))
    points = surface_samples(lambda x: box.sdf(x, (R, t)), t, box.radius + 0.01, 20_000)
    save_checkpoint(folder / "object.safetensors",
                    Gaussians.from_points(torch.as_tensor(points, dtype=torch.float32), sh_degree=0), kind="object")
    cameras = list(data["S1/hand_01"].cameras)
    width, height = session["rig"].size[0].astype(int)
    add_arrays(dataset, "S1/hand_01", {"paint/masks": np.ones((len(cameras), height, width), bool)},
               {"mask_cameras": cameras}, stage="segment")
    return {"dataset": dataset, "hand": folder / "hand.safetensors", "object": folder / "object.safetensors",
            "angles": data["S1/grasp_01"].joint_angles, "calib": session["root"] / "calib"}


def test_contacts_in_processes_are_the_inline_run_bit_for_bit(contact_inputs):
    """Soft contacts (every distance counts) of two tasks of 32 frames in two local processes are
    the maps of one task in this process, and of one model_contacts call over the take (whose
    instantaneous maps the tasks keep in float16, as DATASET.h5 does)."""
    from manus_capture.contact_tasks import contacts_in_tasks
    from manus_capture.contacts import model_contacts
    from manus_capture.splat.checkpoint import load_checkpoint
    from manus_capture.splat.hand import HandGaussians

    c = contact_inputs
    inline = contacts_in_tasks("S1/grasp_01", c["hand"], c["object"], c["angles"], 0.004, True)
    pooled = contacts_in_tasks("S1/grasp_01", c["hand"], c["object"], c["angles"], 0.004, True, workers=2,
                               frames_per_task=32)
    gaussians, extra, _ = load_checkpoint(c["hand"])
    direct = model_contacts(HandGaussians.from_checkpoint(gaussians, extra), c["angles"],
                            load_checkpoint(c["object"])[0], 0.004, True)
    assert inline.instant.shape == (len(c["angles"]), len(gaussians)) and inline.accumulated.max() > 0.5
    for maps in (pooled, direct):
        for name in ("instant", "accumulated", "object_instant", "object_accumulated"):
            got = getattr(maps, name)
            assert np.array_equal(got.astype(getattr(inline, name).dtype), getattr(inline, name)), name


def test_contacts_and_evaluate_on_the_cluster_match_local_runs(contact_inputs, cluster, tmp_path):
    """contacts in tasks of 32 frames on the two workers against one task here; evaluate's two
    scores (the Gaussian hand, the capsule baseline) on the workers against this process."""
    import h5py
    from click.testing import CliRunner

    from manus_capture.cli import cli

    address, _ = cluster
    c = contact_inputs
    models = ["--hand", str(c["hand"]), "--object", str(c["object"])]
    maps = {}
    for name, extra in (("local", []), ("dask", ["--scheduler", address, "--frames-per-task", "32"])):
        dataset = tmp_path / f"{name}.h5"
        dataset.write_bytes(c["dataset"].read_bytes())
        res = CliRunner().invoke(cli, ["contacts", str(dataset), "--take", "S1/grasp_01", *models, "--soft",
                                       "--device", "cpu", *extra])
        assert res.exit_code == 0, res.output
        with h5py.File(dataset) as f:
            maps[name] = {n: a[()] for n, a in f["S1/grasp_01/contacts"].items()}
    assert maps["local"]["accumulated"].max() > 0.5
    for n, value in maps["local"].items():
        assert np.array_equal(maps["dask"][n], value), n

    scores = {}
    for name, extra in (("local", []), ("dask", ["--scheduler", address])):
        res = CliRunner().invoke(cli, ["evaluate", str(c["dataset"]), "--grasp", "S1/grasp_01", "--canonical",
                                       "S1/hand_01", "--calib", str(c["calib"]), *models, "--gt-views", "3",
                                       "-o", str(tmp_path / f"{name}.json"), *extra])
        assert res.exit_code == 0, res.output
        scores[name] = json.loads((tmp_path / f"{name}.json").read_text())
    assert scores["local"]["contact_iou"] > 0 and scores["local"]["baseline_iou"] > 0
    assert scores["dask"] == scores["local"]


def test_reconstruct_on_the_cluster_matches_a_local_run(grasp_session, cluster, tmp_path):  # noqa: F811
    """Each model trained on a worker (one torch thread: its nanny's OMP_NUM_THREADS=1) is the one
    trained here with four (--threads 1 sets the count inside the task; with 4 it differs)."""
    import torch
    from click.testing import CliRunner

    from manus_capture.cli import cli
    from manus_capture.splat.checkpoint import load_checkpoint

    address, _ = cluster
    common = ["--cameras", str(grasp_session / "cameras.json"), "--iterations", "20"]
    commands = {"object": ["object", "--take", str(grasp_session / "S" / "object"), "--masks", "truth"],
                "hand": ["hand", "--take", str(grasp_session / "S" / "grasp"), "--truth", "--frames", "0",
                         "--test-frames", "3"]}
    threads = torch.get_num_threads()
    for kind, args in commands.items():
        checkpoints = {}
        for name, extra in (("local", []), ("dask", ["--scheduler", address])):
            checkpoints[name] = tmp_path / f"{kind}-{name}.safetensors"
            torch.set_num_threads(4)
            try:
                res = CliRunner().invoke(cli, ["reconstruct", *args, *common, *extra, "-o", str(checkpoints[name])])
            finally:
                torch.set_num_threads(threads)
            assert res.exit_code == 0, res.output
        (local, local_extra, local_meta), (dask, dask_extra, dask_meta) = map(load_checkpoint, checkpoints.values())
        assert dask_meta == local_meta
        for n, value in {**local.tensors(), **local_extra}.items():
            assert torch.equal({**dask.tensors(), **dask_extra}[n], value), f"{kind} {n}"
