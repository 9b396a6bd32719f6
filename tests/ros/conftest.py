"""Fixtures for the DDS tests: node processes and a probe node, always cleaned up.

Every process these tests start (and this one) runs with a ``ROS_DOMAIN_ID`` unique to the test
run and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (set by :mod:`rosutil` on import). Node
processes run in their own process groups and are stopped (SIGINT, then SIGKILL of the whole
group) by the fixture's finaliser, whatever the test's outcome.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from rosutil import Nodes, Probe, Recorder


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark every test of this directory ``ros``."""
    here = Path(__file__).parent
    for item in items:
        if Path(str(item.fspath)).is_relative_to(here):
            item.add_marker(pytest.mark.ros)


@pytest.fixture()
def nodes(tmp_path: Path) -> Iterator[Nodes]:
    """Node processes, killed (process groups) after the test."""
    n = Nodes(tmp_path)
    try:
        yield n
    finally:
        n.stop_all()


@pytest.fixture()
def probe() -> Iterator[Probe]:
    """A probe node, destroyed after the test."""
    p = Probe()
    try:
        yield p
    finally:
        p.close()


@pytest.fixture()
def recorder() -> Iterator[Callable[..., Recorder]]:
    """Starts recorders; each is stopped after the test whatever its outcome."""
    started: list[Recorder] = []

    def start(bag: Path, *args: str, **popen: Any) -> Recorder:
        started.append(Recorder(bag, *args, **popen))
        return started[-1]

    try:
        yield start
    finally:
        for rec in started:
            rec.close()
