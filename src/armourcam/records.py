"""The one PointCloud2 record codec, driven by the definitions in ``msg/``.

Custom ``.msg`` files cannot be compiled for rclpy here, so per-frame arrays (detections, poses,
displacements, unit motions) travel on live topics as ``sensor_msgs/PointCloud2`` rows whose
``PointField`` list is generated from the project's record definitions, and bags register the very
same definitions with rosbags. This module is rclpy-free: nodes, bag tools and tests share it.

API summary
-----------
Definitions (``msg/*.msg``, shipped inside the package as ``armourcam/msg``; the repository's
top-level ``msg`` is a symlink to it):

- :data:`MSG_DIR`, :data:`PACKAGE` (``"armourcam_msgs"``), :func:`definition_names`,
  :func:`definition_text`, :func:`msgtype` (``"armourcam_msgs/msg/Name"``), :func:`typesdict`
  (all definitions parsed for ``rosbags`` ``Typestore.register``), :func:`constants`.
- :func:`layout` -> :class:`RecordLayout`: numpy structured ``dtype`` (little-endian, naturally
  aligned), ``point_step`` and the generated :class:`PointFieldSpec` list of a per-row record
  (``FiducialDetectionRecord``, ``FiducialPoseRecord``, ``DisplacementRecord``,
  ``UnitMotionRecord``). :func:`identify` names the record a field list carries.

Codec (bytes level, no message classes):

- :func:`encode` ``(name, records) -> EncodedCloud(fields, point_step, data, width)`` where
  ``records`` is a structured array or a sequence of mappings.
- :func:`decode` ``(name, fields, point_step, data, width, ...) -> structured array`` (validates
  the fields against the definition; the cloud's own offsets and byte order are honoured).
- :func:`to_pointcloud2` / :func:`from_pointcloud2`: build or read a ``sensor_msgs/PointCloud2``
  message object by duck typing (rclpy's and rosbags' classes alike).

Domain converters (round trip exact for every stored field):

- :func:`detections_to_records` / :func:`records_to_detections` (``FiducialDetection``)
- :func:`poses_to_records` / :func:`records_to_poses` (``FiducialPose``)
- :func:`rows_to_records` / :func:`records_to_rows`: any record from/to plain dicts (used for
  displacements and unit motions); :func:`covariance_to_upper` / :func:`upper_to_covariance`.

Errors: :class:`RecordError` (a ``ValueError``) names the record and what does not match.

Conventions: pixels ``(u, v)`` = (column, row) with pixel centres at integer coordinates; 3-D
quantities in the camera's optical frame (OpenCV: x right, y down, z forward), millimetres. Each
field's unit and frame is documented in its ``.msg`` file.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from fiducial_detector.types import Ellipse, FiducialDetection
from pose_estimator.camera import CameraModel
from pose_estimator.estimate import estimate_ellipses
from pose_estimator.types import FiducialPose

MSG_DIR = Path(__file__).resolve().parent / "msg"
"""Directory of the ``.msg`` definitions (package data; the repo's top-level ``msg`` links here)."""

PACKAGE = "armourcam_msgs"
"""ROS package name under which the definitions are registered in bags."""

# sensor_msgs/PointField datatype constants (PointField.INT8 ... PointField.FLOAT64).
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)

_POINTFIELD_OF: dict[str, tuple[int, str]] = {
    # msg primitive -> (PointField datatype, numpy little-endian dtype)
    "int8": (INT8, "<i1"),
    "uint8": (UINT8, "<u1"),
    "byte": (UINT8, "<u1"),
    "char": (UINT8, "<u1"),
    "bool": (UINT8, "<u1"),
    "int16": (INT16, "<i2"),
    "uint16": (UINT16, "<u2"),
    "int32": (INT32, "<i4"),
    "uint32": (UINT32, "<u4"),
    "float32": (FLOAT32, "<f4"),
    "float64": (FLOAT64, "<f8"),
}
_NUMPY_OF_DATATYPE = {INT8: "i1", UINT8: "u1", INT16: "i2", UINT16: "u2", INT32: "i4"}
_NUMPY_OF_DATATYPE.update({UINT32: "u4", FLOAT32: "f4", FLOAT64: "f8"})
_DATATYPE_NAME = {INT8: "INT8", UINT8: "UINT8", INT16: "INT16", UINT16: "UINT16"}
_DATATYPE_NAME.update({INT32: "INT32", UINT32: "UINT32", FLOAT32: "FLOAT32", FLOAT64: "FLOAT64"})


class RecordError(ValueError):
    """A record definition, a record value or a PointCloud2 does not match ``msg/``."""


@dataclass(frozen=True, slots=True)
class PointFieldSpec:
    """One ``sensor_msgs/PointField``: ``name``, byte ``offset``, ``datatype``, ``count``."""

    name: str
    offset: int
    datatype: int
    count: int


@dataclass(frozen=True, slots=True)
class FieldSpec:
    """One field of a record definition.

    Attributes
    ----------
    name : str
    type : str
        The msg primitive (``"float64"``, ``"uint8"`` ...).
    count : int
        1 for a scalar, N for a fixed-size array ``type[N]``.
    comment : str
        The definition's trailing comment (unit and frame).
    """

    name: str
    type: str
    count: int
    comment: str


