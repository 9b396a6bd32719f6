"""Tests of bag I/O (armourcam.bagio): round trips, truncated bags, the real ROS 1 fixture."""

from __future__ import annotations

import dataclasses
import enum
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from armourcam import bagio, image_codec, records
from armourcam.bagio import BagError, BagTruncatedError
from pose_estimator.camera import CameraModel
from pose_estimator.types import FiducialPose

FIXTURES = Path(__file__).resolve().parents[2].parent / "shared" / "fixtures"
ROS1_BAG = FIXTURES / "real_camera_aruco_ros1.bag"
SEC = 1_000_000_000


def _camera() -> CameraModel:
    K = np.array([[812.5, 0.0, 321.25], [0.0, 811.0, 239.5], [0.0, 0.0, 1.0]])
    return CameraModel(640, 480, K, "plumb_bob", np.array([0.11, -0.23, 1e-3, -2e-3, 0.05]))


def _poses(rng: np.random.Generator, n: int) -> list[FiducialPose]:
    out = []
    for k in range(n):
        a = rng.normal(size=(3, 3))
        out.append(
            FiducialPose(
                code=k,
                position_mm=rng.uniform(-100, 800, 3),
                normal=np.array([0.0, 0.0, -1.0]),
                covariance_mm2=a @ a.T,
                n_frames=k + 1,
            )
        )
    return out


def _write_session(path: Path, rng: np.random.Generator, storage: str = "mcap") -> dict:
    """A small monitoring session of every kind of message armourcam puts in bags."""
    cam = _camera()
    mono = [rng.integers(0, 256, (480, 640), dtype=np.uint8) for _ in range(4)]
    colour = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    poses = records.poses_to_records(_poses(rng, 7))
    with bagio.BagWriter(path, storage=storage) as w:  # type: ignore[arg-type]
        w.write_camera_info("/camera/camera_info", cam, 1 * SEC, frame_id="cam")
        w.write_bool("/hall/run_active", False, 1 * SEC + 1)
        for k, img in enumerate(mono):
            w.write_image("/camera/image_raw", img, (2 + k) * SEC, frame_id="cam")
        w.write_image("/colour/image_raw", colour, 7 * SEC, encoding="rgb8")
        w.write_compressed_image("/camera/image_raw/compressed", colour, 8 * SEC, codec="png")
        w.write_string("/hall/run_id", "run-07", 9 * SEC)
        w.write_empty("/armourcam/capture_baseline", 9 * SEC + 5)
        w.write_records("/armourcam/poses", "FiducialPoseRecord", poses, 10 * SEC)
        w.write_record_array(
            "/armourcam/pose_array", "FiducialPoseArray", 10 * SEC + 1, frame_id="cam", poses=poses
        )
        w.write_record_array(
            "/armourcam/report",
            "RunReport",
            11 * SEC,
            latched=True,
            run_id="run-07",
            report_json='{"summary": {"displaced_units": 2}}',
        )
        counts = dict(w.counts)
    return {"cam": cam, "mono": mono, "colour": colour, "poses": poses, "counts": counts}


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_write_read_round_trip(tmp_path: Path, storage: str) -> None:
    rng = np.random.default_rng(1234)
    truth = _write_session(tmp_path / "bag", rng, storage)
    with bagio.open_bag(tmp_path / "bag") as bag:
        assert bag.kind == "rosbag2" and bag.truncation is None
        assert {t: i.count for t, i in bag.topics.items()} == truth["counts"]
        assert bag.message_count == 13
        assert bag.topics["/armourcam/pose_array"].msgtype == "armourcam_msgs/msg/FiducialPoseArray"
        assert (bag.start_ns, bag.end_ns) == (1 * SEC, 11 * SEC + 1)
        # Camera info -> CameraModel.
        assert bag.camera_info_topic() == "/camera/camera_info"
        cam = bag.camera_model()
        np.testing.assert_array_equal(cam.K, truth["cam"].K)
        np.testing.assert_array_equal(cam.D, truth["cam"].D)
        assert (cam.width, cam.height, cam.distortion_model) == (640, 480, "plumb_bob")
        # Several image topics: the choice must be explicit.
        with pytest.raises(BagError, match="several image topics"):
            bag.image_topic()
        frames = list(bag.frames("/camera/image_raw"))
        assert [f.index for f in frames] == [0, 1, 2, 3]
        assert [f.stamp_ns for f in frames] == [(2 + k) * SEC for k in range(4)]
        assert all(f.frame_id == "cam" and f.error is None for f in frames)
        for f, img in zip(frames, truth["mono"], strict=True):
            assert f.image is not None
            np.testing.assert_array_equal(f.image, img)
        (rgb,) = bag.frames("/colour/image_raw", colour=True)
        assert rgb.image is not None
        np.testing.assert_array_equal(rgb.image, truth["colour"][..., ::-1])
        (png,) = bag.frames("/camera/image_raw/compressed", colour=True)
        assert png.image is not None
        np.testing.assert_array_equal(png.image, truth["colour"])
        # Records: PointCloud2 rows and the array message carry the same poses.
        (cloud,) = bag.messages(["/armourcam/poses"])
        got = records.from_pointcloud2(cloud.message)
        assert got.tobytes() == truth["poses"].tobytes()
        (arr,) = bag.messages(msgtypes=["armourcam_msgs/msg/FiducialPoseArray"])
        assert arr.message.header.frame_id == "cam"
        assert [p.z for p in arr.message.poses] == truth["poses"]["z"].tolist()
        np.testing.assert_array_equal(
            arr.message.poses[3].covariance, truth["poses"]["covariance"][3]
        )
        (report,) = bag.messages(["/armourcam/report"])
        assert report.message.run_id == "run-07" and "displaced_units" in report.message.report_json
        # Hall topics, time window and ordering.
        window = list(bag.messages(start_ns=9 * SEC, stop_ns=10 * SEC))
        assert [m.topic for m in window] == ["/hall/run_id", "/armourcam/capture_baseline"]
        times = [m.timestamp_ns for m in bag.messages(deserialize=False)]
        assert times == sorted(times) and len(times) == 13
        with pytest.raises(BagError, match=r"topics \['/nope'\] are not in the bag"):
            list(bag.messages(["/nope"]))


