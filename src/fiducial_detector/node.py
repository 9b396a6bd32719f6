"""ROS 2 node ``fiducial_detector``: camera images -> per-frame fiducial detections.

A thin shell around :func:`fiducial_detector.detect` (paper section 3, steps 1-4): decode the
image message with :mod:`armourcam.image_codec`, detect, publish the detections as rows of
``armourcam_msgs/FiducialDetectionRecord`` in a ``sensor_msgs/PointCloud2`` whose header is the
image's (stamp and frame_id), so downstream nodes and bags can line outputs up with frames.

Topics
------
Default names are relative: they resolve in the node's namespace (``-r __ns:=/cell2``:
``/cell2/camera/image_raw``; without one ``/camera/image_raw``). ``/diagnostics`` is absolute.

Subscribed
    ``image_topic`` (default ``camera/image_raw``), ``sensor_msgs/Image`` when
    ``transport`` is ``raw`` (mono8, mono16, rgb8, bgr8, rgba8, bgra8, bayer_*8/16; ``step``
    honoured); ``<image_topic>/compressed``, ``sensor_msgs/CompressedImage`` (jpeg, png) when
    ``transport`` is ``compressed``. QoS per ``qos``: ``reliable`` (replay) or ``sensor_data``
    (live camera, best effort), KEEP_LAST ``queue_depth``.
Published
    ``detections_topic`` (default ``armourcam/detections``), ``sensor_msgs/PointCloud2`` of
    ``FiducialDetectionRecord`` rows (fields generated from ``msg/``), QoS as the input
    (``reliable`` or ``sensor_data``), one message per decoded frame (an empty cloud when
    nothing is found, and for a valid image smaller than the smallest fiducial looked for,
    ``MIN_OUTER_DIAMETER_PX`` = 18 px, on either side: ``frames_too_small``).
    ``/diagnostics``, ``diagnostic_msgs/DiagnosticArray``, reliable, every
    ``diagnostics_period_s``: frames received / published / dropped / too small, the last
    problem, the age of the last image (``last_input_age_s``); WARN while a frame was dropped
    in the last 30 s (:class:`armourcam.graph.RecentProblems`) and while no image came for more than
    ``stale_after_s`` after earlier ones (a stalled camera; before the first image: OK,
    :class:`armourcam.graph.InputAge`).

A frame that cannot be decoded (unknown encoding, wrong ``step``, zero size, a JPEG truncated
before its end-of-image marker or without scan data: :func:`armourcam.image_codec.jpeg_damage`...)
or detected is logged with the reason, counted (``frames_dropped``) and dropped; the node lives on.

Parameters (all read-only unless noted): see :data:`PARAMS` (``image_topic``, ``transport``,
``detections_topic``, ``qos``, ``queue_depth``, ``design``, ``subpixel``, ``decimate``,
``diagnostics_period_s``, ``stale_after_s``).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from typing import Any, cast

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image, PointCloud2, PointField

from armourcam import image_codec, records
from armourcam.graph import (
    FrameTimes,
    GraphError,
    InputAge,
    Param,
    RecentProblems,
    declare_parameters,
    merge_status,
    publish_diagnostics,
    record_qos,
    run_node,
    stream_qos,
)

from .design import DESIGNS
from .detect import (
    DECIMATE_FACTORS,
    MIN_OUTER_DIAMETER_PX,
    SUBPIXEL_METHODS,
    DesignChoice,
    SubpixelMethod,
)

PARAMS = (
    Param("image_topic", "camera/image_raw", "Camera image topic (raw images)."),
    Param(
        "transport",
        "raw",
        "raw: sensor_msgs/Image on image_topic; compressed: sensor_msgs/CompressedImage on "
        "image_topic + '/compressed'.",
        choices=("raw", "compressed"),
    ),
    Param(
        "detections_topic",
        "armourcam/detections",
        "Output: sensor_msgs/PointCloud2 of FiducialDetectionRecord rows, header of the image.",
    ),
    Param(
        "qos",
        "reliable",
        "QoS of input and output: reliable for replay, sensor_data for a live camera.",
        choices=("reliable", "sensor_data"),
    ),
    Param("queue_depth", 10, "KEEP_LAST depth of input and output queues.", minimum=1),
    Param(
        "design",
        "any",
        "Fiducial design to look for (any: both designs).",
        choices=("any", *sorted(DESIGNS)),
    ),
    Param(
        "subpixel",
        "profile",
        "Sub-pixel ellipse method: profile (fast, for live frames) or ml (the edge model, "
        "about half the centre noise, several times slower).",
        choices=SUBPIXEL_METHODS,
    ),
    Param(
        "decimate",
        1,
        "Candidate search on the image reduced by this factor (1-4; codes and fits use the full "
        "image). 2 saves about 9 ms on a 6 Mpx frame; fiducials must then be at least 45 px "
        "across (ring design) or 60 px (dot).",
        choices=DECIMATE_FACTORS,
    ),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics, s.", minimum=0.1),
    Param(
        "stale_after_s",
        5.0,
        "/diagnostics WARN when no image came for this long after earlier ones, s (0: never).",
        minimum=0.0,
    ),
)


@dataclass(frozen=True, slots=True)
class DetectorNodeConfig:
    """Validated parameters of the node (see :data:`PARAMS`)."""

    image_topic: str
    transport: str
    detections_topic: str
    qos: str
    queue_depth: int
    design: str
    subpixel: str
    decimate: int
    diagnostics_period_s: float
    stale_after_s: float


class FiducialDetectorNode(Node):
    """Images in, detections out (one message per decodable frame)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("fiducial_detector", **kwargs)
        values = declare_parameters(self, PARAMS)
        self.config = DetectorNodeConfig(**values)
        cfg = self.config
        from fiducial_detector.detect import detect  # the core (imports OpenCV and friends)

        self._detect = detect
        if not cfg.image_topic or not cfg.detections_topic:
            raise GraphError("fiducial_detector: image_topic and detections_topic must be set")
        qos = stream_qos(cfg.qos, cfg.queue_depth)
        # The transport's topic follows the base topic as remapped (``-r /camera/image_raw:=
        # /cam2/image_raw`` moves ``.../compressed`` too), as image_transport does.
        topic = self.resolve_topic_name(cfg.image_topic)
        if cfg.transport == "compressed":
            topic = topic.rstrip("/") + "/compressed"
        self.input_topic = topic
        self._pub = self.create_publisher(
            PointCloud2, cfg.detections_topic, record_qos(cfg.qos, cfg.queue_depth)
        )
        self._diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        msg_type: Any = CompressedImage if cfg.transport == "compressed" else Image
        self._sub = self.create_subscription(msg_type, topic, self._on_image, qos)
        self.create_timer(cfg.diagnostics_period_s, self._publish_diagnostics)
        self.received = self.published = self.dropped = self.too_small = 0
        self.problems = RecentProblems()
        self.frame_times = FrameTimes()
        self.input_age = InputAge("image", cfg.stale_after_s)
        self.get_logger().info(
            f"detecting on {self._sub.topic_name} ({msg_type.__name__}, {cfg.qos}) -> "
            f"{self._pub.topic_name}"
        )

    def _on_image(self, msg: Any) -> None:
        self.received += 1
        self.input_age.received()  # even an undecodable frame: the camera is alive
        t0 = time.perf_counter()
        try:
            image = image_codec.decode(msg)
            if min(image.shape[:2]) < MIN_OUTER_DIAMETER_PX:
                # A valid frame too small for the smallest fiducial looked for holds none: its
                # answer is an empty cloud (downstream stays in step frame by frame), not a drop.
                dets = []
                self._too_small(image.shape[1], image.shape[0])
            else:
                dets = self._detect(
                    image,
                    design=cast(DesignChoice, self.config.design),
                    subpixel=cast(SubpixelMethod, self.config.subpixel),
                    decimate=self.config.decimate,
                )
        except Exception as err:
            # image_codec's and the detector's input errors are ValueErrors; anything else is a
            # bug worth its type name in the log, but still not worth the rig's monitoring.
            self.dropped += 1
            kind = "" if isinstance(err, ValueError) else f"{type(err).__name__}: "
            text = f"frame {self.received} dropped: {kind}{err}"
            self.problems.report("warn", text)
            self.get_logger().error(text)
            return
        cloud = records.to_pointcloud2(
            PointCloud2,
            PointField,
            msg.header,
            records.DETECTION,
            records.detections_to_records(dets),
        )
        self._pub.publish(cloud)
        self.published += 1
        self.frame_times.add(1e3 * (time.perf_counter() - t0))

    def _too_small(self, width: int, height: int) -> None:
        self.too_small += 1
        self.get_logger().warning(
            f"image {width}x{height} is smaller than the smallest fiducial looked for "
            f"({MIN_OUTER_DIAMETER_PX:g} px): empty detections published",
            throttle_duration_sec=10.0,
        )

    def _publish_diagnostics(self) -> None:
        # A stalled camera is a state (WARN while it lasts); drops are events, shown while recent.
        level, message = merge_status(
            self.input_age.status(), (self.problems.level(), self.problems.message())
        )
        publish_diagnostics(
            self,
            self._diag,
            level=level,
            message=message or "ok",
            hardware_id=self.input_topic,
            values={
                "frames_received": str(self.received),
                "frames_published": str(self.published),
                "frames_dropped": str(self.dropped),
                "frames_too_small": str(self.too_small),
                **self.input_age.values(),
                **self.problems.values(),
                **self.frame_times.values(),
            },
        )


NODE_CLASS = FiducialDetectorNode


def main(args: list[str] | None = None) -> int:
    """Console script ``fiducial_detector``."""
    return run_node(FiducialDetectorNode, args)


if __name__ == "__main__":
    sys.exit(main())
