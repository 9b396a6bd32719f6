"""The one module for bag I/O: reading ROS 1 / ROS 2 bags and writing ROS 2 MCAP bags.

Built on rosbags (``AnyReader``, ``Writer``) with recovery scanners for truncated MCAP files and
unindexed ROS 1 bags (a recorder killed mid-run); no rclpy. Messages come back as rosbags message
objects, which :mod:`armourcam.image_codec` and :mod:`armourcam.records` read by duck typing like
rclpy's.

API summary
-----------
Reading:

- :func:`open_bag` ``(path) -> Bag``: a rosbag2 directory (MCAP or SQLite storage), a single
  ``.mcap`` file, or a ROS 1 ``.bag``. Use as a context manager.
- :class:`Bag`: ``topics`` (``{topic: TopicInfo(topic, msgtype, count, latched)}``),
  ``message_count``, ``start_ns``/``end_ns``, ``kind`` (``rosbag2``, ``rosbag1``,
  ``mcap-recovered``, ``rosbag1-recovered``), ``truncation`` (a :class:`Truncation` or None);
  ``messages(topics=None, msgtypes=None, *, start_ns=None, stop_ns=None, deserialize=True)``
  -> iterator of :class:`BagMessage` (``topic, msgtype, timestamp_ns, index, rawdata,
  serialization, message``); ``topics_of_type(*msgtypes)``; ``image_topic(topic=None)`` and
  ``camera_info_topic(topic=None)`` (found by type when not given); ``frames(...)`` -> iterator
  of decoded :class:`Frame` (a bad frame carries its error instead of stopping the iteration);
  ``camera_model(topic=None)`` (first CameraInfo as a ``CameraModel``).
- A truncated bag yields every message that is readable; then :class:`BagTruncatedError` (a
  :class:`BagError`) is raised naming the byte offset and message index where reading stopped
  (``on_truncation="report"`` stops quietly instead; ``bag.truncation`` holds the same report).

Writing:

- :class:`BagWriter` ``(path, *, storage="mcap")``: a ROS 2 bag (rosbags ``Writer`` version 9)
  whose typestore knows the ROS 2 Kilted standard types and armourcam's ``msg/`` definitions
  (``armourcam_msgs/msg/...``). ``write(topic, msgtype, message, timestamp_ns)``,
  ``write_image``, ``write_compressed_image``, ``write_camera_info``, ``write_records`` (PointCloud2
  rows), ``write_record_array`` (e.g. ``FiducialPoseArray``), ``write_string``, ``write_bool``,
  ``write_empty``, ``write_raw`` (CDR bytes as received); ``new(msgtype, **fields)``,
  ``header(stamp_ns, frame_id)``; ``add_topic(topic, msgtype, *, latched=False,
  offered_qos=())``: ``latched=True`` records TRANSIENT_LOCAL QoS for a topic (read back as
  ``TopicInfo.latched``), ``offered_qos`` the QoS profiles its publishers offered.
- :func:`qos_from_profile` ``(profile)`` -> rosbags ``Qos`` (from an rclpy ``QoSProfile``).
- :func:`armourcam_typestore` ``()`` -> rosbags ``Typestore`` (Kilted + armourcam types).

Conversions:

- :func:`camera_model_from_info` ``(msg) -> CameraModel`` (ROS 1 ``K``/``D`` or ROS 2 ``k``/``d``);
  :func:`camera_info_fields` ``(camera, *, style="rclpy"|"rosbags") -> dict``.
- :func:`normal_type` ``(msgtype)``: ``pkg/Name`` -> ``pkg/msg/Name`` (ROS 1 and 2 spellings).
- :func:`stamp_to_ns` / :func:`ns_to_stamp_fields`; :func:`copy_message` ``(src, dst_class)``:
  field-by-field copy of a message into another implementation's class (e.g. a ROS 1 bag's
  CameraInfo into rclpy's ``sensor_msgs.msg.CameraInfo``; names matched case-insensitively).

Errors: :class:`BagError` (a ``ValueError``) with the path and what is wrong.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from pose_estimator.camera import CameraModel
from pose_estimator.errors import CalibrationError

from . import image_codec, records

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)


class BagError(ValueError):
    """A bag cannot be read or written as asked."""


class BagTruncatedError(BagError):
    """A bag ends early; every readable message before the cut has been yielded.

    Attributes
    ----------
    truncation : Truncation
    """

    def __init__(self, truncation: Truncation) -> None:
        super().__init__(truncation.describe())
        self.truncation = truncation


@dataclass(frozen=True, slots=True)
class Truncation:
    """Where reading a damaged bag stopped.

    Attributes
    ----------
    path : Path
        The damaged file.
    offset : int
        Byte offset of the first record that could not be read completely.
    size : int
        File size in bytes.
    messages_read : int
        Messages readable before the cut (the index the next message would have had).
    reason : str
    """

    path: Path
    offset: int
    size: int
    messages_read: int
    reason: str

    def describe(self) -> str:
        """One-line report."""
        return (
            f"{self.path}: bag is truncated or damaged at byte {self.offset} of {self.size} "
            f"({self.reason}); {self.messages_read} messages before that point were read"
        )


@dataclass(frozen=True, slots=True)
class TopicInfo:
    """A topic of a bag: name, ROS 2 style type name (``pkg/msg/Name``), message count, and
    whether it was recorded latched (ROS 2 TRANSIENT_LOCAL offered QoS, ROS 1 ``latching``)."""

    topic: str
    msgtype: str
    count: int
    latched: bool = False


@dataclass(frozen=True, slots=True, eq=False)
class BagMessage:
    """One message of a bag.

    Attributes
    ----------
    topic, msgtype : str
    timestamp_ns : int
        Receive (log) time in the bag, ns since the epoch.
    index : int
        Position of the message in the iteration (0-based).
    rawdata : bytes
        Serialised message.
    serialization : {"cdr", "ros1"}
        Format of ``rawdata`` (ROS 2 bags hold CDR, ROS 1 bags ROS 1 serialisation).
    message : object or None
        The deserialised rosbags message (None when ``deserialize=False``).
    """

    topic: str
    msgtype: str
    timestamp_ns: int
    index: int
    rawdata: bytes
    serialization: str
    message: Any = None


@dataclass(frozen=True, slots=True, eq=False)
class Frame:
    """A decoded camera frame from a bag.

    Attributes
    ----------
    topic : str
    index : int
        Index of the frame among the topic's messages (0-based).
    timestamp_ns : int
        Log time in the bag, ns.
    stamp_ns : int
        ``header.stamp`` of the image, ns (0 when the header is empty).
    frame_id : str
    image : ndarray or None
        Grey ``(H, W)`` (or BGR with ``colour=True``) uint8/uint16 image; None when undecodable.
    error : str or None
        Why the frame could not be decoded.
    """

    topic: str
    index: int
    timestamp_ns: int
    stamp_ns: int
    frame_id: str
    image: NDArray[Any] | None
    error: str | None = None


# --------------------------------------------------------------------------------------------
# Small conversions


def stamp_to_ns(stamp: Any) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time`` (``sec``/``nanosec``, or ``secs``/``nsecs``)."""
    sec = stamp.sec if hasattr(stamp, "sec") else stamp.secs
    nsec = stamp.nanosec if hasattr(stamp, "nanosec") else stamp.nsecs
    return int(sec) * 1_000_000_000 + int(nsec)