def test_latched_qos_is_recorded(tmp_path: Path) -> None:
    _write_session(tmp_path / "bag", np.random.default_rng(0))
    meta = (tmp_path / "bag" / "metadata.yaml").read_text()
    assert meta.count("durability: transient_local") == 1
    with bagio.open_bag(tmp_path / "bag") as bag:
        assert [t for t, i in bag.topics.items() if i.latched] == ["/armourcam/report"]


# Stand-ins for rclpy's policy enums and Duration (rmw's member names; core tests run without
# rclpy): qos_from_profile reads profiles by duck typing.
_History = enum.IntEnum("_History", {"KEEP_LAST": 1, "UNKNOWN": 3})
_Reliability = enum.IntEnum("_Reliability", {"RELIABLE": 1, "BEST_EFFORT": 2})
_Durability = enum.IntEnum("_Durability", {"TRANSIENT_LOCAL": 1, "VOLATILE": 2})
_Liveliness = enum.IntEnum("_Liveliness", {"AUTOMATIC": 1, "MANUAL_BY_TOPIC": 3})


@dataclasses.dataclass
class _Duration:
    nanoseconds: int


def _profile(reliability: str, durability: str) -> SimpleNamespace:
    """A publisher's QoS as discovery reports it (history unknown, depth 0, infinite deadline
    and lease), shaped like an rclpy ``QoSProfile``."""
    inf = _Duration(2**63 - 1)
    return SimpleNamespace(
        history=_History.UNKNOWN,
        depth=0,
        reliability=_Reliability[reliability],
        durability=_Durability[durability],
        deadline=inf,
        lifespan=_Duration(1_500_000_000),
        liveliness=_Liveliness.AUTOMATIC,
        liveliness_lease_duration=inf,
        avoid_ros_namespace_conventions=False,
    )


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_offered_qos_profiles_are_recorded(tmp_path: Path, storage: str) -> None:
    """Publishers' QoS as discovered (rclpy profiles) is stored as rosbags ``Qos``, one profile
    per publisher, and read back: a topic is latched only with a TRANSIENT_LOCAL offer."""
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    camera = [_profile("BEST_EFFORT", "VOLATILE"), _profile("RELIABLE", "VOLATILE")]
    with bagio.BagWriter(tmp_path / "bag", storage=storage) as w:  # type: ignore[arg-type]
        w.add_topic("/camera/image_raw", bagio.IMAGE, offered_qos=camera)
        w.add_topic("/armourcam/markers", "visualization_msgs/msg/MarkerArray", latched=True)
        w.add_topic("/hall/run_id", "std_msgs/msg/String", offered_qos=[bagio._latched_qos()])
        w.write_string("/hall/run_id", "run-01", 1)
        w.write_image("/camera/image_raw", np.zeros((4, 6), np.uint8), 2)
        with pytest.raises(BagError, match="latched or offered_qos, not both"):
            w.add_topic("/x", "std_msgs/msg/String", latched=True, offered_qos=camera)
        with pytest.raises(BagError, match="not a QoS profile"):
            w.add_topic("/y", "std_msgs/msg/String", offered_qos=["reliable"])
    inf = QosTime(9_223_372_036, 854_775_807)
    with AnyReader([tmp_path / "bag"]) as reader:
        offered = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
    assert offered["/camera/image_raw"] == [
        Qos(
            QosHistory.UNKNOWN,
            0,
            reliability,
            QosDurability.VOLATILE,
            inf,
            QosTime(1, 500_000_000),
            QosLiveliness.AUTOMATIC,
            inf,
            False,
        )
        for reliability in (QosReliability.BEST_EFFORT, QosReliability.RELIABLE)
    ]
    assert [q.durability for q in offered["/armourcam/markers"]] == [QosDurability.TRANSIENT_LOCAL]
    with bagio.open_bag(tmp_path / "bag") as bag:
        assert {t: i.latched for t, i in bag.topics.items()} == {
            "/armourcam/markers": True,
            "/camera/image_raw": False,
            "/hall/run_id": True,
        }


