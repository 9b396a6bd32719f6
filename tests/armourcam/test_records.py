"""Tests of the PointCloud2 record codec driven by ``msg/`` (armourcam.records)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from armourcam import records
from armourcam.records import RecordError
from fiducial_detector.types import Ellipse, FiducialDetection
from pose_estimator.types import FiducialPose

REPO = Path(__file__).resolve().parents[2]
RECORDS = [
    "DisplacementRecord",
    "FiducialDetectionRecord",
    "FiducialPoseRecord",
    "UnitMotionRecord",
]


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def _detection(rng: np.random.Generator, design: str, n_ellipses: int) -> FiducialDetection:
    ellipses = tuple(
        Ellipse(
            center_px=(float(rng.uniform(0, 3000)), float(rng.uniform(0, 2000))),
            semi_major=float(rng.uniform(20, 60)),
            semi_minor=float(rng.uniform(5, 20)),
            angle=float(rng.uniform(0, np.pi)),
            covariance=_spd(rng, 5) * 1e-4,
            radius=float(rng.uniform(0.2, 1.0)),
            rms_residual=float(rng.uniform(0, 0.1)),
            systematic_px=float(rng.choice([0.0, 0.05])),
        )
        for _ in range(n_ellipses)
    )
    return FiducialDetection(
        code=int(rng.integers(0, 66)),
        hamming=int(rng.integers(0, 2)),
        center_px=ellipses[0].center_px,
        ellipses=ellipses,
        contrast=float(rng.uniform(0.1, 0.9)),
        design=design,
        rotation=float(rng.uniform(-np.pi, np.pi)),
    )


def _pose(rng: np.random.Generator, detection: FiducialDetection | None) -> FiducialPose:
    normal = rng.normal(size=3)
    return FiducialPose(
        code=int(rng.integers(0, 66)),
        position_mm=rng.uniform(-300, 900, size=3),
        normal=normal / np.linalg.norm(normal),
        covariance_mm2=_spd(rng, 3) * 1e-3,
        detection=detection,
        n_frames=int(rng.integers(1, 30)),
    )


def _assert_detections_equal(a: FiducialDetection, b: FiducialDetection) -> None:
    assert (a.code, a.hamming, a.design, a.center_px) == (b.code, b.hamming, b.design, b.center_px)
    assert (a.contrast, a.rotation) == (b.contrast, b.rotation)
    assert len(a.ellipses) == len(b.ellipses)
    for ea, eb in zip(a.ellipses, b.ellipses, strict=True):
        assert ea.center_px == eb.center_px
        assert (ea.semi_major, ea.semi_minor, ea.angle) == (eb.semi_major, eb.semi_minor, eb.angle)
        assert (ea.radius, ea.rms_residual, ea.systematic_px) == (
            eb.radius,
            eb.rms_residual,
            eb.systematic_px,
        )
        np.testing.assert_array_equal(ea.covariance, eb.covariance)


def _through_cloud(name: str, recs: np.ndarray) -> np.ndarray:
    enc = records.encode(name, recs)
    assert len(enc.data) == enc.width * enc.point_step
    return records.decode(name, enc.fields, enc.point_step, enc.data, enc.width)


def test_msg_dir_is_package_data_and_repo_msg_links_to_it() -> None:
    """The definitions live in the package; the repository's ``msg/`` shows the same files."""
    assert records.MSG_DIR.parent == Path(records.__file__).resolve().parent
    names = records.definition_names()
    assert set(RECORDS) <= set(names)
    assert {"FiducialPoseArray", "FiducialDetectionArray", "DisplacementArray"} <= set(names)
    top = REPO / "msg"
    assert top.resolve() == records.MSG_DIR
    assert sorted(p.name for p in top.glob("*.msg")) == [f"{n}.msg" for n in names]


