"""A frame that cannot be decoded is logged and dropped; the detector node lives on."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import pytest
from rosutil import Nodes, Probe

from armourcam import image_codec
from armourcam.graph import stream_qos


def good_image(stamp: Any) -> Any:
    from sensor_msgs.msg import Image

    img = np.full((120, 160), 128, np.uint8)
    msg = Image(**image_codec.image_to_msg_fields(img))
    msg.header.stamp = stamp
    return msg


def bad_images(stamp: Any) -> dict[str, Any]:
    """One of each kind of undecodable raw frame, with the words its error must contain."""
    from sensor_msgs.msg import Image

    img = np.full((120, 160), 128, np.uint8)
    unknown = Image(**image_codec.image_to_msg_fields(img))
    unknown.encoding = "weird42"
    short_step = Image(**image_codec.image_to_msg_fields(img))
    short_step.step = 100  # < width
    zero = Image(height=0, width=0, encoding="mono8", step=0, data=b"")
    truncated = Image(**image_codec.image_to_msg_fields(img))
    truncated.data = bytes(truncated.data[:5000])
    out = {"weird42": unknown, "step": short_step, "zero": zero, "short": truncated}
    for m in out.values():
        m.header.stamp = stamp
    return out


def two_detectors(
    nodes: Nodes, probe: Probe, params: dict[str, Any] | None = None
) -> tuple[Any, Any, dict[str, list[Any]]]:
    """A raw-image detector ("raw") and a compressed-image one ("jpeg", its output on
    ``/armourcam/detections_jpeg``), both with ``params``; returns the probe's raw and JPEG
    publishers, matched by then, and the detections each detector published, by label."""
    from sensor_msgs.msg import CompressedImage, Image, PointCloud2

    nodes.start("fiducial_detector", params=params, label="raw")
    nodes.start(
        "fiducial_detector",
        "-r",
        "__node:=fiducial_detector_jpeg",
        "-r",
        "/armourcam/detections:=/armourcam/detections_jpeg",
        params={"transport": "compressed", **(params or {})},
        label="jpeg",
    )
    qos = stream_qos("reliable", 20)
    raw_pub = probe.node.create_publisher(Image, "/camera/image_raw", qos)
    jpeg_pub = probe.node.create_publisher(CompressedImage, "/camera/image_raw/compressed", qos)
    outputs: dict[str, list[Any]] = {"raw": [], "jpeg": []}
    probe.node.create_subscription(PointCloud2, "/armourcam/detections", outputs["raw"].append, qos)
    probe.node.create_subscription(
        PointCloud2, "/armourcam/detections_jpeg", outputs["jpeg"].append, qos
    )
    assert probe.spin_until(
        lambda: raw_pub.get_subscription_count() and jpeg_pub.get_subscription_count(), 20.0
    ), nodes.log("raw") + nodes.log("jpeg")
    probe.spin_for(1.0)
    return raw_pub, jpeg_pub, outputs


def test_bad_frames_are_dropped_and_the_node_stays_up(nodes: Nodes, probe: Probe) -> None:
    from sensor_msgs.msg import CompressedImage

    raw_pub, jpeg_pub, outputs = two_detectors(nodes, probe)

    stamp = probe.node.get_clock().now().to_msg()
    for msg in bad_images(stamp).values():
        raw_pub.publish(msg)
    ok, buf = cv2.imencode(".jpg", np.full((120, 160), 128, np.uint8))
    assert ok
    corrupt = CompressedImage(format="jpeg", data=buf.tobytes()[: len(buf) // 3])
    garbage = CompressedImage(format="jpeg", data=b"\xff\xd8 this is not a jpeg")
    for m in (corrupt, garbage):
        m.header.stamp = stamp
        jpeg_pub.publish(m)
    probe.spin_for(0.5)

    # After the bad frames, good ones still go through: the nodes live on.
    good_stamp = probe.node.get_clock().now().to_msg()
    raw_pub.publish(good_image(good_stamp))
    good_jpeg = CompressedImage(format="jpeg", data=buf.tobytes())
    good_jpeg.header.stamp = good_stamp
    jpeg_pub.publish(good_jpeg)
    assert probe.spin_until(lambda: outputs["raw"] and outputs["jpeg"], 20.0), nodes.log(
        "raw"
    ) + nodes.log("jpeg")
    probe.spin_for(0.5)
    # Exactly one output each (the good frame), carrying the good frame's header.
    assert len(outputs["raw"]) == 1 and len(outputs["jpeg"]) == 1
    assert outputs["raw"][0].header.stamp == good_stamp
    assert nodes.alive("raw") and nodes.alive("jpeg")
    raw_log, jpeg_log = nodes.log("raw"), nodes.log("jpeg")
    assert raw_log.count("dropped") == 4, raw_log
    assert "weird42" in raw_log
    assert jpeg_log.count("dropped") == 2, jpeg_log


def test_a_non_finite_parameter_stops_the_node_at_start_up(nodes: Nodes) -> None:
    """NaN passes every comparison and infinity the minimum: both are refused at start-up with
    one line naming the parameter (exit 2), not taken in to drop every frame or crash later."""
    for label, params in (
        ("nan", {"diameter_mm": ".nan"}),
        ("inf", {"diagnostics_period_s": ".inf"}),
    ):
        proc = nodes.start("pose_estimator", params=params, label=label)
        assert proc.wait(timeout=30) == 2, nodes.log(label)
        (name,) = params
        assert f"parameter {name} must be a finite number" in nodes.log(label)


def test_a_remapped_image_topic_moves_the_compressed_transport_too(
    nodes: Nodes, probe: Probe
) -> None:
    """``-r /camera/image_raw:=/cam2/image_raw`` with ``transport: compressed`` subscribes to
    ``/cam2/image_raw/compressed`` (it stayed on ``/camera/...``), as image_transport does."""
    from sensor_msgs.msg import CompressedImage, PointCloud2

    nodes.start(
        "fiducial_detector",
        "-r",
        "/camera/image_raw:=/cam2/image_raw",
        params={"transport": "compressed"},
        label="cam2",
    )
    qos = stream_qos("reliable", 10)
    pub = probe.node.create_publisher(CompressedImage, "/cam2/image_raw/compressed", qos)
    out: list[Any] = []
    probe.node.create_subscription(PointCloud2, "/armourcam/detections", out.append, qos)
    assert probe.spin_until(lambda: pub.get_subscription_count() > 0, 20.0), nodes.log("cam2")
    probe.spin_for(1.0)
    ok, buf = cv2.imencode(".jpg", np.full((120, 160), 128, np.uint8))
    assert ok
    pub.publish(CompressedImage(format="jpeg", data=buf.tobytes()))
    assert probe.spin_until(lambda: out, 20.0), nodes.log("cam2")
    assert "detecting on /cam2/image_raw/compressed" in nodes.log("cam2")


def _jpeg_damaged_but_decodable() -> dict[str, bytes]:
    """JPEGs libjpeg decodes with grey filling (or used to pass the old end-marker check):
    cut short with an ``FF D9`` left in a comment segment, and headers plus an end-of-image
    marker without scan data; with the words the node's log must give for each."""
    rng = np.random.default_rng(3)
    ok, buf = cv2.imencode(".jpg", rng.integers(0, 256, size=(40, 48)).astype(np.uint8))
    assert ok
    jpeg = buf.tobytes()
    jpeg = jpeg[:2] + b"\xff\xfe\x00\x08ab\xff\xd9cd" + jpeg[2:]
    sos = jpeg.index(b"\xff\xda")
    scan = sos + 2 + int.from_bytes(jpeg[sos + 2 : sos + 4], "big")
    return {
        "no end-of-image marker, data is truncated": jpeg[: (scan + len(jpeg)) // 2],
        "no image data before the end-of-image marker": jpeg[:scan] + b"\xff\xd9",
    }


def test_damaged_jpegs_are_dropped_and_tiny_images_answered_empty(
    nodes: Nodes, probe: Probe
) -> None:
    """A damaged JPEG that libjpeg would still decode is logged, dropped and counted in
    /diagnostics; a valid image too small to hold a fiducial is answered with an empty cloud
    carrying its header (downstream stays in step frame by frame), a malformed one is still
    dropped; the nodes live on."""
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import CompressedImage, Image

    raw_pub, jpeg_pub, outputs = two_detectors(nodes, probe, {"diagnostics_period_s": 0.2})
    diagnostics: dict[str, dict[str, str]] = {}

    def on_diagnostics(msg: Any) -> None:
        for s in msg.status:
            label = "jpeg" if s.name.startswith("/fiducial_detector_jpeg:") else "raw"
            diagnostics[label] = {kv.key: kv.value for kv in s.values}

    probe.node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 50)

    def stamped(msg: Any, frame: int) -> Any:
        msg.header.stamp.sec, msg.header.frame_id = 1000 + frame, f"cam{frame}"
        return msg

    # Raw: valid images of 1x1, 7x7 and 5x40 (colour) pixels, and a malformed tiny one.
    tiny = [
        np.zeros((1, 1), np.uint8),
        np.full((7, 7), 200, np.uint8),
        np.zeros((5, 40, 3), np.uint8),
    ]
    for i, img in enumerate(tiny):
        raw_pub.publish(stamped(Image(**image_codec.image_to_msg_fields(img)), i))
    malformed = Image(**image_codec.image_to_msg_fields(np.zeros((4, 4), np.uint8)))
    malformed.step = 3
    raw_pub.publish(stamped(malformed, 9))
    # JPEG: the damaged ones, then a valid 6x6 one.
    for i, data in enumerate(_jpeg_damaged_but_decodable().values()):
        jpeg_pub.publish(stamped(CompressedImage(format="jpeg", data=data), 10 + i))
    small = image_codec.compressed_to_msg_fields(np.full((6, 6), 90, np.uint8), "jpeg")
    jpeg_pub.publish(stamped(CompressedImage(**small), 20))

    assert probe.spin_until(lambda: len(outputs["raw"]) >= 3 and outputs["jpeg"], 20.0), nodes.log(
        "raw"
    ) + nodes.log("jpeg")
    probe.spin_for(0.5)
    # One empty cloud per valid tiny image, with its header; nothing for the bad frames.
    for label, frames in (("raw", [0, 1, 2]), ("jpeg", [20])):
        got = outputs[label]
        assert [(m.header.stamp.sec, m.header.frame_id) for m in got] == [
            (1000 + f, f"cam{f}") for f in frames
        ], nodes.log(label)
        assert all(m.width == 0 and len(m.data) == 0 for m in got)
    assert nodes.alive("raw") and nodes.alive("jpeg")
    assert probe.spin_until(
        lambda: (
            diagnostics.get("raw", {}).get("frames_received") == "4"
            and diagnostics.get("jpeg", {}).get("frames_received") == "3"
        ),
        10.0,
    ), diagnostics
    assert (diagnostics["raw"]["frames_dropped"], diagnostics["raw"]["frames_too_small"]) == (
        "1",
        "3",
    )
    assert (diagnostics["jpeg"]["frames_dropped"], diagnostics["jpeg"]["frames_too_small"]) == (
        "2",
        "1",
    )
    jpeg_log = nodes.log("jpeg")
    assert jpeg_log.count("dropped") == 2, jpeg_log
    for words in _jpeg_damaged_but_decodable():
        assert words in jpeg_log, jpeg_log
    assert "Corrupt JPEG data" not in jpeg_log  # refused before libjpeg saw it
    assert "smaller than the smallest fiducial" in nodes.log("raw")


def test_the_detectors_size_cut_off_is_an_image_the_core_takes() -> None:
    """The node answers images smaller than ``MIN_OUTER_DIAMETER_PX`` itself (empty cloud) and
    hands larger ones to the core: that size must be one the core accepts (it refuses images
    under 8 px as unable to hold a fiducial)."""
    import math

    from fiducial_detector import DetectorError, detect
    from fiducial_detector.detect import MIN_OUTER_DIAMETER_PX

    side = math.ceil(MIN_OUTER_DIAMETER_PX)
    assert detect(np.zeros((side, side), np.uint8)) == []
    assert detect(np.zeros((side, 3 * side, 3), np.uint8)) == []
    with pytest.raises(DetectorError, match="too small to hold a fiducial"):
        detect(np.zeros((7, 7), np.uint8))