def test_mcap_bag_opens_in_foxglove_style_readers(tmp_path: Path) -> None:
    """The bag's embedded schemas suffice for another reader (mcap-ros2-support, as Foxglove)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    rng = np.random.default_rng(5)
    truth = _write_session(tmp_path / "bag", rng)
    (mcap_file,) = (tmp_path / "bag").glob("*.mcap")
    seen = {}
    with mcap_file.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, ros_msg in reader.iter_decoded_messages():
            seen[channel.topic] = ros_msg
    assert len(seen) == len(truth["counts"])
    poses = seen["/armourcam/pose_array"].poses
    assert [p.code for p in poses] == truth["poses"]["code"].tolist()
    # And the single .mcap file opens on its own.
    with bagio.open_bag(mcap_file) as bag:
        assert bag.message_count == 13


def _image_bag(path: Path, n: int, rng: np.random.Generator) -> list[bytes]:
    raws = []
    with bagio.BagWriter(path) as w:
        w.write_camera_info("/camera/camera_info", _camera(), 0)
        for k in range(n):
            img = rng.integers(0, 256, (240, 320), dtype=np.uint8)
            w.write_image("/camera/image_raw", img, (k + 1) * SEC // 10)
            raws.append(img.tobytes())
    return raws


@pytest.mark.parametrize("fraction", [0.05, 0.31, 0.5, 0.77, 0.999])
def test_truncated_mcap_yields_its_readable_prefix(tmp_path: Path, fraction: float) -> None:
    rng = np.random.default_rng(42)
    images = _image_bag(tmp_path / "full", 30, rng)
    (src,) = (tmp_path / "full").glob("*.mcap")
    data = src.read_bytes()
    cut = int(len(data) * fraction)
    damaged = tmp_path / "cut.mcap"
    damaged.write_bytes(data[:cut])
    # Independent expectation: an image is readable when its whole payload lies before the cut.
    readable = 0
    for raw in images:
        at = data.find(raw)
        assert at > 0
        if at + len(raw) > cut:
            break
        readable += 1
    with bagio.open_bag(damaged) as bag:
        assert bag.kind == "mcap-recovered"
        t = bag.truncation
        assert t is not None and t.size == cut and 0 < t.offset < cut
        assert bag.topics["/camera/image_raw"].count == readable
        got = []
        with pytest.raises(BagTruncatedError, match=rf"truncated or damaged at byte {t.offset} "):
            for m in bag.messages(["/camera/image_raw"]):
                got.append(image_codec.decode(m.message))
        assert len(got) == readable
        for img, raw in zip(got, images, strict=False):
            assert img.tobytes() == raw
        assert t.messages_read == readable + 1  # the camera info came first
        # "report" mode stops quietly with the same messages.
        assert len(list(bag.messages(on_truncation="report"))) == readable + 1


def test_damaged_summary_loses_nothing(tmp_path: Path) -> None:
    """A cut inside the summary/footer (after the data section) leaves every message readable."""
    images = _image_bag(tmp_path / "full", 5, np.random.default_rng(8))
    (src,) = (tmp_path / "full").glob("*.mcap")
    damaged = tmp_path / "cut.mcap"
    damaged.write_bytes(src.read_bytes()[:-20])
    with bagio.open_bag(damaged) as bag:
        assert bag.kind == "mcap-recovered" and bag.truncation is None
        assert [f.image.tobytes() for f in bag.frames() if f.image is not None] == images


def test_truncated_bag_directory(tmp_path: Path) -> None:
    """A rosbag2 directory whose .mcap was cut (recorder killed) still reads up to the cut."""
    rng = np.random.default_rng(3)
    images = _image_bag(tmp_path / "bag", 20, rng)
    (src,) = (tmp_path / "bag").glob("*.mcap")
    data = src.read_bytes()
    src.write_bytes(data[: len(data) // 2])
    with bagio.open_bag(tmp_path / "bag") as bag:
        assert bag.truncation is not None
        frames = list(bag.frames(on_truncation="report"))
        assert 0 < len(frames) < 20
        for f, raw in zip(frames, images, strict=False):
            assert f.image is not None and f.image.tobytes() == raw
        assert str(src) in bag.truncation.describe()


def test_bad_frame_is_reported_and_iteration_goes_on(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    good = rng.integers(0, 256, (20, 30), dtype=np.uint8)
    with bagio.BagWriter(tmp_path / "bag") as w:
        w.write_image("/cam", good, 1)
        fields = image_codec.image_to_msg_fields(good, data_as="numpy")
        fields["step"] = 29  # wrong step
        w.write("/cam", bagio.IMAGE, w.new(bagio.IMAGE, header=w.header(2), **fields), 2)
        fields["step"], fields["encoding"] = 30, "mono12"  # unknown encoding
        w.write("/cam", bagio.IMAGE, w.new(bagio.IMAGE, header=w.header(3), **fields), 3)
        w.write_image("/cam", good, 4)
    with bagio.open_bag(tmp_path / "bag") as bag:
        frames = list(bag.frames())
    assert [f.error is None for f in frames] == [True, False, False, True]
    assert frames[1].error is not None and "step 29 is smaller" in frames[1].error
    assert frames[2].error is not None and "unknown image encoding 'mono12'" in frames[2].error
    assert frames[3].image is not None and np.array_equal(frames[3].image, good)


def test_ros1_fixture_reads() -> None:
    with bagio.open_bag(ROS1_BAG) as bag:
        assert bag.kind == "rosbag1"
        assert bag.topics["/raspicam_node/camera_info"].count == 15
        assert bag.topics["/raspicam_node/image/compressed"].count == 1
        assert bag.image_topic() == "/raspicam_node/image/compressed"
        assert bag.camera_info_topic() == "/raspicam_node/camera_info"
        (frame,) = bag.frames()
        assert frame.error is None and frame.image is not None
        assert frame.image.shape == (960, 1280) and frame.image.dtype == np.uint8
        assert frame.frame_id == "raspicam" and frame.stamp_ns > 1_400_000_000 * SEC
        cam = bag.camera_model()
        assert (cam.width, cam.height, cam.distortion_model) == (1280, 960, "plumb_bob")
        assert cam.K[0, 0] == pytest.approx(1014.3431, abs=1e-3)
        infos = list(bag.messages(msgtypes=["sensor_msgs/CameraInfo"]))
        assert len(infos) == 15 and all(m.serialization == "ros1" for m in infos)
        # The decoded JPEG is OpenCV's own decode of the same bytes.
        (jpeg,) = bag.messages(["/raspicam_node/image/compressed"])
        ref = cv2.imdecode(np.asarray(jpeg.message.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        np.testing.assert_array_equal(frame.image, ref)


@pytest.mark.parametrize("fraction", [0.004, 0.2, 0.5, 0.99, 0.999])
def test_truncated_ros1_bag_yields_its_readable_prefix(tmp_path: Path, fraction: float) -> None:
    """A ROS 1 bag cut short (no index) is scanned: every whole message is read, in file order."""
    data = ROS1_BAG.read_bytes()
    with bagio.open_bag(ROS1_BAG) as bag:
        raws = sorted((data.find(m.rawdata), m.rawdata) for m in bag.messages(deserialize=False))
    assert all(at > 0 for at, _ in raws)
    cut = int(len(data) * fraction)
    expected = [raw for at, raw in raws if at + len(raw) <= cut]
    damaged = tmp_path / "cut.bag"
    damaged.write_bytes(data[:cut])
    with bagio.open_bag(damaged) as bag:
        assert bag.kind == "rosbag1-recovered"
        assert bag.truncation is not None and bag.truncation.messages_read == len(expected)
        assert bag.message_count == len(expected)
        got = list(bag.messages(on_truncation="report"))
        assert [m.rawdata for m in got] == expected
        assert all(m.serialization == "ros1" and m.message is not None for m in got)
        if any(m.msgtype == bagio.CAMERA_INFO for m in got):
            assert bag.camera_model().K[0, 0] == pytest.approx(1014.3431, abs=1e-3)
        if any(m.msgtype == bagio.COMPRESSED_IMAGE for m in got):
            (frame,) = bag.frames(on_truncation="report")
            assert frame.image is not None and frame.image.shape == (960, 1280)
        with pytest.raises(BagTruncatedError, match="truncated or damaged at byte"):
            list(bag.messages())


@pytest.mark.filterwarnings("ignore::DeprecationWarning:lark")
def test_copy_ros1_messages_into_rclpy_classes() -> None:
    """Replay of a ROS 1 bag: its messages become rclpy messages with the same content."""
    sensor_msgs = pytest.importorskip("sensor_msgs.msg")
    serialization = pytest.importorskip("rclpy.serialization")
    with bagio.open_bag(ROS1_BAG) as bag:
        info = next(iter(bag.messages(msgtypes=[bagio.CAMERA_INFO])))
        jpeg = next(iter(bag.messages(msgtypes=[bagio.COMPRESSED_IMAGE])))
    ci = bagio.copy_message(info.message, sensor_msgs.CameraInfo)
    np.testing.assert_array_equal(ci.k, info.message.K)
    assert ci.header.frame_id == "raspicam" and ci.distortion_model == "plumb_bob"
    assert bagio.stamp_to_ns(ci.header.stamp) == bagio.stamp_to_ns(info.message.header.stamp)
    back = serialization.deserialize_message(
        serialization.serialize_message(ci), sensor_msgs.CameraInfo
    )
    assert (
        bagio.camera_model_from_info(back).K.tolist()
        == bagio.camera_model_from_info(info.message).K.tolist()
    )
    img = bagio.copy_message(jpeg.message, sensor_msgs.CompressedImage)
    assert image_codec.decode(img).shape == (960, 1280)
    # And a CameraInfo built for rclpy from a CameraModel converts back to the same model.
    cam = _camera()
    rebuilt = bagio.camera_model_from_info(
        sensor_msgs.CameraInfo(**bagio.camera_info_fields(cam, style="rclpy"))
    )
    np.testing.assert_array_equal(rebuilt.K, cam.K)
    np.testing.assert_array_equal(rebuilt.D, cam.D)


def test_errors(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="no such bag"):
        bagio.open_bag(tmp_path / "missing.mcap")
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(BagError, match="bag file is empty"):
        bagio.open_bag(tmp_path / "empty.mcap")
    (tmp_path / "text.mcap").write_text("this is not a bag at all\n")
    with pytest.raises(BagError, match="not an MCAP file"):
        bagio.open_bag(tmp_path / "text.mcap")
    (tmp_path / "text.bag").write_text("this is not a bag at all\n")
    with pytest.raises(BagError, match="cannot open bag"):
        bagio.open_bag(tmp_path / "text.bag")
    _image_bag(tmp_path / "bag", 1, np.random.default_rng(0))
    # An MCAP file copied out of its bag directory under a ROS 1 name.
    (mcap,) = (tmp_path / "bag").glob("*.mcap")
    (tmp_path / "copied.bag").write_bytes(mcap.read_bytes())
    with pytest.raises(BagError, match=r"copied\.bag: an MCAP file named \.bag; rename it"):
        bagio.open_bag(tmp_path / "copied.bag")
    with pytest.raises(BagError, match=r"cannot create bag .* exists"):
        bagio.BagWriter(tmp_path / "bag")
    with bagio.BagWriter(tmp_path / "other") as w:
        w.write_string("/t", "x", 1)
        with pytest.raises(BagError, match="already has type std_msgs/msg/String"):
            w.write_bool("/t", True, 2)
        with pytest.raises(BagError, match="unknown message type"):
            w.new("nope_msgs/msg/Nothing")
    with bagio.open_bag(tmp_path / "other") as bag:
        with pytest.raises(BagError, match="no image topic"):
            bag.image_topic()
        assert bag.camera_info_topic() is None
        with pytest.raises(BagError, match="no sensor_msgs/CameraInfo topic"):
            bag.camera_model()
        with pytest.raises(BagError, match="topic '/t' has type std_msgs/msg/String"):
            bag.image_topic("/t")


@pytest.mark.filterwarnings("ignore::DeprecationWarning:lark")
def test_copy_nested_ros2_messages_into_rclpy_classes() -> None:
    """Bag messages with nested message sequences (markers, clouds) copy into rclpy classes."""
    visualization_msgs = pytest.importorskip("visualization_msgs.msg")
    geometry_msgs = pytest.importorskip("geometry_msgs.msg")
    sensor_msgs = pytest.importorskip("sensor_msgs.msg")
    serialization = pytest.importorskip("rclpy.serialization")
    store = bagio.armourcam_typestore()
    marker = visualization_msgs.Marker(ns="disp", id=4, text="unit 4", type=0)
    marker.points = [geometry_msgs.Point(x=1.0), geometry_msgs.Point(y=2.5, z=-1.0)]
    original = visualization_msgs.MarkerArray(markers=[marker, visualization_msgs.Marker(id=5)])
    bagged = store.deserialize_cdr(
        serialization.serialize_message(original), "visualization_msgs/msg/MarkerArray"
    )
    # Marker's constant POINTS must not be mistaken for its field points.
    assert bagio.copy_message(bagged, visualization_msgs.MarkerArray) == original

    recs = records.layout("UnitMotionRecord").empty(3)
    recs["unit"] = [7, 8, 9]
    cloud = records.to_pointcloud2(
        store.types[bagio.POINT_CLOUD2],
        store.types["sensor_msgs/msg/PointField"],
        bagged.markers[0].header,
        "UnitMotionRecord",
        recs,
    )
    copied = bagio.copy_message(cloud, sensor_msgs.PointCloud2)
    assert records.from_pointcloud2(copied).tobytes() == recs.tobytes()
