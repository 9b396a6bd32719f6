"""Atomic file writes: readers see the old file or the new one, never a torn one.

The data goes to a temporary file in the target's directory, is flushed to disk, then replaces
the target with ``os.replace`` (atomic on POSIX within one file system), so a report or a
baseline survives a crash or a restart mid-write. The temporary file is created private
(``mkstemp``); before it replaces the target it gets the target's own permissions, or for a new
file those of an ordinary one (``0o666`` less the process' umask), so colleagues read reports as
they read any other output.
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Mapping
from pathlib import Path


def write_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically, creating its directory; returns the path."""
    (target,) = write_atomic_set({Path(path): data})
    return target


def write_atomic_set(files: Mapping[Path, bytes]) -> list[Path]:
    """Write several files so that a failure leaves every one of them as it was.

    Each file's data first goes to disk under a temporary name beside it (where a full disk or
    an unwritable directory fails, before any target is touched); only once all are written do
    they replace their targets, by renames, which need no space. So a report directory never
    mixes a new ``report.json`` with an old ``overlay.png``. Returns the paths, in order.
    """
    written: list[tuple[str, Path]] = []
    try:
        for path, data in files.items():
            target = Path(path)
            make_directory(target.parent)
            written.append((_written_beside(target, data), target))
        for tmp, target in written:
            os.replace(tmp, target)
    except BaseException:
        for tmp, _ in written:
            Path(tmp).unlink(missing_ok=True)
        raise
    return [target for _, target in written]


def make_directory(path: Path) -> None:
    """Create the directory ``path`` and its parents where missing; one in the way that is a
    file is named as such (``mkdir`` says only "File exists")."""
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                raise NotADirectoryError(f"{p} is a file, not a directory")
            break
    path.mkdir(parents=True, exist_ok=True)


def _written_beside(target: Path, data: bytes) -> str:
    """``data`` flushed to disk in a new temporary file beside ``target``, with the target's
    permissions (or an ordinary new file's); returns its path."""
    try:
        mode = stat.S_IMODE(target.stat().st_mode)
    except FileNotFoundError:
        mode = 0o666 & ~_umask()
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fchmod(fh.fileno(), mode)
            os.fsync(fh.fileno())
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return tmp


def _umask() -> int:
    """The process' umask, read without changing it where the system tells it (Linux), since
    setting it, even briefly, would apply to files other threads create meanwhile."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