@pytest.mark.parametrize("name", RECORDS)
def test_layout_is_generated_from_the_definition(name: str) -> None:
    """PointFields follow the .msg fields in order, naturally aligned, each documented."""
    lay = records.layout(name)
    text = records.definition_text(name)
    declared = [
        line.split("#")[0].split()[1]
        for line in text.splitlines()
        if line.split("#")[0].strip() and "=" not in line.split("#")[0]
    ]
    assert [p.name for p in lay.point_fields] == declared == list(lay.field_names)
    for f, p in zip(lay.fields, lay.point_fields, strict=True):
        size = np.dtype(lay.dtype[f.name].base).itemsize
        assert p.offset % size == 0
        assert p.count == f.count
        assert f.comment, f"{name}.{f.name} has no comment giving its unit/frame"
    assert lay.point_step == lay.dtype.itemsize
    assert lay.point_step % 8 == 0
    ends = [
        p.offset + np.dtype(lay.dtype[p.name].base).itemsize * p.count for p in lay.point_fields
    ]
    assert max(ends) <= lay.point_step


@pytest.mark.parametrize("name", ["FiducialPoseArray", "RunReport", "DisplacementArray"])
def test_wrapper_messages_cannot_be_rows(name: str) -> None:
    """Strings, headers and sequences cannot travel as PointFields."""
    with pytest.raises(RecordError, match="only numeric primitives"):
        records.layout(name)


def test_unknown_definition() -> None:
    with pytest.raises(RecordError, match="no record definition 'Nope'"):
        records.layout("Nope")