def ns_to_stamp_fields(ns: int) -> dict[str, int]:
    """``{"sec": ..., "nanosec": ...}`` of a time in ns (for ``builtin_interfaces/Time``)."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def _get(msg: Any, *names: str) -> Any:
    for name in names:
        if hasattr(msg, name):
            return getattr(msg, name)
    raise AttributeError(f"{type(msg).__name__} has none of the fields {names}")


def camera_model_from_info(msg: Any) -> CameraModel:
    """``CameraModel`` from a ``sensor_msgs/CameraInfo`` (ROS 2 ``k``/``d`` or ROS 1 ``K``/``D``).

    Raises
    ------
    CalibrationError
        For a malformed calibration (e.g. an all-zero ``k`` from an uncalibrated camera).
    """
    try:
        width, height = int(msg.width), int(msg.height)
        k = np.asarray(_get(msg, "k", "K"), dtype=np.float64)
        d = np.asarray(_get(msg, "d", "D"), dtype=np.float64)
        model = str(msg.distortion_model)
    except (AttributeError, TypeError, ValueError) as err:
        raise CalibrationError(f"not a usable CameraInfo: {err}") from err
    return CameraModel.from_camera_info(width, height, k, model, d)


def camera_info_fields(
    camera: CameraModel, *, style: Literal["rclpy", "rosbags"] = "rclpy"
) -> dict[str, Any]:
    """Fields of a ``sensor_msgs/CameraInfo`` for ``camera`` (without ``header`` and ``roi``).

    ``p`` is ``[K | 0]`` (a monocular camera), ``r`` the identity. With ``style="rclpy"``, ``d`` is
    a list (rclpy refuses numpy arrays for sequences); with ``"rosbags"`` every array is numpy.
    """
    d: Any = camera.D.astype(np.float64)
    if style == "rclpy":
        d = [float(x) for x in d]
    return {
        "height": camera.height,
        "width": camera.width,
        "distortion_model": camera.distortion_model,
        "d": d,
        "k": camera.K.ravel().astype(np.float64),
        "r": np.eye(3).ravel(),
        "p": np.hstack([camera.K, np.zeros((3, 1))]).ravel(),
        "binning_x": 0,
        "binning_y": 0,
    }


def _message_fields(cls_or_msg: Any) -> list[str]:
    names = getattr(cls_or_msg, "get_fields_and_field_types", None)
    if names is not None:  # rclpy: slot names are the field names prefixed by "_"
        return list(names().keys())
    if dataclasses.is_dataclass(cls_or_msg):  # rosbags; constants are ClassVars, not fields
        return [f.name for f in dataclasses.fields(cls_or_msg)]
    raise BagError(f"{cls_or_msg!r} is not a ROS message class")


def _is_message(value: Any) -> bool:
    return hasattr(value, "get_fields_and_field_types") or (
        hasattr(value, "__dataclass_fields__") and hasattr(value, "__msgtype__")
    )


def copy_message(src: Any, dst_class: Any) -> Any:
    """Copy a message into another implementation's class, field by field.

    Used to republish rosbags messages (ROS 1 or ROS 2 bags) with rclpy classes. Fields are matched
    by name, case-insensitively (ROS 1 ``K`` -> ROS 2 ``k``); fields the destination lacks (ROS 1
    ``header.seq``) are dropped, fields the source lacks keep the destination's default. Numeric
    arrays are passed as numpy arrays, ``uint8`` arrays as bytes. rclpy destinations only (rosbags
    classes need every field at construction).
    """
    dst = dst_class()
    exact = set(_message_fields(src))
    folded = {n.lower(): n for n in exact}
    for name in _message_fields(dst):
        sname = name if name in exact else folded.get(name.lower())
        if sname is None:
            continue
        value = getattr(src, sname)
        current = getattr(dst, name)
        if _is_message(value):
            value = copy_message(value, type(current))
        elif isinstance(value, list) and value and _is_message(value[0]):
            elem = _element_class(dst, name)
            value = [copy_message(v, elem) for v in value]
        elif isinstance(value, np.ndarray):
            if value.dtype == np.uint8 and not isinstance(current, np.ndarray):
                value = value.tobytes()
            elif not isinstance(current, np.ndarray):
                value = value.tolist()
        setattr(dst, name, value)
    return dst


def _element_class(dst: Any, name: str) -> Any:
    import importlib

    slot_types = dict(zip(_message_fields(dst), dst.SLOT_TYPES, strict=True))
    value_type = getattr(slot_types[name], "value_type", None)
    if value_type is None or not hasattr(value_type, "namespaces"):
        raise BagError(f"cannot find the element type of {type(dst).__name__}.{name}")
    module = importlib.import_module(".".join(value_type.namespaces))
    return getattr(module, value_type.name)


# --------------------------------------------------------------------------------------------
# Recovery reader for truncated MCAP files

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x03, 0x04, 0x05, 0x06
_OP_FOOTER, _OP_DATA_END = 0x02, 0x0F
_OP_NAMES = {0x03: "schema", 0x04: "channel", 0x05: "message", 0x07: "message index"}
_OP_NAMES.update({0x09: "attachment", 0x0C: "metadata", 0x0F: "data end", 0x02: "footer"})


class _CutError(Exception):
    def __init__(self, offset: int, reason: str) -> None:
        super().__init__(reason)
        self.offset = offset
        self.reason = reason


@dataclass(slots=True)
class _McapScan:
    """Sequential scan of an MCAP file that stops cleanly at the first incomplete record.

    Reads record by record from the file (no index, no footer needed); an uncompressed chunk cut
    short still yields its complete messages.
    """

    path: Path
    schemas: dict[int, tuple[str, str, str]] = field(default_factory=dict)
    channels: dict[int, tuple[str, int]] = field(default_factory=dict)  # id -> (topic, schema)
    cut: _CutError | None = None
    size: int = 0

    def messages(self) -> Iterator[tuple[int, int, bytes]]:
        """Yield ``(channel_id, log_time, data)`` in file order; sets ``cut`` on a damaged end."""
        self.size = self.path.stat().st_size
        with self.path.open("rb") as fh:
            if fh.read(8) != _MCAP_MAGIC:
                raise BagError(f"{self.path}: not an MCAP file (bad magic)")
            try:
                yield from self._top(fh)
            except _CutError as cut:
                self.cut = cut

    def _top(self, fh: Any) -> Iterator[tuple[int, int, bytes]]:
        pos = 8
        while True:
            head = fh.read(9)
            if not head:
                raise _CutError(pos, "file ends before the MCAP footer (recording not closed)")
            if len(head) < 9:
                raise _CutError(pos, "incomplete record header")
            op = head[0]
            (length,) = struct.unpack_from("<Q", head, 1)
            body = fh.read(length)
            if op == _OP_CHUNK:
                yield from self._chunk(body, length, pos)
            elif len(body) < length:
                kind = _OP_NAMES.get(op, f"opcode 0x{op:02x}")
                raise _CutError(pos, f"{kind} record of {length} bytes cut short at {len(body)}")
            elif op in (_OP_FOOTER, _OP_DATA_END):
                return
            else:
                yield from self._record(op, body)
            pos += 9 + length

    def _record(self, op: int, rec: bytes) -> Iterator[tuple[int, int, bytes]]:
        if op == _OP_SCHEMA:
            (sid,) = struct.unpack_from("<H", rec, 0)
            name, p = _mcap_str(rec, 2)
            encoding, p = _mcap_str(rec, p)
            (n,) = struct.unpack_from("<I", rec, p)
            self.schemas[sid] = (name, encoding, rec[p + 4 : p + 4 + n].decode("utf-8"))
        elif op == _OP_CHANNEL:
            cid, sid = struct.unpack_from("<HH", rec, 0)
            topic, _ = _mcap_str(rec, 4)
            self.channels[cid] = (topic, sid)
        elif op == _OP_MESSAGE:
            cid, _seq, log_time = struct.unpack_from("<HIQ", rec, 0)
            yield cid, log_time, rec[22:]

    def _inner(self, buf: bytes, base: int | None) -> Iterator[tuple[int, int, bytes]]:
        """Records inside a chunk; ``base`` is the file offset of ``buf`` (None: compressed)."""
        pos = 0
        while pos < len(buf):
            at = -1 if base is None else base + pos
            if pos + 9 > len(buf):
                raise _CutError(at, "chunk cut short inside a record header")
            op = buf[pos]
            (length,) = struct.unpack_from("<Q", buf, pos + 1)
            if pos + 9 + length > len(buf):
                raise _CutError(at, f"chunk cut short inside a record of {length} bytes")
            yield from self._record(op, buf[pos + 9 : pos + 9 + length])
            pos += 9 + length

    def _chunk(self, body: bytes, length: int, chunk_at: int) -> Iterator[tuple[int, int, bytes]]:
        try:
            (usize,) = struct.unpack_from("<Q", body, 16)
            (crc,) = struct.unpack_from("<I", body, 24)
            compression, p = _mcap_str(body, 28)
            (records_len,) = struct.unpack_from("<Q", body, p)
        except (struct.error, UnicodeDecodeError) as err:
            raise _CutError(chunk_at, "chunk header cut short") from err
        start = p + 8
        complete = len(body) == length and start + records_len <= len(body)
        if compression == "":
            # Uncompressed chunks are readable record by record up to the cut.
            yield from self._inner(body[start : start + records_len], chunk_at + 9 + start)
            if not complete:
                raise _CutError(chunk_at, "chunk cut short")
            return
        if not complete:
            raise _CutError(chunk_at, f"{compression} chunk cut short")
        from rosbags.rosbag2.storage_mcap import decompress

        try:
            raw = decompress(body[start : start + records_len], compression, usize, crc)
        except Exception as err:  # a damaged compressed chunk is where reading stops
            raise _CutError(chunk_at, f"cannot decompress chunk: {err}") from err
        try:
            yield from self._inner(raw, None)
        except _CutError as err:
            raise _CutError(chunk_at, f"damaged chunk: {err.reason}") from err


def _mcap_str(buf: Any, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, pos)
    return bytes(buf[pos + 4 : pos + 4 + n]).decode("utf-8"), pos + 4 + n


_ROS1_MAGIC = b"#ROSBAG V2.0\n"
_ROS1_MSG, _ROS1_CHUNK, _ROS1_CONN = 0x02, 0x05, 0x07


def _ros1_header(buf: bytes) -> dict[str, bytes]:
    fields: dict[str, bytes] = {}
    pos = 0
    while pos + 4 <= len(buf):
        (n,) = struct.unpack_from("<I", buf, pos)
        name, sep, value = buf[pos + 4 : pos + 4 + n].partition(b"=")
        if not sep or pos + 4 + n > len(buf):
            raise ValueError("malformed ROS 1 record header")
        fields[name.decode("ascii")] = value
        pos += 4 + n
    return fields


@dataclass(slots=True)
class _Ros1Scan:
    """Sequential scan of a ROS 1 bag (v2.0) that stops cleanly at the first incomplete record.

    Needs no index (a recorder killed before closing leaves none). Uncompressed and bz2 chunks
    cut short still yield their complete messages; lz4 chunks must be whole.
    """

    path: Path
    schemas: dict[int, tuple[str, str, str]] = field(default_factory=dict)
    channels: dict[int, tuple[str, int]] = field(default_factory=dict)
    cut: _CutError | None = None
    size: int = 0
    index_pos: int = 0

    def messages(self) -> Iterator[tuple[int, int, bytes]]:
        """Yield ``(conn_id, time_ns, data)`` in file order; sets ``cut`` on a damaged end."""
        self.size = self.path.stat().st_size
        with self.path.open("rb") as fh:
            if fh.read(len(_ROS1_MAGIC)) != _ROS1_MAGIC:
                raise BagError(f"{self.path}: not a ROS 1 bag (v2.0)")
            try:
                yield from self._top(fh)
            except _CutError as cut:
                self.cut = cut

    def _top(self, fh: Any) -> Iterator[tuple[int, int, bytes]]:
        pos = len(_ROS1_MAGIC)
        while True:
            head = fh.read(4)
            if not head:
                if self.index_pos and pos <= self.index_pos:
                    raise _CutError(pos, "file ends before the bag index (recording not closed)")
                return
            rec = head + fh.read(struct.unpack_from("<I", head)[0] + 4) if len(head) == 4 else head
            try:
                header, data_len, at = self._split(rec, 0)
            except (struct.error, ValueError) as err:
                raise _CutError(pos, "incomplete record header") from err
            data = rec[at:] + fh.read(data_len)
            op = header.get("op", b"\x00")[0]
            if op == _ROS1_CHUNK:
                yield from self._chunk(header, data, data_len, pos, pos + at)
            elif len(data) < data_len:
                raise _CutError(pos, f"record of {data_len} bytes cut short at {len(data)}")
            else:
                if op == 0x03 and "index_pos" in header:
                    (self.index_pos,) = struct.unpack("<Q", header["index_pos"])
                yield from self._record(op, header, data)
            pos += at + data_len

    @staticmethod
    def _split(buf: bytes, pos: int = 0) -> tuple[dict[str, bytes], int, int]:
        """Header fields, data length and data start of the record at ``pos`` of ``buf``."""
        (hlen,) = struct.unpack_from("<I", buf, pos)
        if pos + 4 + hlen + 4 > len(buf):
            raise ValueError("short header")
        header = _ros1_header(buf[pos + 4 : pos + 4 + hlen])
        (data_len,) = struct.unpack_from("<I", buf, pos + 4 + hlen)
        return header, data_len, pos + 8 + hlen

    def _record(
        self, op: int, header: dict[str, bytes], data: bytes
    ) -> Iterator[tuple[int, int, bytes]]:
        from rosbags.typesys.msg import normalize_msgtype

        if op == _ROS1_CONN:
            (conn,) = struct.unpack("<I", header["conn"])
            info = _ros1_header(data)
            msgtype = normalize_msgtype(info["type"].decode())
            self.channels[conn] = (header["topic"].decode(), conn)
            self.schemas[conn] = (msgtype, "ros1msg", info["message_definition"].decode())
        elif op == _ROS1_MSG:
            (conn,) = struct.unpack("<I", header["conn"])
            secs, nsecs = struct.unpack("<II", header["time"])
            yield conn, secs * 1_000_000_000 + nsecs, data

    def _chunk(
        self, header: dict[str, bytes], data: bytes, data_len: int, at: int, data_at: int
    ) -> Iterator[tuple[int, int, bytes]]:
        """Records of a chunk at file offset ``at`` whose data starts at ``data_at``."""
        compression = header.get("compression", b"none").decode()
        complete = len(data) == data_len
        if compression == "none":
            raw = data
        elif compression == "bz2":
            import bz2

            try:  # a bz2 stream decompresses as far as it goes
                raw = bz2.BZ2Decompressor().decompress(data)
            except (OSError, ValueError) as err:
                raise _CutError(at, f"damaged bz2 chunk: {err}") from err
        elif compression == "lz4" and complete:
            import lz4.frame

            try:
                raw = lz4.frame.decompress(data)
            except RuntimeError as err:
                raise _CutError(at, f"damaged lz4 chunk: {err}") from err
        else:
            raise _CutError(at, f"{compression} chunk cut short")
        pos = 0
        while pos < len(raw):
            where = data_at + pos if compression == "none" else at
            try:
                inner, inner_len, start = self._split(raw, pos)
            except (struct.error, ValueError) as err:
                raise _CutError(where, "chunk cut short inside a record header") from err
            if start + inner_len > len(raw):
                raise _CutError(where, f"chunk cut short inside a record of {inner_len} bytes")
            op = inner.get("op", b"\x00")[0]
            yield from self._record(op, inner, raw[start : start + inner_len])
            pos = start + inner_len
        if not complete:
            raise _CutError(at, "chunk cut short")


# --------------------------------------------------------------------------------------------
# Reading


def _mcap_files(path: Path) -> list[Path]:
    if path.is_file():
        return [path] if path.suffix == ".mcap" else []
    return sorted(path.glob("*.mcap"))


class Bag:
    """An open bag; create with :func:`open_bag`. See the module docstring for the API."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.truncation: Truncation | None = None
        self._reader: Any = None
        self._recover: list[Path] = []
        self._ros1 = False
        self._typestore: Any = None
        self._topics: dict[str, TopicInfo] = {}
        self.kind = ""
        self.start_ns = 0
        self.end_ns = 0
        self._open()

    # -- opening

    def _open(self) -> None:
        from rosbags.highlevel import AnyReader, AnyReaderError

        if not self.path.exists():
            raise BagError(f"{self.path}: no such bag")
        if self.path.is_file() and self.path.stat().st_size == 0:
            raise BagError(f"{self.path}: bag file is empty")
        try:
            reader = AnyReader([self.path])
            reader.open()
        except (AnyReaderError, OSError, KeyError, ValueError, struct.error) as err:
            mcaps = _mcap_files(self.path)
            if mcaps:
                self._open_recovery(mcaps, err)
                return
            if self.path.is_file() and _is_ros1(self.path):
                self._ros1 = True
                self._open_recovery([self.path], err)
                return
            if self.path.is_file() and _starts_with(self.path, _MCAP_MAGIC):
                # Readers pick the format by the name: an MCAP file named .bag is read as ROS 1.
                raise BagError(
                    f"{self.path}: an MCAP file named {self.path.suffix or 'without a suffix'}; "
                    "rename it to end in .mcap"
                ) from err
            raise BagError(f"{self.path}: cannot open bag: {err}") from err
        self._reader = reader
        self._typestore = reader.typestore
        self.kind = "rosbag2" if reader.is2 else "rosbag1"
        counts: dict[tuple[str, str], int] = {}
        latched: set[str] = set()
        for conn in reader.connections:
            key = (conn.topic, conn.msgtype)
            counts[key] = counts.get(key, 0) + conn.msgcount
            if _is_latched(conn):
                latched.add(conn.topic)
        self._topics = {t: TopicInfo(t, m, n, t in latched) for (t, m), n in sorted(counts.items())}
        self.start_ns = reader.start_time if reader.message_count else 0
        self.end_ns = reader.end_time if reader.message_count else 0

    def _scan(self, path: Path) -> _McapScan | _Ros1Scan:
        return _Ros1Scan(path) if self._ros1 else _McapScan(path)

    def _open_recovery(self, mcaps: list[Path], err: Exception) -> None:
        """Index a damaged MCAP or ROS 1 bag by scanning it (no index/summary to trust)."""
        self.kind = "rosbag1-recovered" if self._ros1 else "mcap-recovered"
        self._recover = mcaps
        counts: dict[str, int] = {}
        types: dict[str, str] = {}
        times: list[int] = []
        for path in mcaps:
            scan = self._scan(path)
            for cid, log_time, _ in scan.messages():
                topic, sid = scan.channels[cid]
                counts[topic] = counts.get(topic, 0) + 1
                types[topic] = scan.schemas[sid][0]
                times.append(log_time)
            for topic, sid in scan.channels.values():
                counts.setdefault(topic, 0)
                types.setdefault(topic, scan.schemas.get(sid, ("", "", ""))[0])
            if scan.cut is not None and self.truncation is None:
                self.truncation = Truncation(
                    path, scan.cut.offset, scan.size, sum(counts.values()), scan.cut.reason
                )
        # Without a cut the data section is whole and only the summary/footer is damaged: every
        # message is readable, so the bag is served as it is (kind says it was recovered).
        if self.truncation is None and not counts:
            raise BagError(f"{self.path}: cannot open bag: {err}") from err
        self._topics = {t: TopicInfo(t, types[t], n) for t, n in sorted(counts.items())}
        self.start_ns = min(times, default=0)
        self.end_ns = max(times, default=-1) + 1 if times else 0

    # -- context manager

    def __enter__(self) -> Bag:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the underlying reader (idempotent)."""
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    # -- metadata

    @property
    def topics(self) -> dict[str, TopicInfo]:
        """``{topic: TopicInfo}`` (for a truncated bag: the readable messages only)."""
        return dict(self._topics)

    @property
    def message_count(self) -> int:
        """Number of (readable) messages."""
        return sum(t.count for t in self._topics.values())

    def topics_of_type(self, *msgtypes: str) -> list[str]:
        """Topics whose type is one of ``msgtypes`` (``pkg/msg/Name``; ``pkg/Name`` accepted)."""
        want = {normal_type(m) for m in msgtypes}
        return [t for t, info in self._topics.items() if normal_type(info.msgtype) in want]

    def image_topic(self, topic: str | None = None) -> str:
        """The image topic: ``topic`` checked, or the only Image/CompressedImage topic.

        When several image topics exist, a raw ``Image`` topic is preferred if there is exactly
        one; otherwise the choice is ambiguous.

        Raises
        ------
        BagError
            If ``topic`` is not an image topic of this bag, or none / several candidates exist.
        """
        return self._pick(topic, IMAGE_TYPES, "image")

    def camera_info_topic(self, topic: str | None = None) -> str | None:
        """The CameraInfo topic: ``topic`` checked, or the only one; None when the bag has none.

        Raises
        ------
        BagError
            If ``topic`` is not a CameraInfo topic of this bag or several candidates exist.
        """
        if topic is None and not self.topics_of_type(CAMERA_INFO):
            return None
        return self._pick(topic, (CAMERA_INFO,), "camera info")

    def _pick(self, topic: str | None, msgtypes: Sequence[str], what: str) -> str:
        candidates = self.topics_of_type(*msgtypes)
        if topic is not None:
            if topic not in candidates:
                have = self._topics.get(topic)
                raise BagError(
                    f"{self.path}: topic {topic!r} "
                    + (f"has type {have.msgtype}" if have else "is not in the bag")
                    + f"; {what} topics: {candidates}"
                )
            return topic
        if len(candidates) == 1:
            return candidates[0]
        if not candidates:
            raise BagError(
                f"{self.path}: no {what} topic ({' or '.join(msgtypes)}); "
                f"topics: {[f'{t} [{i.msgtype}]' for t, i in self._topics.items()]}"
            )
        raw = [t for t in candidates if normal_type(self._topics[t].msgtype) == msgtypes[0]]
        if len(raw) == 1 and len(msgtypes) > 1:
            return raw[0]
        raise BagError(f"{self.path}: several {what} topics {candidates}; choose one")

    # -- messages

    def messages(
        self,
        topics: Iterable[str] | None = None,
        msgtypes: Iterable[str] | None = None,
        *,
        start_ns: int | None = None,
        stop_ns: int | None = None,
        deserialize: bool = True,
        on_truncation: Literal["raise", "report"] = "raise",
    ) -> Iterator[BagMessage]:
        """Iterate over messages in log-time order (file order for a recovered MCAP).

        Parameters
        ----------
        topics, msgtypes
            Keep only these topics / types (None: all).
        start_ns, stop_ns
            Keep log times in ``[start_ns, stop_ns)``.
        deserialize
            Deserialise into rosbags message objects (else ``message`` is None).
        on_truncation
            ``"raise"``: after the last readable message raise :class:`BagTruncatedError`;
            ``"report"``: just stop (``bag.truncation`` says where).

        Raises
        ------
        BagError
            If a message cannot be read or deserialised (naming its index and topic).
        """
        topic_set = set(topics) if topics is not None else None
        type_set = {normal_type(m) for m in msgtypes} if msgtypes is not None else None

        def keep(topic: str, msgtype: str) -> bool:
            return (topic_set is None or topic in topic_set) and (
                type_set is None or normal_type(msgtype) in type_set
            )

        if topic_set is not None and (missing := sorted(topic_set - set(self._topics))):
            raise BagError(f"{self.path}: topics {missing} are not in the bag")
        if self._recover:
            yield from self._recovered(keep, start_ns, stop_ns, deserialize)
            if self.truncation is not None and on_truncation == "raise":
                raise BagTruncatedError(self.truncation)
            return
        if self._reader is None:
            raise BagError(f"{self.path}: bag is closed")
        yield from self._indexed(keep, start_ns, stop_ns, deserialize)

    def _indexed(
        self, keep: Any, start_ns: int | None, stop_ns: int | None, deserialize: bool
    ) -> Iterator[BagMessage]:
        reader = self._reader
        conns = [c for c in reader.connections if keep(c.topic, c.msgtype)]
        serialization = "cdr" if reader.is2 else "ros1"
        index = 0
        it = reader.messages(connections=conns, start=start_ns, stop=stop_ns) if conns else iter(())
        while True:
            try:
                item = next(it)
            except StopIteration:
                return
            except Exception as err:
                raise BagError(
                    f"{self.path}: cannot read message {index} (after {index} good messages): {err}"
                ) from err
            conn, t, raw = item
            msg = self._deserialize(raw, conn.msgtype, index, conn.topic) if deserialize else None
            yield BagMessage(conn.topic, conn.msgtype, t, index, bytes(raw), serialization, msg)
            index += 1

    def _deserialize(self, raw: bytes, msgtype: str, index: int, topic: str) -> Any:
        try:
            if self._reader is not None:
                return self._reader.deserialize(raw, msgtype)
            if self._ros1:
                return self._typestore.deserialize_ros1(raw, msgtype)
            return self._typestore.deserialize_cdr(raw, msgtype)
        except Exception as err:
            raise BagError(
                f"{self.path}: message {index} on {topic} ({msgtype}) cannot be deserialised: {err}"
            ) from err

    def _recovered(
        self, keep: Any, start_ns: int | None, stop_ns: int | None, deserialize: bool
    ) -> Iterator[BagMessage]:
        from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

        index = 0
        serialization = "ros1" if self._ros1 else "cdr"
        for path in self._recover:
            scan = self._scan(path)
            registered: set[int] = set()
            for cid, t, raw in scan.messages():
                topic, sid = scan.channels[cid]
                name, encoding, text = scan.schemas[sid]
                if not keep(topic, name) or (start_ns is not None and t < start_ns):
                    continue
                if stop_ns is not None and t >= stop_ns:
                    continue
                msg = None
                if deserialize:
                    if sid not in registered:
                        store = self._typestore or get_typestore(Stores.EMPTY)
                        try:
                            if encoding == "ros2idl":
                                store.register(get_types_from_idl(text))
                            elif encoding == "ros1msg":
                                store.register(get_types_from_msg(text, name))
                            else:
                                store.register(_types_from_msg_bundle(text, name))
                        except Exception as err:
                            raise BagError(f"{path}: bad schema for {name}: {err}") from err
                        self._typestore = store
                        registered.add(sid)
                    msg = self._deserialize(raw, name, index, topic)
                yield BagMessage(topic, name, t, index, raw, serialization, msg)
                index += 1

    def frames(
        self,
        topic: str | None = None,
        *,
        colour: bool = False,
        on_truncation: Literal["raise", "report"] = "raise",
    ) -> Iterator[Frame]:
        """Decoded frames of the image topic (found by type when not given).

        A frame the codec cannot decode is yielded with ``image=None`` and ``error`` set, so a
        caller logs it and carries on; reading errors still raise :class:`BagError`.
        """
        topic = self.image_topic(topic)
        for k, bm in enumerate(self.messages([topic], on_truncation=on_truncation)):
            header = getattr(bm.message, "header", None)
            stamp = stamp_to_ns(header.stamp) if header is not None else 0
            frame_id = str(getattr(header, "frame_id", "")) if header is not None else ""
            try:
                image = image_codec.decode(bm.message, colour=colour)
            except image_codec.ImageCodecError as err:
                yield Frame(topic, k, bm.timestamp_ns, stamp, frame_id, None, str(err))
                continue
            yield Frame(topic, k, bm.timestamp_ns, stamp, frame_id, image)

    def camera_model(self, topic: str | None = None) -> CameraModel:
        """The camera from the first message of the CameraInfo topic.

        Raises
        ------
        BagError
            If the bag has no CameraInfo (or its calibration is malformed).
        """
        name = self.camera_info_topic(topic)
        if name is None:
            raise BagError(f"{self.path}: bag has no sensor_msgs/CameraInfo topic")
        for bm in self.messages([name], on_truncation="report"):
            try:
                return camera_model_from_info(bm.message)
            except CalibrationError as err:
                raise BagError(f"{self.path}: {name} message {bm.index}: {err}") from err
        raise BagError(f"{self.path}: {name} has no readable message")


def _is_ros1(path: Path) -> bool:
    return _starts_with(path, _ROS1_MAGIC)


def _starts_with(path: Path, magic: bytes) -> bool:
    with path.open("rb") as fh:
        return fh.read(len(magic)) == magic


def _is_latched(conn: Any) -> bool:
    ext = conn.ext
    if hasattr(ext, "latching"):
        return bool(ext.latching)
    return any(
        getattr(getattr(q, "durability", None), "name", "") == "TRANSIENT_LOCAL"
        for q in getattr(ext, "offered_qos_profiles", ()) or ()
    )


def _types_from_msg_bundle(text: str, name: str) -> dict[str, Any]:
    """Types of a ``ros2msg`` schema: the main definition and its ``MSG: pkg/Name`` dependencies."""
    from rosbags.typesys import get_types_from_msg

    sep = "=" * 80 + "\n"
    parts = text.split(sep)
    types: dict[str, Any] = dict(get_types_from_msg(parts[0], name))
    for part in parts[1:]:
        head, _, body = part.partition("\n")
        dep = head.removeprefix("MSG: ").strip()
        if "/msg/" not in dep and "/" in dep:
            dep = dep.replace("/", "/msg/", 1)
        types.update(get_types_from_msg(body, dep))
    return types


def normal_type(msgtype: str) -> str:
    """``pkg/Name`` -> ``pkg/msg/Name`` (ROS 1 and ROS 2 spellings compare equal)."""
    parts = msgtype.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else msgtype


def open_bag(path: str | Path) -> Bag:
    """Open a bag for reading: rosbag2 directory (MCAP/SQLite), single ``.mcap`` or ROS 1 ``.bag``.

    A truncated MCAP (no footer/summary, e.g. a recorder killed mid-run) or a truncated, unindexed
    ROS 1 bag opens in recovery mode (``bag.kind`` is ``mcap-recovered`` / ``rosbag1-recovered``):
    its readable prefix is indexed by scanning and ``bag.truncation`` says where it stops.

    Raises
    ------
    BagError
        If the path does not exist or is not a readable bag.
    """
    return Bag(Path(path))


# --------------------------------------------------------------------------------------------
# Writing


def armourcam_typestore() -> Any:
    """A rosbags typestore with the ROS 2 Kilted standard types and every armourcam definition."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    store.register(records.typesdict())
    return store


