"""Allocator settings of armourcam processes (armourcam.heap)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from armourcam.heap import ALLOCATOR_VARIABLES, keep_freed_memory

# A frame's worth of large temporaries (8 x 256 KB), allocated, touched and freed 20 times in a
# fresh process; prints the minor page faults of the 20 frames after three warm-up frames.
_FRAMES = """
import resource, sys
import numpy as np
from armourcam.heap import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
def frames(count):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(count):
        blocks = [np.ones(32 * 1024) for _ in range(8)]
        del blocks
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
frames(3)
print(frames(20))
"""


def _faults(mode: str) -> int:
    env = {k: v for k, v in os.environ.items() if k not in ALLOCATOR_VARIABLES}
    out = subprocess.run(
        [sys.executable, "-c", _FRAMES, mode], env=env, capture_output=True, text=True, check=True
    )
    return int(out.stdout.split()[-1])


def test_freed_memory_stays_in_the_process() -> None:
    """With glibc's defaults every frame faults its temporaries' pages back in; once applied,
    the pages are reused."""
    if not keep_freed_memory():
        pytest.skip("no glibc mallopt here (or the environment sets the thresholds)")
    assert _faults("default") > 20 * 8 * 32  # most of 64 pages per block, every frame
    assert _faults("keep") < 100


def test_environment_setting_wins(monkeypatch: pytest.MonkeyPatch) -> None:
    """An explicit MALLOC_TRIM_THRESHOLD_ leaves the allocator as the environment set it."""
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "131072")
    assert keep_freed_memory() is False
