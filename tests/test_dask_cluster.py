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
from test_annotate import session  # noqa: F401  (a fixture)
from test_segment_cli import grasp_session  # noqa: F401  (a fixture)
from test_annotate_detect import CAMERAS, TICKS, installed, rendered  # noqa: F401  (fixtures)

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
                             "--chunk", "1", "--frames-per-task", "1", *extra, "-o", str(out)],
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

    from dataset_tools.annotate import take_key
    from manus_capture.cli import cli

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
