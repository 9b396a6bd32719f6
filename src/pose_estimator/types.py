"""Result types of the pose estimator (camera frame, millimetres)."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from itertools import repeat

import numpy as np
from numpy.typing import NDArray

from fiducial_detector.types import FiducialDetection


@dataclass(frozen=True, slots=True, eq=False)
class FiducialPose:
    """3-D pose of one fiducial in the camera frame (x right, y down, z forward; millimetres).

    Attributes
    ----------
    code : int
        Code number of the fiducial.
    position_mm : (3,) ndarray
        Centre of the printed fiducial.
    normal : (3,) ndarray
        Unit normal of the printed face, pointing out of the face (towards the camera side).
    covariance_mm2 : (3, 3) ndarray
        Covariance of ``position_mm``.
    detection : FiducialDetection or None
        The detection it was estimated from (None for fused or synthetic poses).
    n_frames : int
        Number of frames fused into this pose.
    systematic_mm2 : (3, 3) ndarray or None
        Covariance of the position's systematic error, beside ``covariance_mm2`` (the scatter
        from image to image, which the matcher weighs by and fusion averages down): the error
        a known bias of its pose circle's fit makes (``Ellipse.systematic_px``), the same in
        every image of the scene, so neither fusing frames nor a displacement between two
        states fitted alike reduces it. None: no known bias.
    axis : (3,) ndarray or None
        Unit vector of the printed target's +x axis in the camera frame, in the fiducial's
        plane (orthogonal to ``normal``): the line on which the coding track's sector 0 starts
        (its boundary with sector 15), sectors running counter-clockwise about ``normal``. With
        the normal it fixes the fiducial's full orientation (:attr:`frame`), spin included,
        which the circle alone leaves free (:mod:`pose_estimator.orientation`). None where it
        was not measured (no code read, synthetic poses).
    """

    code: int
    position_mm: NDArray[np.float64]
    normal: NDArray[np.float64]
    covariance_mm2: NDArray[np.float64]
    detection: FiducialDetection | None = None
    n_frames: int = 1
    systematic_mm2: NDArray[np.float64] | None = None
    axis: NDArray[np.float64] | None = None

    @property
    def frame(self) -> NDArray[np.float64] | None:
        """The printed target's frame in the camera frame, ``(3, 3)`` with columns ``axis``,
        ``normal x axis`` (the printed +y) and ``normal`` (the target frame's +z, out of the
        face), or None without an axis."""
        if self.axis is None:
            return None
        n = np.asarray(self.normal, dtype=np.float64)
        a = np.asarray(self.axis, dtype=np.float64)
        return np.column_stack([a, np.cross(n, a), n])

    @property
    def sigma_mm(self) -> NDArray[np.float64]:
        """Standard deviations of x, y and z, mm (the scatter, ``covariance_mm2``)."""
        return np.sqrt(np.clip(np.diag(self.covariance_mm2), 0.0, None))

    @property
    def systematic_sigma_mm(self) -> NDArray[np.float64]:
        """Standard deviations of the systematic error of x, y and z, mm (0: none known)."""
        if self.systematic_mm2 is None:
            return np.zeros(3)
        return np.sqrt(np.clip(np.diag(self.systematic_mm2), 0.0, None))

    @classmethod
    def from_rows(
        cls,
        codes: Iterable[int],
        positions_mm: Iterable[NDArray[np.float64]],
        normals: Iterable[NDArray[np.float64]],
        covariances_mm2: Iterable[NDArray[np.float64]],
        detections: Iterable[FiducialDetection | None],
        systematic_mm2: Iterable[NDArray[np.float64] | None] | None = None,
        axes: Iterable[NDArray[np.float64] | None] | None = None,
    ) -> list[FiducialPose]:
        """Single-frame poses, one per item of the parallel iterables (as the constructor makes
        them, ``n_frames = 1``; ``systematic_mm2`` None: no pose has a known bias; ``axes``
        None: no pose has an axis).

        The estimator makes hundreds per frame; the generated ``__init__`` of a frozen dataclass
        costs a slow ``object.__setattr__`` call per field, so the slots are filled directly, one
        field at a time over all poses by ``map`` (no Python-level loop per pose).
        """
        columns: dict[str, list[object]] = {
            "code": list(codes),
            "position_mm": list(positions_mm),
            "normal": list(normals),
            "covariance_mm2": list(covariances_mm2),
            "detection": list(detections),
        }
        if systematic_mm2 is not None:
            columns["systematic_mm2"] = list(systematic_mm2)
        if axes is not None:
            columns["axis"] = list(axes)
        n = len(columns["code"])
        if any(len(values) != n for values in columns.values()):
            sizes = {name: len(values) for name, values in columns.items()}
            raise ValueError(f"from_rows needs parallel iterables of one length, got {sizes}")
        out: list[FiducialPose] = list(map(object.__new__, repeat(cls, n)))
        columns["n_frames"] = [1] * n
        columns.setdefault("systematic_mm2", [None] * n)
        columns.setdefault("axis", [None] * n)
        for name, values in columns.items():
            _consume(map(getattr(cls, name).__set__, out, values))
        return out


#: Runs an iterator to exhaustion, keeping nothing.
_consume: Callable[[Iterable[object]], None] = deque[object](maxlen=0).extend