def test_definitions_register_with_rosbags_and_serialize() -> None:
    """Bags: the same definitions register in a Kilted typestore and round-trip through CDR."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    store.register(records.typesdict())
    rng = np.random.default_rng(3)
    recs = records.poses_to_records([_pose(rng, None) for _ in range(4)])
    rec_cls = store.types["armourcam_msgs/msg/FiducialPoseRecord"]
    objs = [
        rec_cls(
            **{
                n: (
                    np.array(r[n])
                    if records.layout("FiducialPoseRecord").dtype[n].shape
                    else r[n].item()
                )
                for n in recs.dtype.names or ()
            }
        )
        for r in recs
    ]
    hdr = store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=5, nanosec=7), frame_id="cam"
    )
    msg = store.types["armourcam_msgs/msg/FiducialPoseArray"](header=hdr, poses=objs)
    back = store.deserialize_cdr(
        store.serialize_cdr(msg, "armourcam_msgs/msg/FiducialPoseArray"),
        "armourcam_msgs/msg/FiducialPoseArray",
    )
    assert back.header.frame_id == "cam"
    assert [p.z for p in back.poses] == recs["z"].tolist()
    np.testing.assert_array_equal(back.poses[2].covariance, recs["covariance"][2])


@pytest.mark.parametrize(("design", "n_ellipses"), [("dot", 1), ("ring", 3), ("ring", 2)])
def test_detections_round_trip_exactly(design: str, n_ellipses: int) -> None:
    rng = np.random.default_rng(1234)
    dets = [_detection(rng, design, n_ellipses) for _ in range(25)]
    recs = records.detections_to_records(dets)
    back = records.records_to_detections(_through_cloud("FiducialDetectionRecord", recs))
    assert len(back) == len(dets)
    for a, b in zip(dets, back, strict=True):
        _assert_detections_equal(a, b)


def test_detection_errors() -> None:
    rng = np.random.default_rng(5)
    det = _detection(rng, "dot", 1)
    bad_design = FiducialDetection(det.code, 0, det.center_px, det.ellipses, 0.5, "square")
    with pytest.raises(RecordError, match="unknown design 'square'"):
        records.detections_to_records([bad_design])
    four = FiducialDetection(det.code, 0, det.center_px, det.ellipses * 4, 0.5, "ring")
    with pytest.raises(RecordError, match="4 ellipses"):
        records.detections_to_records([four])
    recs = records.detections_to_records([det])
    recs["n_ellipses"] = 0
    with pytest.raises(RecordError, match="n_ellipses 0"):
        records.records_to_detections(recs)


def test_poses_round_trip_exactly_with_detection_links() -> None:
    rng = np.random.default_rng(99)
    dets = [_detection(rng, "ring", 3) for _ in range(6)]
    poses = [_pose(rng, dets[k]) for k in (4, 0, 2)] + [_pose(rng, None)]
    # One pose with a known fit bias (its systematic covariance), the others without.
    poses[1] = replace(poses[1], systematic_mm2=_spd(rng, 3) * 1e-2)
    # Two with a printed axis (in the plane of their normals), the others without.
    for k in (0, 1):
        a = np.cross(poses[k].normal, rng.normal(size=3))
        poses[k] = replace(poses[k], axis=a / np.linalg.norm(a))
    recs = _through_cloud("FiducialPoseRecord", records.poses_to_records(poses, dets))
    assert recs["detection_index"].tolist() == [4, 0, 2, -1]
    assert recs["u"][0] == dets[4].center_px[0] and np.isnan(recs["u"][3])
    back = records.records_to_poses(recs, dets)
    for a, b in zip(poses, back, strict=True):
        assert (a.code, a.n_frames) == (b.code, b.n_frames)
        np.testing.assert_array_equal(a.position_mm, b.position_mm)
        np.testing.assert_array_equal(a.normal, b.normal)
        np.testing.assert_array_equal(a.covariance_mm2, b.covariance_mm2)
        if a.systematic_mm2 is None:
            assert b.systematic_mm2 is None
        else:
            np.testing.assert_array_equal(a.systematic_mm2, b.systematic_mm2)
        if a.axis is None:
            assert b.axis is None
        else:
            np.testing.assert_array_equal(a.axis, b.axis)
        assert a.detection is b.detection
    assert [p.systematic_mm2 is not None for p in back] == [False, True, False, False]
    assert [p.axis is not None for p in back] == [True, True, False, False]
    assert all(p.detection is None for p in records.records_to_poses(recs))
    bad = FiducialPose(-3, poses[0].position_mm, poses[0].normal, poses[0].covariance_mm2)
    with pytest.raises(RecordError, match=r"pose 1: code -3 outside 0\.\.4294967295"):
        records.poses_to_records([poses[0], bad])
    flat = FiducialPose(1, np.zeros(2), poses[0].normal, poses[0].covariance_mm2)
    with pytest.raises(RecordError, match="malformed position"):
        records.poses_to_records([flat])
    with pytest.raises(RecordError, match="detection_index 4 but only 2"):
        records.records_to_poses(recs, dets[:2])


def _displacement_rows(rng: np.random.Generator, n: int) -> list[dict[str, Any]]:
    labels = records.constants("DisplacementRecord")
    rows = []
    for k in range(n):
        before = rng.normal(size=3) * 100
        after = before + rng.normal(size=3)
        vanished = k % 4 == 3
        rows.append(
            {
                "before_mm": before.tolist(),
                "after_mm": [np.nan] * 3 if vanished else after.tolist(),
                "displacement_mm": [np.nan] * 3 if vanished else (after - before).tolist(),
                "displacement_covariance": records.covariance_to_upper(_spd(rng, 3)).tolist(),
                "distance_mm": np.nan if vanished else float(np.linalg.norm(after - before)),
                "cost": float(rng.uniform()),
                "code_before": int(rng.integers(0, 66)),
                "code_after": -1 if vanished else int(rng.integers(0, 66)),
                "index_before": k,
                "index_after": -1 if vanished else n - k,
                "unit": k // 4,
                "label": labels["LABEL_VANISHED"] if vanished else labels["LABEL_SAME_CODE"],
            }
        )
    return rows


def test_displacement_rows_round_trip_with_nan() -> None:
    rng = np.random.default_rng(7)
    rows = _displacement_rows(rng, 9)
    back = records.records_to_rows(
        _through_cloud("DisplacementRecord", records.rows_to_records("DisplacementRecord", rows))
    )
    for a, b in zip(rows, back, strict=True):
        assert a.keys() == b.keys()
        for key in a:
            np.testing.assert_array_equal(np.asarray(a[key], float), np.asarray(b[key], float))


def test_row_errors_name_the_problem() -> None:
    rng = np.random.default_rng(8)
    row = _displacement_rows(rng, 1)[0]
    with pytest.raises(RecordError, match=r"missing fields \['cost'\]"):
        records.rows_to_records(
            "DisplacementRecord", [{k: v for k, v in row.items() if k != "cost"}]
        )
    with pytest.raises(RecordError, match=r"unknown fields \['colour'\]"):
        records.rows_to_records("DisplacementRecord", [{**row, "colour": 1}])
    with pytest.raises(RecordError, match="before_mm: expected shape"):
        records.rows_to_records("DisplacementRecord", [{**row, "before_mm": [1.0, 2.0]}])
    with pytest.raises(RecordError, match="label: value 300 does not fit uint8"):
        records.rows_to_records("DisplacementRecord", [{**row, "label": 300}])
    with pytest.raises(RecordError, match=r"unit: value 1\.5 does not fit int32"):
        records.rows_to_records("DisplacementRecord", [{**row, "unit": 1.5}])


def test_decode_honours_foreign_offsets_padding_and_byte_order() -> None:
    """A cloud laid out by another producer (shuffled offsets, padding, big-endian) decodes."""
    rng = np.random.default_rng(11)
    recs = records.rows_to_records("DisplacementRecord", _displacement_rows(rng, 5))
    lay = records.layout("DisplacementRecord")
    rev = list(reversed(lay.field_names))
    formats = [(">" + lay.dtype[n].base.str[1:], lay.dtype[n].shape) for n in rev]
    offsets, pos = [], 4
    for n in rev:
        offsets.append(pos)
        pos += lay.dtype[n].itemsize + 3
    foreign = np.dtype({"names": rev, "formats": formats, "offsets": offsets, "itemsize": pos + 5})
    arr = np.zeros(len(recs), dtype=foreign)
    for n in rev:
        arr[n] = recs[n]
    fields = [
        records.PointFieldSpec(n, off, p.datatype, p.count)
        for n, off in zip(rev, offsets, strict=True)
        for p in lay.point_fields
        if p.name == n
    ]
    # Two rows of the cloud (height 2) with row padding of 16 bytes.
    row_step = 3 * foreign.itemsize + 16
    data = bytearray(2 * row_step)
    raw = arr[:3].tobytes(), arr[[3, 4, 0]].tobytes()
    data[: len(raw[0])] = raw[0]
    data[row_step : row_step + len(raw[1])] = raw[1]
    out = records.decode(
        "DisplacementRecord", fields, foreign.itemsize, bytes(data), 3, 2,
        is_bigendian=True, row_step=row_step,
    )  # fmt: skip
    want = np.concatenate([recs, recs[:1]])
    for n in lay.field_names:
        np.testing.assert_array_equal(out[n], want[n])


def test_mismatched_clouds_are_refused() -> None:
    rng = np.random.default_rng(12)
    enc = records.encode("FiducialPoseRecord", records.poses_to_records([_pose(rng, None)]))
    fields = list(enc.fields)

    def dec(fs: list[records.PointFieldSpec], data: bytes = enc.data, **kw: Any) -> np.ndarray:
        return records.decode("FiducialPoseRecord", fs, enc.point_step, data, 1, **kw)

    with pytest.raises(RecordError, match="missing field 'z'"):
        dec([f for f in fields if f.name != "z"])
    as_float = [
        records.PointFieldSpec(f.name, f.offset, records.FLOAT32, f.count) if f.name == "x" else f
        for f in fields
    ]
    with pytest.raises(RecordError, match="field 'x' is FLOAT32\\[1\\], expected FLOAT64\\[1\\]"):
        dec(as_float)
    short_cov = [
        records.PointFieldSpec(f.name, f.offset, f.datatype, 3) if f.name == "covariance" else f
        for f in fields
    ]
    with pytest.raises(RecordError, match="covariance"):
        dec(short_cov)
    with pytest.raises(RecordError, match="unknown fields \\['rgb'\\]"):
        dec([*fields, records.PointFieldSpec("rgb", 0, records.FLOAT32, 1)])
    # Non-strict decoding ignores extra fields.
    extra = dec([*fields, records.PointFieldSpec("rgb", 0, records.FLOAT32, 1)], strict=False)
    assert (
        extra["code"][0]
        == records.decode("FiducialPoseRecord", fields, enc.point_step, enc.data, 1)["code"][0]
    )
    with pytest.raises(RecordError, match=f"data has {enc.point_step - 1} bytes"):
        dec(fields, enc.data[:-1])
    outside = [
        records.PointFieldSpec(f.name, enc.point_step - 3, f.datatype, f.count)
        if f.name == "x"
        else f
        for f in fields
    ]
    with pytest.raises(RecordError, match="outside point_step"):
        dec(outside)
    assert records.identify(fields) == "FiducialPoseRecord"
    assert records.identify(fields[:-1]) is None


# rclpy's type support imports lark, which imports the deprecated sre_parse module.
@pytest.mark.filterwarnings("ignore::DeprecationWarning:lark")
def test_rclpy_pointcloud2_round_trip_and_bag_compatibility() -> None:
    """Nodes (rclpy classes, CDR on the wire) and bags (rosbags) read the same clouds."""
    pc2 = pytest.importorskip("sensor_msgs.msg")
    std = pytest.importorskip("std_msgs.msg")
    serialization = pytest.importorskip("rclpy.serialization")
    from rosbags.typesys import Stores, get_typestore

    rng = np.random.default_rng(21)
    dets = [_detection(rng, "ring", 3) for _ in range(40)]
    recs = records.detections_to_records(dets)
    header = std.Header(frame_id="camera_optical")
    msg = records.to_pointcloud2(
        pc2.PointCloud2, records.pointfield_class_for(pc2.PointCloud2), header,
        "FiducialDetectionRecord", recs,
    )  # fmt: skip
    assert (msg.width, msg.height, msg.point_step) == (
        40,
        1,
        records.layout("FiducialDetectionRecord").point_step,
    )
    assert [f.name for f in msg.fields][:2] == ["u", "v"]
    wire = serialization.serialize_message(msg)
    received = serialization.deserialize_message(wire, pc2.PointCloud2)
    for a, b in zip(
        dets, records.records_to_detections(records.from_pointcloud2(received)), strict=True
    ):
        _assert_detections_equal(a, b)
    # The same CDR bytes read by rosbags (as a bag would hold them).
    store = get_typestore(Stores.ROS2_KILTED)
    bagged = store.deserialize_cdr(wire, "sensor_msgs/msg/PointCloud2")
    np.testing.assert_array_equal(
        records.from_pointcloud2(bagged, "FiducialDetectionRecord")["ellipse_covariance"],
        recs["ellipse_covariance"],
    )
    # And a rosbags-built cloud is read back by rclpy.
    built = records.to_pointcloud2(
        store.types["sensor_msgs/msg/PointCloud2"], store.types["sensor_msgs/msg/PointField"],
        bagged.header, "FiducialDetectionRecord", recs,
    )  # fmt: skip
    again = serialization.deserialize_message(
        bytes(store.serialize_cdr(built, "sensor_msgs/msg/PointCloud2")), pc2.PointCloud2
    )
    assert records.from_pointcloud2(again).tobytes() == recs.tobytes()


def test_empty_cloud() -> None:
    enc = records.encode("UnitMotionRecord", records.layout("UnitMotionRecord").empty(0))
    assert (enc.width, enc.data) == (0, b"")
    out = records.decode("UnitMotionRecord", enc.fields, enc.point_step, enc.data, 0)
    assert out.shape == (0,)


def test_covariance_packing() -> None:
    rng = np.random.default_rng(2)
    c = _spd(rng, 5)
    up = records.covariance_to_upper(c)
    assert up.shape == (15,)
    np.testing.assert_array_equal(records.upper_to_covariance(up, 5), c)
    with pytest.raises(RecordError, match="do not make a 3x3"):
        records.upper_to_covariance(up, 3)


def test_rows_to_records_accepts_zero_rows() -> None:
    """A frame or run with nothing to report encodes as an empty, well-typed array."""
    from armourcam import records

    out = records.rows_to_records(records.DISPLACEMENT, [])
    assert out.shape == (0,)
    assert out.dtype == records.layout(records.DISPLACEMENT).dtype
