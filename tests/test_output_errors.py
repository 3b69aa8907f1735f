"""A full disk or a read-only folder while a command writes its output (issue 22): one line on stderr
naming the path, exit 1, no traceback, no partial or temporary file or folder left behind, and the
outputs already there untouched.

The filesystem is real: a small tmpfs, filled to the last byte or remounted read-only. Where this
process may not mount (a CI container without CAP_SYS_ADMIN), the same commands run in a child
whose writes fail the same way: past a file size limit of 0 bytes (RLIMIT_FSIZE: EFBIG) for the
full disk, and in folders of mode 0555 without CAP_DAC_OVERRIDE, so that even root obeys the mode
(EACCES), for the read-only one.
"""

from __future__ import annotations

import ctypes
import dataclasses
import errno
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dataset_tools.hand.bones import BoneLengths, save_subject
from manus_capture.cli import cli
from manus_core.errors import OutputError
from manus_core.fileio import DISK_ERRNOS, as_output_error, atomic_output
from manus_core.skeleton import DEFAULT_BONE_LENGTHS
from rig.layouts import make_rig
from rig.record import RecordOptions, record_take
from rig.sim.cube import true_cameras

pytestmark = pytest.mark.faults

LIBC = ctypes.CDLL(None, use_errno=True)
MS_RDONLY, MS_REMOUNT = 1, 32
PR_CAPBSET_DROP, CAP_DAC_OVERRIDE = 24, 1
REASONS = {"full": r"(no space left on device \(ENOSPC\)|file too large \(EFBIG\))",
           "read-only": r"(read-only file system \(EROFS\)|permission denied \(EACCES\))"}


def _libc(call, *args) -> None:
    if call(*args) != 0:
        code = ctypes.get_errno()
        raise OSError(code, os.strerror(code))


def _file_size_limit_0() -> None:
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)   # a write past the limit fails with EFBIG, not a kill
    resource.setrlimit(resource.RLIMIT_FSIZE, (0, 0))


def _without_dac_override() -> None:
    if os.geteuid() == 0:   # root passes any mode with CAP_DAC_OVERRIDE; the child's python never gets it
        _libc(LIBC.prctl, PR_CAPBSET_DROP, CAP_DAC_OVERRIDE, 0, 0, 0)


def _fill(folder: Path) -> None:
    fd = os.open(folder / "filler", os.O_WRONLY | os.O_CREAT)
    try:
        while True:
            os.write(fd, bytes(65536))
    except OSError as exc:
        assert exc.errno == errno.ENOSPC, exc
    finally:
        os.close(fd)


@dataclasses.dataclass
class Place:
    """A folder where writes fail, and the command line run against it."""

    path: Path
    preexec: Callable[[], None] | None   # what the child does first (None: the filesystem refuses)

    def run(self, *args, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
        # no progress bars: stderr holds what the command says and nothing else
        env = {**os.environ, "TQDM_DISABLE": "1", **(env or {})}
        return subprocess.run([sys.executable, "-m", "manus_capture.cli", *map(str, args)], capture_output=True,
                              text=True, env=env, preexec_fn=self.preexec, timeout=120)


def _mount_tmpfs(folder: Path) -> bool:
    """A 4 MB tmpfs on `folder`; False where this process may not mount."""
    try:
        _libc(LIBC.mount, b"tmpfs", bytes(folder), b"tmpfs", 0, b"size=4m")
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.EACCES):
            raise
        return False
    return True


