"""Atomic file output: a command never leaves a half-written file under its final name.

A write that fails for want of space or permission (DISK_ERRNOS) leaves nothing behind, neither
the temporary file nor a folder made for the output, and becomes one OutputError naming the
output: "out/D.h5: cannot write: no space left on device (ENOSPC)".
"""

from __future__ import annotations

import errno
import os
import re
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from manus_core.errors import OutputError

# Failed writes that are the user's to fix (free space, a quota or file size limit, permissions, a
# read-only mount), not bugs.
DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EACCES, errno.EPERM, errno.EROFS})


def disk_errno(exc: BaseException) -> int | None:
    """The errno of a failed write that is one of DISK_ERRNOS, else None.

    h5py raises OSError for a failed write with, at times, errno None, and RuntimeError for a
    failed copy of an object; either way the errno is in its message ("... errno = 28, error
    message = 'No space left on device' ...").
    """
    if not isinstance(exc, (OSError, RuntimeError)):
        return None
    if getattr(exc, "errno", None) is not None:
        return exc.errno if exc.errno in DISK_ERRNOS else None
    text = str(exc)
    found = re.search(r"errno = (\d+)", text)
    if found:
        return int(found[1]) if int(found[1]) in DISK_ERRNOS else None
    return next((code for code in sorted(DISK_ERRNOS) if os.strerror(code) in text), None)


def as_output_error(exc: BaseException, path: str | os.PathLike | None = None) -> OutputError | None:
    """`exc` as one line if it is a write that failed for one of DISK_ERRNOS, else None.

    With `path` (the output being written): "PATH: cannot write: REASON (ENAME)". Without, the
    file the error names (h5py names it only in its message), or none when it names none.
    """
    code = disk_errno(exc)
    if code is None:
        return None
    reason = f"{os.strerror(code).lower()} ({errno.errorcode[code]})"
    if path is not None:
        error = OutputError(f"{path}: cannot write: {reason}")
    else:
        named = getattr(exc, "filename", None) or next(iter(re.findall(r"name = '([^']*)'", str(exc))), None)
        error = OutputError(f"{named}: {reason}" if named else f"cannot write: {reason}")
    error.errno = code
    return error


def _missing_folders(folder: Path) -> list[Path]:
    """`folder` and its ancestors that do not exist yet, deepest first."""
    missing = []
    while not folder.exists() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    return missing


@contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside `path` for a writer (h5py, a copy to edit, ...). When the block ends
    without error the file is fsynced and renamed over `path`; otherwise it is removed, with the
    folders made for it, and a failed write of DISK_ERRNOS is raised as an OutputError naming
    `path` (see the module doc)."""
    path = Path(path)
    made = _missing_folders(path.parent)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.close(fd)
        yield Path(tmp)
        # mkstemp creates 0600; give the file the permissions an ordinary open() would
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        for folder in made:
            try:
                folder.rmdir()
            except OSError:   # not empty: something else was written there meanwhile
                break
        error = None if isinstance(exc, OutputError) else as_output_error(exc, path)
        if error is not None:
            raise error from exc
        raise


def write_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write bytes to `path` atomically (see atomic_output)."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)