class BagWriter:
    """Write a ROS 2 bag (rosbags ``Writer``, format version 9), MCAP by default.

    Parameters
    ----------
    path : str or Path
        The bag directory to create (must not exist).
    storage : {"mcap", "sqlite3"}

    Use as a context manager; the bag is closed (and its metadata written) even when the body
    raises, so what was written is kept.
    """

    def __init__(self, path: str | Path, *, storage: Literal["mcap", "sqlite3"] = "mcap") -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer, WriterError

        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
        if plugin is None:
            raise BagError(f"unknown storage {storage!r}; use 'mcap' or 'sqlite3'")
        self.path = Path(path)
        self.typestore = armourcam_typestore()
        try:
            writer = Writer(self.path, version=9, storage_plugin=plugin)
            writer.open()
        except (WriterError, OSError) as err:
            raise BagError(f"cannot create bag {self.path}: {err}") from err
        self._writer: Any = writer
        self._connections: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Finish the bag (idempotent)."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    # -- building blocks

    def new(self, msgtype: str, **fields: Any) -> Any:
        """A rosbags message object of ``msgtype`` (every field must be given)."""
        try:
            cls = self.typestore.types[normal_type(msgtype)]
        except KeyError:
            raise BagError(f"unknown message type {msgtype!r}") from None
        return cls(**fields)

    def header(self, stamp_ns: int, frame_id: str = "") -> Any:
        """A ``std_msgs/Header`` with ``stamp_ns`` and ``frame_id``."""
        stamp = self.new("builtin_interfaces/msg/Time", **ns_to_stamp_fields(stamp_ns))
        return self.new("std_msgs/msg/Header", stamp=stamp, frame_id=frame_id)

    def add_topic(
        self,
        topic: str,
        msgtype: str,
        *,
        latched: bool = False,
        offered_qos: Sequence[Any] = (),
    ) -> Any:
        """Register ``topic`` (done implicitly by the ``write*`` methods); returns the connection.

        Parameters
        ----------
        topic, msgtype : str
        latched : bool
            Record a RELIABLE + TRANSIENT_LOCAL, depth 1 offered QoS (as the matcher's latched
            outputs have), read back as ``TopicInfo.latched`` so a replayer republishes the topic
            latched.
        offered_qos : sequence
            The QoS profiles the topic's publishers offered, one per publisher, stored in the
            bag's metadata as ``ros2 bag record`` does: rclpy ``QoSProfile`` or rosbags ``Qos``
            objects (see :func:`qos_from_profile`). Not together with ``latched``.

        Only the first registration of a topic stores QoS; later calls return its connection.

        Raises
        ------
        BagError
            If the topic exists with another type, both ``latched`` and ``offered_qos`` are
            given, or a profile is not a QoS profile.
        """
        msgtype = normal_type(msgtype)
        conn = self._connections.get(topic)
        if conn is not None:
            if conn.msgtype != msgtype:
                raise BagError(f"topic {topic} already has type {conn.msgtype}, not {msgtype}")
            return conn
        if self._writer is None:
            raise BagError(f"bag {self.path} is closed")
        if latched and offered_qos:
            raise BagError(f"{topic}: give latched or offered_qos, not both")
        qos = [_latched_qos()] if latched else [qos_from_profile(q) for q in offered_qos]
        conn = self._writer.add_connection(
            topic, msgtype, typestore=self.typestore, offered_qos_profiles=qos
        )
        self._connections[topic] = conn
        self.counts[topic] = 0
        return conn

    def write(self, topic: str, msgtype: str, message: Any, timestamp_ns: int) -> None:
        """Serialise (CDR) and write one message at log time ``timestamp_ns``."""
        conn = self.add_topic(topic, msgtype)
        if self._writer is None:
            raise BagError(f"bag {self.path} is closed")
        try:
            raw = self.typestore.serialize_cdr(message, conn.msgtype)
        except Exception as err:
            raise BagError(f"cannot serialise a {conn.msgtype} for {topic}: {err}") from err
        self._writer.write(conn, int(timestamp_ns), raw)
        self.counts[topic] += 1

    def write_raw(self, topic: str, msgtype: str, rawdata: bytes, timestamp_ns: int) -> None:
        """Write an already CDR-serialised message (e.g. as received by a generic subscription),
        without deserialising it. The type must be known to :attr:`typestore`."""
        conn = self.add_topic(topic, msgtype)
        if self._writer is None:
            raise BagError(f"bag {self.path} is closed")
        self._writer.write(conn, int(timestamp_ns), rawdata)
        self.counts[topic] += 1

    # -- typed writers

    def write_image(
        self,
        topic: str,
        image: NDArray[Any],
        timestamp_ns: int,
        *,
        frame_id: str = "camera",
        encoding: str | None = None,
        stamp_ns: int | None = None,
    ) -> None:
        """Write ``image`` as a ``sensor_msgs/Image`` (see ``image_codec.image_to_msg_fields``)."""
        fields = image_codec.image_to_msg_fields(image, encoding, data_as="numpy")
        header = self.header(timestamp_ns if stamp_ns is None else stamp_ns, frame_id)
        self.write(topic, IMAGE, self.new(IMAGE, header=header, **fields), timestamp_ns)

    def write_compressed_image(
        self,
        topic: str,
        image: NDArray[Any],
        timestamp_ns: int,
        *,
        frame_id: str = "camera",
        codec: Literal["jpeg", "png"] = "jpeg",
        quality: int = 95,
        stamp_ns: int | None = None,
    ) -> None:
        """Write ``image`` as a ``sensor_msgs/CompressedImage`` (JPEG or PNG)."""
        fields = image_codec.compressed_to_msg_fields(
            image, codec, quality=quality, data_as="numpy"
        )
        header = self.header(timestamp_ns if stamp_ns is None else stamp_ns, frame_id)
        msg = self.new(COMPRESSED_IMAGE, header=header, **fields)
        self.write(topic, COMPRESSED_IMAGE, msg, timestamp_ns)

    def write_camera_info(
        self,
        topic: str,
        camera: CameraModel,
        timestamp_ns: int,
        *,
        frame_id: str = "camera",
        stamp_ns: int | None = None,
    ) -> None:
        """Write ``camera`` as a ``sensor_msgs/CameraInfo``."""
        roi = self.new(
            "sensor_msgs/msg/RegionOfInterest",
            x_offset=0,
            y_offset=0,
            height=0,
            width=0,
            do_rectify=False,
        )
        header = self.header(timestamp_ns if stamp_ns is None else stamp_ns, frame_id)
        fields = camera_info_fields(camera, style="rosbags")
        self.write(
            topic,
            CAMERA_INFO,
            self.new(CAMERA_INFO, header=header, roi=roi, **fields),
            timestamp_ns,
        )

    def write_records(
        self,
        topic: str,
        name: str,
        recs: Any,
        timestamp_ns: int,
        *,
        frame_id: str = "camera",
        stamp_ns: int | None = None,
        latched: bool = False,
    ) -> None:
        """Write records of definition ``name`` as a ``sensor_msgs/PointCloud2`` (as nodes do)."""
        self.add_topic(topic, POINT_CLOUD2, latched=latched)
        header = self.header(timestamp_ns if stamp_ns is None else stamp_ns, frame_id)
        msg = records.to_pointcloud2(
            self.typestore.types[POINT_CLOUD2],
            self.typestore.types["sensor_msgs/msg/PointField"],
            header,
            name,
            recs,
        )
        self.write(topic, POINT_CLOUD2, msg, timestamp_ns)

    def record_objects(self, name: str, recs: Any) -> list[Any]:
        """rosbags message objects (``armourcam_msgs/msg/<name>``) for structured records."""
        arr = records._as_records(name, recs)
        cls = self.typestore.types[records.msgtype(name)]
        lay = records.layout(name)
        out = []
        for rec in arr:
            kwargs: dict[str, Any] = {}
            for f in lay.fields:
                value = rec[f.name]
                if f.count == 1:
                    kwargs[f.name] = bool(value) if f.type == "bool" else value.item()
                else:
                    kwargs[f.name] = np.array(value, dtype=lay.dtype[f.name].base)
            out.append(cls(**kwargs))
        return out

    def write_record_array(
        self,
        topic: str,
        array_name: str,
        timestamp_ns: int,
        *,
        frame_id: str = "camera",
        stamp_ns: int | None = None,
        latched: bool = False,
        **fields: Any,
    ) -> None:
        """Write an armourcam array message, e.g. ``FiducialPoseArray`` with ``poses=records``.

        Record-array fields (``FiducialPoseRecord[] poses`` ...) take structured records (as from
        :func:`armourcam.records.poses_to_records`); other fields are passed as they are.
        """
        from rosbags.typesys.base import Nodetype

        msgtype = records.msgtype(array_name)
        self.add_topic(topic, msgtype, latched=latched)
        header = self.header(timestamp_ns if stamp_ns is None else stamp_ns, frame_id)
        cls = self.typestore.types[msgtype]
        kwargs: dict[str, Any] = {"header": header}
        for fname, desc in self.typestore.fielddefs[msgtype][1]:
            if fname == "header":
                continue
            if fname not in fields:
                raise BagError(f"{array_name}: field {fname!r} not given")
            value = fields.pop(fname)
            node, detail = desc
            if node == Nodetype.SEQUENCE and detail[0][0] == Nodetype.NAME:  # records
                rec_name = detail[0][1].rsplit("/", 1)[-1]
                value = self.record_objects(rec_name, value)
            kwargs[fname] = value
        if fields:
            raise BagError(f"{array_name} has no fields {sorted(fields)}")
        self.write(topic, msgtype, cls(**kwargs), timestamp_ns)

    def write_string(self, topic: str, text: str, timestamp_ns: int) -> None:
        """Write a ``std_msgs/String``."""
        self.write(
            topic, "std_msgs/msg/String", self.new("std_msgs/msg/String", data=text), timestamp_ns
        )

    def write_bool(self, topic: str, value: bool, timestamp_ns: int) -> None:
        """Write a ``std_msgs/Bool``."""
        self.write(
            topic,
            "std_msgs/msg/Bool",
            self.new("std_msgs/msg/Bool", data=bool(value)),
            timestamp_ns,
        )

    def write_empty(self, topic: str, timestamp_ns: int) -> None:
        """Write a ``std_msgs/Empty``."""
        self.write(
            topic,
            "std_msgs/msg/Empty",
            self.new("std_msgs/msg/Empty", **self._empty_fields()),
            timestamp_ns,
        )

    def _empty_fields(self) -> dict[str, Any]:
        # rosbags gives std_msgs/Empty a placeholder member (IDL structs cannot be empty).
        names = [n for n, _ in self.typestore.fielddefs["std_msgs/msg/Empty"][1]]
        return dict.fromkeys(names, 0)