@contextmanager
def failing_place(folder: Path, how: str, contents: Callable[[Path], None]) -> Iterator[Place]:
    """`folder` holding what `contents` puts there, then full or read-only (see the module doc)."""
    folder.mkdir()
    if _mount_tmpfs(folder):
        try:
            contents(folder)
            if how == "full":
                _fill(folder)
            else:
                _libc(LIBC.mount, None, bytes(folder), None, MS_REMOUNT | MS_RDONLY, None)
            yield Place(folder, None)
        finally:
            _libc(LIBC.umount, bytes(folder))
        return
    contents(folder)
    if how == "full":
        yield Place(folder, _file_size_limit_0)
        return
    folders = [folder, *(p for p in folder.rglob("*") if p.is_dir())]
    for f in folders:
        f.chmod(0o555)
    try:
        yield Place(folder, _without_dac_override)
    finally:
        for f in folders:
            f.chmod(0o755)


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every file (its bytes) and folder (None) under `folder`."""
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else None for p in sorted(folder.rglob("*"))}


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> Path:
    """A recorded simulated take with its sync report, its true calibration, a subject file and a
    DATASET.h5 of it; run here first, so that the children find every cache (fonts, numba) made."""
    root = tmp_path_factory.mktemp("made")
    rig = make_rig("cube53", cameras=3, resolution=(64, 36), sync="hardware-trigger")
    rig = dataclasses.replace(rig, sim=dataclasses.replace(rig.sim, supersample=1))
    assert record_take(rig, root / "S", "g", "grasp", 0.1, RecordOptions(use_leds=False)).status == "complete"
    true_cameras(rig).save(root / "cameras.json")
    save_subject(root / "s01.json", "s01", BoneLengths(DEFAULT_BONE_LENGTHS, np.full(20, np.nan), np.zeros(20, int)))
    runner = CliRunner()
    runner.invoke(cli, ["sync-report", str(root / "S" / "g")])
    assert (root / "S" / "g" / "sync_report.json").exists()
    done = runner.invoke(cli, [*annotate_args(root, root / "D.h5")])
    assert done.exit_code == 0, done.output
    return root


def annotate_args(made: Path, output: Path) -> list[str]:
    return ["annotate", str(made / "S" / "g"), "--calib", str(made / "cameras.json"), "-o", str(output),
            "--keypoints", "simulated", "--bones", str(made / "s01.json")]


# command -> (what the folder holds first, the command line, the path its error names)
COMMANDS = {
    # the take is in the folder, with the report of an earlier run, which must stay as it was
    "sync-report": (lambda made, place: shutil.copytree(made / "S", place / "S"),
                    lambda made, place: ["sync-report", "--force", place / "S" / "g"],
                    lambda place: place / "S" / "g"),
    # an earlier plot is replaced (--force): it must stay as it was
    "stats --plot": (lambda made, place: (place / "plot.png").write_bytes(b"an earlier plot"),
                     lambda made, place: ["stats", made / "D.h5", "--plot", place / "plot.png", "--force"],
                     lambda place: place / "plot.png"),
    # a new folder for the output: neither it nor the parts folder beside DATASET.h5 may stay
    "annotate -o": (lambda made, place: None,
                    lambda made, place: annotate_args(made, place / "out" / "D.h5"),
                    lambda place: place / "out"),
}


@pytest.mark.parametrize("command, how", [(c, "full") for c in COMMANDS] +
                         [("stats --plot", "read-only"), ("annotate -o", "read-only")])
def test_a_failed_write_is_one_line_naming_the_path(made, tmp_path, command, how):
    contents, args, named = COMMANDS[command]
    with failing_place(tmp_path / "place", how, lambda place: contents(made, place)) as place:
        before = snapshot(place.path)
        done = place.run(*args(made, place.path))
        after = snapshot(place.path)
    lines = done.stderr.splitlines()
    assert done.returncode == 1, done.stderr
    assert len(lines) == 1 and lines[0].startswith(f"Error: {named(place.path)}"), done.stderr
    assert re.search(f"cannot write: {REASONS[how]}$", lines[0]), lines[0]
    assert after == before     # no partial file, no temporary file or folder, earlier outputs as they were


def test_a_folder_that_cannot_be_made_is_one_line(tmp_path):
    """Outside fileio too: `models install` cannot make its cache folder (the CLI maps the OSError)."""
    with failing_place(tmp_path / "place", "read-only", lambda place: None) as place:
        done = place.run("models", "install", "mediapipe-hand", env={"XDG_CACHE_HOME": str(place.path / "cache")})
        after = snapshot(place.path)
    # onnxruntime, on import, warns that it cannot keep its telemetry id in that cache: its line, not ours
    ours = [line for line in done.stderr.splitlines() if "onnxruntime" not in line]
    assert done.returncode == 1 and len(ours) == 1, done.stderr
    assert re.fullmatch(f"Error: {place.path / 'cache'}: {REASONS['read-only']}", ours[0]), done.stderr
    assert after == {}


@pytest.mark.parametrize("code", sorted(DISK_ERRNOS))
def test_every_disk_errno_becomes_an_output_error_and_leaves_nothing(tmp_path, code):
    target = tmp_path / "new" / "deeper" / "out.bin"
    with pytest.raises(OutputError) as err:
        with atomic_output(target) as tmp:
            tmp.write_bytes(b"half")
            raise OSError(code, os.strerror(code))   # what the writer met
    assert str(err.value) == f"{target}: cannot write: {os.strerror(code).lower()} ({errno.errorcode[code]})"
    assert err.value.exit_code == 1 and err.value.errno == code
    assert list(tmp_path.iterdir()) == []


def test_h5py_errors_without_an_errno_are_read_from_the_message():
    """h5py at times gives an OSError with errno None, and for a failed copy of an object (as
    DatasetWriter.finalize makes) a RuntimeError; both carry the C library's errno in the message."""
    h5 = OSError("Can't synchronously write data (file write failed: time = Wed Nov 25 17:03:56 2026\n, "
                 "filename = '/data/D.h5', file descriptor = 3, errno = 28, error message = 'No space left on "
                 "device', buf = 0x7f37606a4810, total write size = 736512, offset = 65536)")
    assert str(as_output_error(h5)) == "/data/D.h5: no space left on device (ENOSPC)"
    assert str(as_output_error(h5, "out/D.h5")) == "out/D.h5: cannot write: no space left on device (ENOSPC)"
    copy = RuntimeError("Unable to synchronously copy object (file write failed: time = Wed Nov 25 17:21:31 2026\n, "
                        "filename = '/data/.D.h5.x1.tmp', file descriptor = 3, errno = 28, error message = 'No space "
                        "left on device', buf = 0x55a4b173c9d1, total write size = 5278, offset = 86016)")
    assert str(as_output_error(copy, "/data/D.h5")) == "/data/D.h5: cannot write: no space left on device (ENOSPC)"
    assert as_output_error(OSError("Unable to open object (object 'masks' doesn't exist)")) is None
    assert as_output_error(RuntimeError("dictionary changed size during iteration")) is None
    assert as_output_error(FileNotFoundError(errno.ENOENT, "No such file or directory", "x")) is None
