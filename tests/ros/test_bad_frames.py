"""A frame that cannot be decoded is logged and dropped; the detector node lives on."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
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


def test_bad_frames_are_dropped_and_the_node_stays_up(nodes: Nodes, probe: Probe) -> None:
    from sensor_msgs.msg import CompressedImage, Image, PointCloud2

    nodes.start("fiducial_detector", label="raw")
    nodes.start(
        "fiducial_detector",
        "-r",
        "__node:=fiducial_detector_jpeg",
        "-r",
        "/armourcam/detections:=/armourcam/detections_jpeg",
        params={"transport": "compressed"},
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