def qos_from_profile(profile: Any) -> Any:
    """The rosbags ``Qos`` (a bag's ``offered_qos_profiles`` entry) of a QoS profile.

    Parameters
    ----------
    profile : object
        A rosbags ``Qos`` (returned as it is), or read by duck typing like an rclpy
        ``QoSProfile`` (e.g. from ``Node.get_publishers_info_by_topic``): ``history``,
        ``reliability``, ``durability``, ``liveliness`` (enums or member names, matched by
        name; names rosbags lacks become ``UNKNOWN``), ``depth``, ``deadline``, ``lifespan``,
        ``liveliness_lease_duration`` (durations with ``nanoseconds``; rclpy's infinite duration
        becomes 9223372036 s 854775807 ns, rosbag2's infinite) and
        ``avoid_ros_namespace_conventions``.

    Returns
    -------
    rosbags.interfaces.Qos

    Raises
    ------
    BagError
        If ``profile`` lacks one of those attributes.
    """
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    if isinstance(profile, Qos):
        return profile

    def policy(enum: Any, value: Any) -> Any:
        name = value if isinstance(value, str) else getattr(value, "name", None)
        if isinstance(name, str) and name in enum.__members__:
            return enum[name]
        return enum.UNKNOWN

    def duration(value: Any) -> QosTime:
        sec, nsec = divmod(int(getattr(value, "nanoseconds", value)), 1_000_000_000)
        return QosTime(sec, nsec)

    try:
        return Qos(
            policy(QosHistory, profile.history),
            int(profile.depth),
            policy(QosReliability, profile.reliability),
            policy(QosDurability, profile.durability),
            duration(profile.deadline),
            duration(profile.lifespan),
            policy(QosLiveliness, profile.liveliness),
            duration(profile.liveliness_lease_duration),
            bool(profile.avoid_ros_namespace_conventions),
        )
    except (AttributeError, TypeError, ValueError) as err:
        raise BagError(f"not a QoS profile: {profile!r} ({err})") from err


def _latched_qos() -> Any:
    """RELIABLE + TRANSIENT_LOCAL, KEEP_LAST 1 (the matcher's latched outputs) as a rosbags
    ``Qos``, through :func:`qos_from_profile` (policies by name, durations zero)."""
    from types import SimpleNamespace

    return qos_from_profile(
        SimpleNamespace(
            history="KEEP_LAST",
            depth=1,
            reliability="RELIABLE",
            durability="TRANSIENT_LOCAL",
            deadline=0,
            lifespan=0,
            liveliness="AUTOMATIC",
            liveliness_lease_duration=0,
            avoid_ros_namespace_conventions=False,
        )
    )
