"""The shipped Fast DDS profile and how processes pick it up."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest

from armourcam import graph

NS = {"dds": "http://www.eprosima.com"}


def test_profile_has_a_shared_memory_segment_for_whole_frames() -> None:
    """A 3008x2000 mono8 frame (6 MB) fits the segment many times over, and the profile is the
    default participant profile (so rmw's participants get it)."""
    root = ET.parse(graph.DDS_PROFILE).getroot()
    shm = [
        d
        for d in root.iterfind(".//dds:transport_descriptor", NS)
        if d.findtext("dds:type", namespaces=NS) == "SHM"
    ]
    assert len(shm) == 1
    assert int(shm[0].findtext("dds:segment_size", namespaces=NS) or 0) >= 8 * 3008 * 2000
    participant = root.find(".//dds:participant", NS)
    assert participant is not None and participant.get("is_default_profile") == "true"


class _Shm:
    """What ``os.statvfs`` reports for a ``/dev/shm`` of ``free`` bytes."""

    def __init__(self, free: int) -> None:
        self.f_bavail, self.f_frsize = free // 4096, 4096


@pytest.mark.parametrize(("free", "expected"), [(24 << 30, True), (64 << 20, False)])
def test_use_dds_profile_needs_room_in_dev_shm(
    monkeypatch: pytest.MonkeyPatch, free: int, expected: bool
) -> None:
    """Set for a roomy /dev/shm; a container's 64 MB one keeps Fast DDS' own small segments."""
    monkeypatch.delenv("FASTDDS_DEFAULT_PROFILES_FILE", raising=False)
    monkeypatch.setattr(graph.os, "statvfs", lambda path: _Shm(free))
    graph.use_dds_profile()
    value = graph.os.environ.get("FASTDDS_DEFAULT_PROFILES_FILE")
    assert value == (str(graph.DDS_PROFILE) if expected else None)


def test_use_dds_profile_keeps_a_rigs_own_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FASTDDS_DEFAULT_PROFILES_FILE", "/etc/rig/dds.xml")
    monkeypatch.setattr(graph.os, "statvfs", lambda path: _Shm(24 << 30))
    graph.use_dds_profile()
    assert graph.os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] == "/etc/rig/dds.xml"