@dataclass(frozen=True, slots=True, eq=False)
class RecordLayout:
    """Binary layout of one per-row record generated from its ``.msg`` definition.

    Attributes
    ----------
    name : str
        Definition name, e.g. ``"FiducialPoseRecord"``.
    fields : tuple of FieldSpec
        The definition's fields in order.
    dtype : numpy.dtype
        Little-endian structured dtype with natural alignment; ``dtype.itemsize == point_step``.
        Array fields have subarray shape ``(count,)``.
    point_fields : tuple of PointFieldSpec
        The generated ``sensor_msgs/PointField`` list.
    point_step : int
        Bytes per row.
    constants : dict
        The definition's constants (``{"DESIGN_DOT": 0, ...}``).
    """

    name: str
    fields: tuple[FieldSpec, ...]
    dtype: np.dtype[Any]
    point_fields: tuple[PointFieldSpec, ...]
    point_step: int
    constants: dict[str, Any]

    @property
    def field_names(self) -> tuple[str, ...]:
        """Names of the fields in definition order."""
        return tuple(f.name for f in self.fields)

    def empty(self, n: int = 0) -> NDArray[Any]:
        """A zero-filled (float fields NaN) structured array of ``n`` records."""
        out = np.zeros(n, dtype=self.dtype)
        for f in self.fields:
            if f.type.startswith("float"):
                out[f.name] = np.nan
        return out


class EncodedCloud(NamedTuple):
    """The PointCloud2 payload of ``width`` records (``height`` is 1, little-endian, dense)."""

    fields: tuple[PointFieldSpec, ...]
    point_step: int
    data: bytes
    width: int


# --------------------------------------------------------------------------------------------
# Definitions


def definition_names() -> list[str]:
    """Names of all definitions in :data:`MSG_DIR`, sorted."""
    return sorted(p.stem for p in MSG_DIR.glob("*.msg"))


@functools.cache
def definition_text(name: str) -> str:
    """Text of ``msg/<name>.msg``.

    Raises
    ------
    RecordError
        If there is no such definition.
    """
    path = MSG_DIR / f"{name}.msg"
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RecordError(
            f"no record definition {name!r} in {MSG_DIR}; known: {definition_names()}"
        ) from None


def msgtype(name: str) -> str:
    """Full ROS 2 type name of a definition: ``"armourcam_msgs/msg/<name>"``."""
    return f"{PACKAGE}/msg/{name}"


@functools.cache
def _parsed(name: str) -> tuple[list[tuple[str, str, Any]], list[tuple[str, Any]]]:
    from rosbags.typesys import get_types_from_msg
    from rosbags.typesys.base import TypesysError

    try:
        types = get_types_from_msg(definition_text(name), msgtype(name))
    except TypesysError as err:
        raise RecordError(f"cannot parse msg/{name}.msg: {err}") from err
    consts, fields = types[msgtype(name)]
    return list(consts), list(fields)


def typesdict() -> dict[str, Any]:
    """All definitions parsed for ``rosbags``: pass to ``typestore.register(...)``.

    Nested armourcam types are included, so one ``register`` call suffices (the typestore must
    already know ``std_msgs/msg/Header``, as every ROS 2 store does).
    """
    from rosbags.typesys import get_types_from_msg

    out: dict[str, Any] = {}
    for name in definition_names():
        out.update(get_types_from_msg(definition_text(name), msgtype(name)))
    return out


def constants(name: str) -> dict[str, Any]:
    """Constants of a definition, e.g. ``constants("DisplacementRecord")["LABEL_SAME_CODE"]``."""
    consts, _ = _parsed(name)
    return {cname: value for cname, _ctype, value in consts}


