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
from pathlib import Path


def write_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically, creating its directory; returns the path."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
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
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target


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