def _comments(name: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for line in definition_text(name).splitlines():
        body, _, comment = line.partition("#")
        parts = body.split()
        if len(parts) >= 2 and "=" not in body:
            out[parts[1]] = comment.strip()
    return out


@functools.cache
def layout(name: str) -> RecordLayout:
    """The binary layout of a per-row record definition.

    Every field must be a numeric primitive or a fixed-size array of one (PointField cannot carry
    strings, sequences, nested messages or 64-bit integers). Offsets follow natural alignment and
    ``point_step`` is padded to the largest alignment, as C structs and PCL clouds are laid out.

    Raises
    ------
    RecordError
        If the definition does not exist or has a field PointField cannot carry.
    """
    from rosbags.typesys.base import Nodetype

    consts, parsed = _parsed(name)
    comments = _comments(name)
    fields: list[FieldSpec] = []
    for fname, desc in parsed:
        node, detail = desc
        if node == Nodetype.BASE:
            ftype, count = detail[0], 1
        elif node == Nodetype.ARRAY and detail[0][0] == Nodetype.BASE:
            ftype, count = detail[0][1][0], int(detail[1])
        else:
            raise RecordError(
                f"{name}.{fname}: a per-row record may hold only numeric primitives and "
                f"fixed-size arrays of them (PointField cannot carry {desc!r})"
            )
        if ftype not in _POINTFIELD_OF:
            raise RecordError(
                f"{name}.{fname}: type {ftype!r} cannot travel as a PointField; "
                f"use one of {sorted(_POINTFIELD_OF)}"
            )
        fields.append(FieldSpec(fname, ftype, count, comments.get(fname, "")))
    if not fields:
        raise RecordError(f"{name} has no fields")

    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    pfs: list[PointFieldSpec] = []
    offset = 0
    max_align = 1
    for f in fields:
        datatype, npfmt = _POINTFIELD_OF[f.type]
        size = np.dtype(npfmt).itemsize
        offset = -(-offset // size) * size  # natural alignment
        max_align = max(max_align, size)
        names.append(f.name)
        formats.append(npfmt if f.count == 1 else (npfmt, (f.count,)))
        offsets.append(offset)
        pfs.append(PointFieldSpec(f.name, offset, datatype, f.count))
        offset += size * f.count
    point_step = -(-offset // max_align) * max_align
    dtype = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )
    return RecordLayout(
        name=name,
        fields=tuple(fields),
        dtype=dtype,
        point_fields=tuple(pfs),
        point_step=point_step,
        constants={cname: value for cname, _ctype, value in consts},
    )


def record_names() -> list[str]:
    """Names of the per-row record definitions (those :func:`layout` accepts), sorted."""
    return list(_record_names())


@functools.cache
def _record_names() -> tuple[str, ...]:
    out = []
    for name in definition_names():
        try:
            layout(name)
        except RecordError:
            continue
        out.append(name)
    return tuple(out)


def _field_specs(fields: Iterable[Any]) -> list[PointFieldSpec]:
    """Duck-type PointField-like objects (rclpy, rosbags, PointFieldSpec) into PointFieldSpec."""
    try:
        return [
            PointFieldSpec(str(f.name), int(f.offset), int(f.datatype), int(f.count))
            for f in fields
        ]
    except AttributeError as err:
        raise RecordError(f"not a PointField list: {err}") from err


def identify(fields: Iterable[Any]) -> str | None:
    """Name of the record definition whose fields (names, types, counts) a PointField list carries.

    Offsets are not compared. Returns None when no definition matches.
    """
    got = {(f.name, f.datatype, f.count) for f in _field_specs(fields)}
    for name in record_names():
        want = {(f.name, f.datatype, f.count) for f in layout(name).point_fields}
        if got == want:
            return name
    return None


# --------------------------------------------------------------------------------------------
# Codec


def rows_to_records(name: str, rows: Iterable[Mapping[str, Any]]) -> NDArray[Any]:
    """Build a structured array of ``name`` records from mappings of field name to value.

    Every field of the definition must be given (array fields as sequences of their length);
    unknown keys are refused, so a typo cannot silently drop data.

    Raises
    ------
    RecordError
        On a missing or unknown key, or a value of the wrong shape or out of the field's range.
    """
    lay = layout(name)
    rows = list(rows)
    out = np.zeros(len(rows), dtype=lay.dtype)
    if not rows:
        return out
    want = set(lay.field_names)
    for i, row in enumerate(rows):
        keys = set(row)
        if keys != want:
            missing, extra = sorted(want - keys), sorted(keys - want)
            raise RecordError(
                f"{name} row {i}: missing fields {missing}, unknown fields {extra}"
                if missing or extra
                else f"{name} row {i}: fields do not match"
            )
    for f in lay.fields:
        column = [row[f.name] for row in rows]
        _assign(out, f, column, name)
    return out


def _assign(out: NDArray[Any], f: FieldSpec, column: Any, name: str) -> None:
    target = out[f.name]
    try:
        values = np.asarray(column, dtype=np.float64 if f.type.startswith("float") else None)
    except (TypeError, ValueError) as err:
        raise RecordError(f"{name}.{f.name}: not numeric: {err}") from err
    if values.shape != target.shape:
        raise RecordError(
            f"{name}.{f.name}: expected shape {target.shape[1:] or 'scalar'} per record, "
            f"got values of shape {values.shape[1:] or 'scalar'}"
        )
    if not f.type.startswith("float") and values.size:
        if values.dtype.kind == "f" and not np.all(np.isfinite(values)):
            raise RecordError(f"{name}.{f.name}: {f.type} field given a non-finite value")
        info = np.iinfo(target.dtype)
        lo, hi = values.min(), values.max()
        if lo < info.min or hi > info.max or not np.array_equal(values, np.round(values)):
            bad = lo if lo < info.min else hi
            raise RecordError(f"{name}.{f.name}: value {bad} does not fit {f.type}")
    out[f.name] = values


def records_to_rows(records: NDArray[Any]) -> list[dict[str, Any]]:
    """Structured records as plain dicts (Python scalars, lists for array fields)."""
    names = records.dtype.names or ()
    return [{n: rec[n].tolist() for n in names} for rec in records]


def _as_records(name: str, records: Any) -> NDArray[Any]:
    lay = layout(name)
    if isinstance(records, np.ndarray) and records.dtype.names is not None:
        if records.ndim != 1:
            raise RecordError(f"{name}: records must be a 1-D structured array")
        if records.dtype == lay.dtype:
            return records
        if set(records.dtype.names) != set(lay.field_names):
            missing = sorted(set(lay.field_names) - set(records.dtype.names))
            extra = sorted(set(records.dtype.names) - set(lay.field_names))
            raise RecordError(f"{name}: missing fields {missing}, unknown fields {extra}")
        out = np.zeros(len(records), dtype=lay.dtype)
        for f in lay.fields:
            _assign(out, f, records[f.name], name)
        return out
    if isinstance(records, Sequence | Iterable) and not isinstance(records, str | bytes):
        return rows_to_records(name, records)
    raise RecordError(f"{name}: cannot encode {type(records).__name__} as records")


def encode(name: str, records: Any) -> EncodedCloud:
    """Serialise records of definition ``name`` into a PointCloud2 payload.

    Parameters
    ----------
    name : str
        Record definition, e.g. ``"FiducialPoseRecord"``.
    records : structured ndarray or sequence of mappings
        A 1-D structured array with exactly the definition's field names (any compatible dtypes),
        e.g. from :func:`poses_to_records`, or mappings accepted by :func:`rows_to_records`.

    Returns
    -------
    EncodedCloud
        ``fields`` (generated from the definition), ``point_step``, little-endian ``data`` of
        ``width * point_step`` bytes, ``width`` (number of records; ``height`` is 1).
    """
    recs = _as_records(name, records)
    lay = layout(name)
    return EncodedCloud(lay.point_fields, lay.point_step, recs.tobytes(), len(recs))


def _as_buffer(data: Any) -> NDArray[np.uint8]:
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data, dtype=np.uint8).reshape(-1)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        # A plain list of ints (rare: some message implementations) - still no Python loop.
        return np.asarray(data, dtype=np.uint8).reshape(-1)


def decode(
    name: str,
    fields: Iterable[Any],
    point_step: int,
    data: Any,
    width: int,
    height: int = 1,
    *,
    is_bigendian: bool = False,
    row_step: int | None = None,
    strict: bool = True,
) -> NDArray[Any]:
    """Read the records of definition ``name`` from a PointCloud2 payload.

    Parameters
    ----------
    name : str
        Record definition the cloud must carry.
    fields : iterable of PointField-like
        Objects with ``name``, ``offset``, ``datatype`` and ``count`` (rclpy or rosbags PointField,
        or :class:`PointFieldSpec`). Offsets may differ from the generated layout.
    point_step, width, height, row_step, is_bigendian
        As in ``sensor_msgs/PointCloud2`` (``row_step`` defaults to ``width * point_step``).
    data : bytes-like or uint8 array
        The cloud's ``data``.
    strict : bool
        When True (default) fields not in the definition are an error; when False they are ignored.

    Returns
    -------
    structured ndarray
        ``width * height`` records in :func:`layout`'s canonical dtype (a copy, native order).

    Raises
    ------
    RecordError
        If a field is missing, has another type or count, lies outside ``point_step``, or the data
        is shorter or longer than the header says.
    """
    lay = layout(name)
    specs = _field_specs(fields)
    by_name = {f.name: f for f in specs}
    if len(by_name) != len(specs):
        raise RecordError(f"{name}: PointCloud2 has duplicate field names")
    problems: list[str] = []
    for want in lay.point_fields:
        got = by_name.get(want.name)
        if got is None:
            problems.append(f"missing field {want.name!r}")
        elif (got.datatype, got.count) != (want.datatype, want.count):
            problems.append(
                f"field {want.name!r} is {_DATATYPE_NAME.get(got.datatype, got.datatype)}"
                f"[{got.count}], expected {_DATATYPE_NAME[want.datatype]}[{want.count}]"
            )
    extra = sorted(set(by_name) - set(lay.field_names))
    if strict and extra:
        problems.append(f"unknown fields {extra}")
    if problems:
        raise RecordError(f"PointCloud2 does not carry {name} records: " + "; ".join(problems))
    point_step, width, height = int(point_step), int(width), int(height)
    if width < 0 or height < 0 or point_step <= 0:
        raise RecordError(f"{name}: bad cloud size {width}x{height}, point_step {point_step}")
    for want in lay.point_fields:
        got = by_name[want.name]
        size = np.dtype(_NUMPY_OF_DATATYPE[want.datatype]).itemsize * want.count
        if got.offset < 0 or got.offset + size > point_step:
            raise RecordError(
                f"{name}: field {want.name!r} at offset {got.offset} (+{size} bytes) lies outside "
                f"point_step {point_step}"
            )
    row_step = width * point_step if row_step is None else int(row_step)
    if row_step < width * point_step:
        raise RecordError(f"{name}: row_step {row_step} < width * point_step {width * point_step}")
    buf = _as_buffer(data)
    if buf.size != row_step * height:
        raise RecordError(
            f"{name}: data has {buf.size} bytes, header says {height} rows of {row_step} bytes "
            f"({row_step * height})"
        )
    order = ">" if is_bigendian else "<"
    src_dtype = np.dtype(
        {
            "names": list(lay.field_names),
            "formats": [
                order + _NUMPY_OF_DATATYPE[p.datatype]
                if p.count == 1
                else (order + _NUMPY_OF_DATATYPE[p.datatype], (p.count,))
                for p in lay.point_fields
            ],
            "offsets": [by_name[n].offset for n in lay.field_names],
            "itemsize": point_step,
        }
    )
    out = np.zeros(width * height, dtype=lay.dtype)  # zeros: padding bytes are deterministic
    if width * height == 0:
        return out
    rows = buf.reshape(height, row_step)[:, : width * point_step]
    src = np.ascontiguousarray(rows).view(src_dtype).reshape(-1)
    for n in lay.field_names:
        out[n] = src[n]
    return out


def to_pointcloud2(
    msg_class: Any,
    field_class: Any,
    header: Any,
    name: str,
    records: Any,
) -> Any:
    """Build a ``sensor_msgs/PointCloud2`` message object carrying ``name`` records.

    Duck-typed: works with rclpy's ``sensor_msgs.msg.PointCloud2``/``PointField`` and with the
    classes of a rosbags typestore (``typestore.types["sensor_msgs/msg/PointCloud2"]``), which take
    ``data`` as a uint8 array instead of bytes.

    Parameters
    ----------
    msg_class, field_class
        The PointCloud2 and PointField message classes.
    header
        A ``std_msgs/Header`` instance of the same family (stamp and frame_id of the source image).
    name : str
        Record definition.
    records
        As for :func:`encode`.
    """
    enc = encode(name, records)
    rosbags_style = hasattr(msg_class, "__msgtype__")
    data: Any = np.frombuffer(enc.data, dtype=np.uint8) if rosbags_style else enc.data
    fields = [
        field_class(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
        for f in enc.fields
    ]
    return msg_class(
        header=header,
        height=1,
        width=enc.width,
        fields=fields,
        is_bigendian=False,
        point_step=enc.point_step,
        row_step=enc.point_step * enc.width,
        data=data,
        is_dense=True,
    )


def from_pointcloud2(msg: Any, name: str | None = None, *, strict: bool = True) -> NDArray[Any]:
    """Read the records of a ``sensor_msgs/PointCloud2`` message object (rclpy or rosbags).

    Parameters
    ----------
    msg
        The message (anything with PointCloud2's attributes).
    name : str, optional
        Record definition expected; identified from the fields when not given.

    Raises
    ------
    RecordError
        If the cloud does not carry the expected (or any known) record.
    """
    if name is None:
        name = identify(msg.fields)
        if name is None:
            got = [f.name for f in _field_specs(msg.fields)]
            raise RecordError(f"PointCloud2 fields {got} match no record definition in msg/")
    return decode(
        name,
        msg.fields,
        msg.point_step,
        msg.data,
        msg.width,
        msg.height,
        is_bigendian=bool(msg.is_bigendian),
        row_step=msg.row_step,
        strict=strict,
    )


def pointfield_class_for(msg_class: Any) -> Any:
    """The PointField class that belongs with a PointCloud2 class (rclpy only; rosbags users
    take ``typestore.types["sensor_msgs/msg/PointField"]``)."""
    module = importlib.import_module(msg_class.__module__.rsplit(".", 1)[0])
    return module.PointField


# --------------------------------------------------------------------------------------------
# Covariance packing


def covariance_to_upper(cov: Any) -> NDArray[np.float64]:
    """Upper triangle, row by row, of a symmetric ``(n, n)`` (or stacked ``(..., n, n)``) matrix."""
    c = np.asarray(cov, dtype=np.float64)
    n = c.shape[-1]
    if c.ndim < 2 or c.shape[-2] != n:
        raise RecordError(f"covariance must be square, got shape {c.shape}")
    iu = np.triu_indices(n)
    return c[..., iu[0], iu[1]]


def upper_to_covariance(upper: Any, n: int) -> NDArray[np.float64]:
    """Inverse of :func:`covariance_to_upper`: the symmetric ``(..., n, n)`` matrix."""
    u = np.asarray(upper, dtype=np.float64)
    if u.shape[-1] != n * (n + 1) // 2:
        raise RecordError(f"{u.shape[-1]} upper-triangle terms do not make a {n}x{n} matrix")
    out = np.zeros((*u.shape[:-1], n, n))
    iu = np.triu_indices(n)
    out[..., iu[0], iu[1]] = u
    out[..., iu[1], iu[0]] = u
    return out


# --------------------------------------------------------------------------------------------
# Domain converters

DETECTION = "FiducialDetectionRecord"
POSE = "FiducialPoseRecord"
DISPLACEMENT = "DisplacementRecord"
UNIT_MOTION = "UnitMotionRecord"


def design_ids() -> dict[str, int]:
    """Design name -> ``FiducialDetectionRecord.design`` id, from the ``DESIGN_*`` constants."""
    return {
        k.removeprefix("DESIGN_").lower(): int(v)
        for k, v in constants(DETECTION).items()
        if k.startswith("DESIGN_")
    }


def _int_column(name: str, field: str, values: list[int], lo: int, hi: int) -> NDArray[np.int64]:
    arr = np.asarray(values, dtype=np.int64).reshape(-1)
    bad = np.flatnonzero((arr < lo) | (arr > hi))
    if bad.size:
        raise RecordError(f"{name} {bad[0]}: {field} {arr[bad[0]]} outside {lo}..{hi}")
    return arr


#: The per-ellipse fields of a detection record, in ``Ellipse``'s order (its covariance apart).
_ELLIPSE_FIELDS = (
    "ellipse_u",
    "ellipse_v",
    "semi_major",
    "semi_minor",
    "angle",
    "radius",
    "rms_residual",
    "systematic_px",
)


def detections_to_records(detections: Sequence[FiducialDetection]) -> NDArray[Any]:
    """``FiducialDetection`` list -> ``FiducialDetectionRecord`` structured array.

    Stored: code, hamming, design, centre, contrast, rotation and every ellipse (centre, axes,
    angle, nominal radius, RMS residual, systematic error, covariance upper triangle). Not
    stored: ``extra``.
    Column-wise (no per-record numpy access): about 2 ms for 400 ring detections.

    Raises
    ------
    RecordError
        For an unknown design, more ellipses than the record has slots, or out-of-range integers.
    """
    lay = layout(DETECTION)
    slots = int(lay.constants["MAX_ELLIPSES"])
    ids = design_ids()
    n = len(detections)
    out = lay.empty(n)
    if n == 0:
        return out
    # Per-ellipse values gathered into (n, slots) tables, NaN where a slot is unused.
    table = np.full((len(_ELLIPSE_FIELDS), n, slots), np.nan)
    covs = np.full((n, slots, 5, 5), np.nan)
    n_ell: list[int] = []
    designs: list[int] = []
    for i, det in enumerate(detections):
        if det.design not in ids:
            raise RecordError(f"detection {i}: unknown design {det.design!r}; known {sorted(ids)}")
        k = len(det.ellipses)
        if not 1 <= k <= slots:
            raise RecordError(f"detection {i}: {k} ellipses, the record holds 1..{slots}")
        designs.append(ids[det.design])
        n_ell.append(k)
        table[:, i, :k] = [
            [e.center_px[0] for e in det.ellipses],
            [e.center_px[1] for e in det.ellipses],
            [e.semi_major for e in det.ellipses],
            [e.semi_minor for e in det.ellipses],
            [e.angle for e in det.ellipses],
            [e.radius for e in det.ellipses],
            [e.rms_residual for e in det.ellipses],
            [e.systematic_px for e in det.ellipses],
        ]
        for j, e in enumerate(det.ellipses):
            covs[i, j] = e.covariance
    out["code"] = _int_column("detection", "code", [d.code for d in detections], 0, 2**32 - 1)
    out["hamming"] = _int_column("detection", "hamming", [d.hamming for d in detections], 0, 255)
    out["design"] = designs
    out["n_ellipses"] = n_ell
    out["u"] = [d.center_px[0] for d in detections]
    out["v"] = [d.center_px[1] for d in detections]
    out["contrast"] = [d.contrast for d in detections]
    out["rotation"] = [d.rotation for d in detections]
    for row, name in enumerate(_ELLIPSE_FIELDS):
        out[name] = table[row]
    out["ellipse_covariance"] = covariance_to_upper(covs).reshape(n, slots * 15)
    return out


def records_to_detections(records: NDArray[Any]) -> list[FiducialDetection]:
    """``FiducialDetectionRecord`` structured array -> ``FiducialDetection`` list (``extra`` empty).

    Raises
    ------
    RecordError
        For an unknown design id or an ``n_ellipses`` outside ``1..MAX_ELLIPSES``.
    """
    recs, n_ell, design = _checked_detections(records)
    slots = int(layout(DETECTION).constants["MAX_ELLIPSES"])
    names = {v: k for k, v in design_ids().items()}
    covs = upper_to_covariance(recs["ellipse_covariance"].reshape(len(recs), slots, 15), 5)
    per_slot = zip(*(recs[name].tolist() for name in _ELLIPSE_FIELDS), strict=True)
    head = zip(
        *(recs[name].tolist() for name in ("code", "hamming", "u", "v", "contrast", "rotation")),
        strict=True,
    )
    out: list[FiducialDetection] = []
    for i, (k, slot, (code, hamming, u, v, contrast, rotation)) in enumerate(
        zip(n_ell.tolist(), per_slot, head, strict=True)
    ):
        eu, ev, a, b, ang, rad, rms, sysm = slot
        ellipses = tuple(
            Ellipse((eu[j], ev[j]), a[j], b[j], ang[j], covs[i, j], rad[j], rms[j], sysm[j])
            for j in range(k)
        )
        out.append(
            FiducialDetection(code, hamming, (u, v), ellipses, contrast, names[design[i]], rotation)
        )
    return out


def _checked_detections(records: Any) -> tuple[NDArray[Any], NDArray[np.int64], list[int]]:
    """Detection records with valid ``n_ellipses`` and design ids: the records, ``n_ellipses``
    and the design ids (:class:`RecordError` naming the first bad row otherwise)."""
    recs = _as_records(DETECTION, records)
    slots = int(layout(DETECTION).constants["MAX_ELLIPSES"])
    n_ell = recs["n_ellipses"].astype(np.int64)
    bad = np.flatnonzero((n_ell < 1) | (n_ell > slots))
    if bad.size:
        raise RecordError(
            f"{DETECTION} row {bad[0]}: n_ellipses {n_ell[bad[0]]} outside 1..{slots}"
        )
    design = recs["design"].astype(int).tolist()
    known = set(design_ids().values())
    unknown = [i for i, d in enumerate(design) if d not in known]
    if unknown:
        raise RecordError(f"{DETECTION} row {unknown[0]}: unknown design id {design[unknown[0]]}")
    return recs, n_ell, design


def detection_ellipse_columns(
    records: NDArray[Any],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``FiducialDetectionRecord`` rows -> the ellipse columns of
    :func:`pose_estimator.estimate_ellipses`, without detection objects: ``(u, v, semi_major,
    semi_minor, angle, radius, systematic_px)`` ``(7, K, N)`` and covariances ``(5, 5, K, N)``,
    NaN beyond each row's ``n_ellipses`` (``K`` is the largest).

    Raises
    ------
    RecordError
        For an unknown design id or an ``n_ellipses`` outside ``1..MAX_ELLIPSES``.
    """
    recs, n_ell, _ = _checked_detections(records)
    kc = int(n_ell.max()) if len(recs) else 1
    # The columns of pose_estimator.detection_columns: the ellipse fields but the RMS residual.
    names = [name for name in _ELLIPSE_FIELDS if name != "rms_residual"]
    values = np.stack([np.asarray(recs[name][:, :kc], dtype=np.float64).T for name in names])
    slots = int(layout(DETECTION).constants["MAX_ELLIPSES"])
    upper = recs["ellipse_covariance"].reshape(len(recs), slots, 15)[:, :kc]
    covs = upper_to_covariance(upper, 5).transpose(2, 3, 1, 0)
    missing = np.arange(kc)[:, None] >= n_ell[None, :]
    values[:, missing] = np.nan
    covs[:, :, missing] = np.nan
    return values, np.ascontiguousarray(covs)


def pose_columns_to_records(
    code: Any,
    position_mm: Any,
    normal: Any,
    covariance_mm2: Any,
    center_px: Any,
    detection_index: Any,
    n_frames: Any = 1,
    systematic_mm2: Any = None,
    axis: Any = None,
) -> NDArray[Any]:
    """Pose columns -> ``FiducialPoseRecord`` structured array (the shared body of
    :func:`poses_to_records`, and the pose node's path without pose objects).

    Parameters
    ----------
    code : (N,) integers
    position_mm, normal : (N, 3) arrays
    covariance_mm2 : (N, 3, 3) array
    center_px : (N, 2) array
        The detection's centre ``(u, v)`` each pose came from (NaN: none).
    detection_index : (N,) integers
        Row of that detection in its frame's detection records (-1: none).
    n_frames : integer or (N,) integers
        Frames fused into each pose.
    systematic_mm2 : (N, 3, 3) array, optional
        Covariances of the positions' systematic errors (``FiducialPose.systematic_mm2``;
        zeros or None: none).
    axis : (N, 3) array, optional
        Printed +x axes (``FiducialPose.axis``; NaN rows or None: not measured).
    """
    lay = layout(POSE)
    try:
        pos = np.asarray(position_mm, dtype=np.float64).reshape(-1, 3)
        n = len(pos)
        nrm = np.asarray(normal, dtype=np.float64).reshape(n, 3)
        cov = np.asarray(covariance_mm2, dtype=np.float64).reshape(n, 3, 3)
        uv = np.asarray(center_px, dtype=np.float64).reshape(n, 2)
        bias = (
            np.zeros((n, 3, 3))
            if systematic_mm2 is None
            else np.asarray(systematic_mm2, dtype=np.float64).reshape(n, 3, 3)
        )
        axes = (
            np.full((n, 3), np.nan)
            if axis is None
            else np.asarray(axis, dtype=np.float64).reshape(n, 3)
        )
    except ValueError as err:
        raise RecordError(f"poses with malformed position/normal/covariance: {err}") from err
    out = lay.empty(n)
    if n == 0:
        return out
    out["x"], out["y"], out["z"] = pos.T
    out["nx"], out["ny"], out["nz"] = nrm.T
    out["ax"], out["ay"], out["az"] = axes.T
    out["covariance"] = covariance_to_upper(cov)
    out["systematic"] = covariance_to_upper(bias)
    out["code"] = _int_column("pose", "code", np.asarray(code).tolist(), 0, 2**32 - 1)
    frames = np.broadcast_to(np.asarray(n_frames), (n,)).tolist()
    out["n_frames"] = _int_column("pose", "n_frames", frames, 1, 2**32 - 1)
    out["detection_index"] = np.asarray(detection_index).reshape(n)
    out["u"], out["v"] = uv.T
    return out


def estimate_pose_records(
    detection_records: NDArray[Any], camera: CameraModel, diameter_mm: float
) -> NDArray[Any]:
    """One frame's ``FiducialDetectionRecord`` rows -> its ``FiducialPoseRecord`` rows, through
    :func:`pose_estimator.estimate_ellipses` and columns only (no per-fiducial objects): the
    pose node's stage. The same rows as :func:`poses_to_records` of :func:`pose_estimator.estimate`
    on the decoded detections; ``detection_index`` is each pose's detection row.

    Raises
    ------
    RecordError
        For malformed detection records (see :func:`detection_ellipse_columns`).
    CalibrationError
        If a detection lies outside the camera's image (:meth:`CameraModel.check_pixels`).
    """
    recs = _as_records(DETECTION, detection_records)
    values, covs = detection_ellipse_columns(recs)
    camera.check_pixels(recs["u"], recs["v"])
    result = estimate_ellipses(
        values, covs, 0.5 * float(diameter_mm), camera, np.asarray(recs["rotation"], np.float64)
    )
    keep = np.flatnonzero(result.valid)
    return pose_columns_to_records(
        recs["code"][keep],
        result.position_mm[keep],
        result.normal[keep],
        result.covariance_mm2[keep],
        np.column_stack([recs["u"][keep], recs["v"][keep]]),
        keep,
        systematic_mm2=None if result.systematic_mm2 is None else result.systematic_mm2[keep],
        axis=None if result.axis is None else result.axis[keep],
    )


def poses_to_records(
    poses: Sequence[FiducialPose], detections: Sequence[FiducialDetection] | None = None
) -> NDArray[Any]:
    """``FiducialPose`` list -> ``FiducialPoseRecord`` structured array.

    Parameters
    ----------
    poses
        The poses (camera frame, mm).
    detections
        The frame's detections, in the order they are published; a pose whose ``detection`` is
        one of them (by identity) records its row in ``detection_index``, else -1.

    Stored: code, position, normal, printed axis (NaN without one), covariance and systematic
    covariance (upper triangles; zeros for a pose without a known bias), n_frames, the
    detection's centre ``(u, v)`` (NaN without a detection) and ``detection_index``.
    """
    if not poses:
        return layout(POSE).empty(0)
    try:
        pos = np.array([np.reshape(p.position_mm, 3) for p in poses], dtype=np.float64)
        nrm = np.array([np.reshape(p.normal, 3) for p in poses], dtype=np.float64)
        cov = np.array([np.reshape(p.covariance_mm2, (3, 3)) for p in poses], dtype=np.float64)
    except ValueError as err:
        raise RecordError(f"poses with malformed position/normal/covariance: {err}") from err
    index_of = {id(d): k for k, d in enumerate(detections or ())}
    index = [index_of.get(id(p.detection), -1) if p.detection is not None else -1 for p in poses]
    nan = (np.nan, np.nan)
    uv = [p.detection.center_px if p.detection is not None else nan for p in poses]
    zero = np.zeros((3, 3))
    bias = [zero if p.systematic_mm2 is None else p.systematic_mm2 for p in poses]
    nan3 = np.full(3, np.nan)
    axes = [nan3 if p.axis is None else np.reshape(p.axis, 3) for p in poses]
    return pose_columns_to_records(
        [p.code for p in poses], pos, nrm, cov, uv, index, [p.n_frames for p in poses], bias, axes
    )


def records_to_poses(
    records: NDArray[Any], detections: Sequence[FiducialDetection] | None = None
) -> list[FiducialPose]:
    """``FiducialPoseRecord`` structured array -> ``FiducialPose`` list.

    ``detection`` is ``detections[detection_index]`` when ``detections`` is given and the index is
    valid, else None (the centre ``(u, v)`` stays available in the records).

    Raises
    ------
    RecordError
        If a ``detection_index`` points outside the given ``detections``.
    """
    recs = _as_records(POSE, records)
    covs = upper_to_covariance(recs["covariance"], 3)
    bias = upper_to_covariance(recs["systematic"], 3)
    biased = np.any(bias != 0.0, axis=(1, 2)).tolist()
    pos = np.column_stack([recs["x"], recs["y"], recs["z"]]).astype(np.float64)
    nrm = np.column_stack([recs["nx"], recs["ny"], recs["nz"]]).astype(np.float64)
    axes = np.column_stack([recs["ax"], recs["ay"], recs["az"]]).astype(np.float64)
    has_axis = np.all(np.isfinite(axes), axis=1).tolist()
    idx = recs["detection_index"].tolist()
    if detections is not None:
        bad = [i for i, k in enumerate(idx) if k >= len(detections)]
        if bad:
            raise RecordError(
                f"{POSE} row {bad[0]}: detection_index {idx[bad[0]]} but only "
                f"{len(detections)} detections"
            )
    codes, frames = recs["code"].tolist(), recs["n_frames"].tolist()
    return [
        FiducialPose(
            code=codes[i],
            position_mm=pos[i].copy(),
            normal=nrm[i].copy(),
            covariance_mm2=covs[i].copy(),
            detection=detections[idx[i]] if detections is not None and idx[i] >= 0 else None,
            n_frames=frames[i],
            systematic_mm2=bias[i].copy() if biased[i] else None,
            axis=axes[i].copy() if has_axis[i] else None,
        )
        for i in range(len(recs))
    ]
