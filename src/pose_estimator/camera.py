"""Pinhole camera with plumb_bob or rational_polynomial lens distortion.

Frames and conventions: the camera frame is OpenCV's (x right, y down, z forward, millimetres);
pixel centres are at integer coordinates. Distortion coefficients follow ROS ``CameraInfo.d`` and
OpenCV: plumb_bob ``(k1, k2, p1, p2, k3)``, rational_polynomial
``(k1, k2, p1, p2, k3, k4, k5, k6)``.
The camera is loaded from a ``sensor_msgs/CameraInfo``'s fields or from the camera_calibration YAML
file written by ROS ``camera_calibration``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import CalibrationError
from .yaml_file import YamlFileError, load_yaml

_COEFF_COUNT = {"plumb_bob": 5, "rational_polynomial": 8}


@dataclass(frozen=True, slots=True, eq=False)
class CameraModel:
    """Intrinsics of one camera.

    Attributes
    ----------
    width, height : int
        Image size in pixels the calibration belongs to.
    K : (3, 3) ndarray
        Camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``.
    distortion_model : {"plumb_bob", "rational_polynomial"}
    D : (n,) ndarray
        Distortion coefficients (all zero for an ideal pinhole).
    """

    width: int
    height: int
    K: NDArray[np.float64]
    distortion_model: str
    D: NDArray[np.float64]

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"image size must be positive, got {self.width}x{self.height}")
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CalibrationError(f"camera matrix must be a finite 3x3 matrix, got {K.tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0 or K[1, 0] or K[2, 0] or K[2, 1]:
            raise CalibrationError(f"camera matrix is not a pinhole matrix: {K.tolist()}")
        if self.distortion_model not in _COEFF_COUNT:
            raise CalibrationError(
                f"unsupported distortion model {self.distortion_model!r}; "
                f"supported: {sorted(_COEFF_COUNT)}"
            )
        D = np.asarray(self.D, dtype=np.float64).ravel()
        n = _COEFF_COUNT[self.distortion_model]
        if D.size == 0:
            D = np.zeros(n)
        if D.size != n or not np.all(np.isfinite(D)):
            raise CalibrationError(
                f"{self.distortion_model} needs {n} finite distortion coefficients, "
                f"got {D.tolist()}"
            )
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "D", D)

    @classmethod
    def ideal(
        cls, width: int, height: int, focal_px: float, center: tuple[float, float] | None = None
    ) -> CameraModel:
        """Distortion-free camera with square pixels and the principal point at ``center``
        (default: the image centre, ``((width - 1) / 2, (height - 1) / 2)``)."""
        cx, cy = center if center is not None else ((width - 1) / 2.0, (height - 1) / 2.0)
        K = np.array([[focal_px, 0.0, cx], [0.0, focal_px, cy], [0.0, 0.0, 1.0]])
        return cls(width, height, K, "plumb_bob", np.zeros(5))

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return bool(np.any(self.D != 0.0))

    def check_image_size(self, width: int, height: int) -> None:
        """Raise :class:`CalibrationError` unless a ``width x height`` image fits this camera."""
        if (width, height) != (self.width, self.height):
            raise CalibrationError(
                f"image is {width}x{height} but the calibration is for {self.width}x{self.height}"
            )

    def check_pixels(self, u: ArrayLike, v: ArrayLike) -> None:
        """Raise :class:`CalibrationError` if any pixel ``(u, v)`` (pixel centres at integer
        coordinates) lies outside this camera's image: detections from an image of another size
        than the calibration's (a camera info that does not belong to the camera) would be
        posed with the wrong principal point and focal length, silently."""
        uu = np.asarray(u, dtype=np.float64).ravel()
        vv = np.asarray(v, dtype=np.float64).ravel()
        outside = ~(
            (uu >= -0.5) & (uu <= self.width - 0.5) & (vv >= -0.5) & (vv <= self.height - 0.5)
        )
        if np.any(outside):
            i = int(np.argmax(outside))
            if not (np.isfinite(uu[i]) and np.isfinite(vv[i])):
                raise CalibrationError(f"detection at ({uu[i]}, {vv[i]}) px is not a pixel")
            raise CalibrationError(
                f"detection at ({uu[i]:.1f}, {vv[i]:.1f}) px lies outside the calibration's "
                f"{self.width}x{self.height} image: the calibration is not this camera's"
            )

    def project(self, points_mm: ArrayLike) -> NDArray[np.float64]:
        """Project camera-frame points to distorted pixel coordinates.

        Parameters
        ----------
        points_mm : (N, 3) array_like
            Points in the camera frame, ``z > 0``.

        Returns
        -------
        (N, 2) ndarray
            Pixel coordinates ``(u, v)``.
        """
        p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        if not self.has_distortion:
            uv = p[:, :2] / p[:, 2:3]
            return uv * np.diag(self.K)[:2] + self.K[:2, 2]
        proj, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), self.K, self.D)
        return np.asarray(proj, dtype=np.float64).reshape(-1, 2)

    def distort_normalized(self, xy: ArrayLike) -> NDArray[np.float64]:
        """Map ideal normalised coordinates ``(x/z, y/z)`` to distorted pixel coordinates."""
        n = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return self.project(np.column_stack([n, np.ones(len(n))]))

    def undistort_normalized(
        self, uv: ArrayLike, guess: ArrayLike | None = None
    ) -> NDArray[np.float64]:
        """Map distorted pixel coordinates to ideal normalised coordinates ``(x/z, y/z)``.

        Vectorised Newton iterations on the lens model (analytic Jacobian), converged to 1e-14
        (far below pixel noise), not OpenCV's default five fixed-point iterations; points where
        Newton does not converge fall back to OpenCV's iterative inverse. ``guess`` (``(N, 2)``
        normalised coordinates near the answer) only saves iterations: the converged result is
        the same.
        """
        return self._undistort_rows(uv, guess, pixels=False)

    def _undistort_rows(
        self, uv: ArrayLike, guess: ArrayLike | None, *, pixels: bool
    ) -> NDArray[np.float64]:
        """:meth:`undistort_components` on ``(N, 2)`` rows (and a guess of the same layout)."""
        px = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        start = None
        if guess is not None:
            g = np.asarray(guess, dtype=np.float64).reshape(-1, 2)
            start = (g[:, 0], g[:, 1])
        a, b = self.undistort_components(px[:, 0], px[:, 1], start, pixels=pixels)
        return np.column_stack([a, b])

    def undistort_components(
        self,
        u: NDArray[np.float64],
        v: NDArray[np.float64],
        guess: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
        *,
        pixels: bool = True,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """:meth:`undistort_pixels` (or, with ``pixels=False``, :meth:`undistort_normalized`)
        on coordinates given as two arrays of any (equal) shape, ``u`` and ``v``.

        Components in separate contiguous arrays let every Newton operation run over one long
        array, with no ``(N, 2)`` interleaving, for callers that keep points that way (the
        boundary samples of all fitted ellipses at once). ``guess`` is a pair of arrays of the
        same shape, in the unit of the result.
        """
        f0, f1 = float(self.K[0, 0]), float(self.K[1, 1])
        c0, c1 = float(self.K[0, 2]), float(self.K[1, 2])
        x0 = (np.asarray(u, dtype=np.float64) - c0) / f0
        y0 = (np.asarray(v, dtype=np.float64) - c1) / f1
        if not self.has_distortion:
            return (x0 * f0 + c0, y0 * f1 + c1) if pixels else (x0, y0)
        if guess is None:
            x, y = x0.copy(), y0.copy()
        elif pixels:
            x = (np.asarray(guess[0], dtype=np.float64) - c0) / f0
            y = (np.asarray(guess[1], dtype=np.float64) - c1) / f1
        else:
            x = np.array(guess[0], dtype=np.float64)
            y = np.array(guess[1], dtype=np.float64)
        x, y, resid = _newton_undistort(x0, y0, x, y, self.D)
        # The residual before the last step bounds the error after it (quadratic convergence).
        bad = ~(np.isfinite(x) & np.isfinite(y)) | ~(resid < 1e-9)
        if np.any(bad):
            px = np.column_stack([np.asarray(u)[bad], np.asarray(v)[bad]])
            fallback = self._undistort_opencv(px)
            x[bad], y[bad] = fallback[:, 0], fallback[:, 1]
        return (x * f0 + c0, y * f1 + c1) if pixels else (x, y)

    def undistortion_jacobian(
        self, u: NDArray[np.float64], v: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Ideal pixels ``u'``, ``v'`` of distorted ones ``u``, ``v`` (arrays of any shape, as
        :meth:`undistort_components`) and the Jacobian ``d(u', v') / d(u, v)`` there.

        The Jacobian is returned as ``(4, ...)``: entries ``(a00, a01, a10, a11)``, from the
        lens model's analytic Jacobian inverted at the ideal point (exact, no finite
        differences).
        """
        x, y = self.undistort_components(u, v, pixels=False)
        f0, f1 = float(self.K[0, 0]), float(self.K[1, 1])
        c0, c1 = float(self.K[0, 2]), float(self.K[1, 2])
        coeffs = _coefficients(self.D)
        xx, yy, xy = x * x, y * y, x * y
        rad, drad = _radial(xx + yy, coeffs)
        j11, j12, j22 = _jacobian(x, y, xx, yy, xy, rad, drad, coeffs)
        inv_det = 1.0 / (j11 * j22 - j12 * j12)
        # Normalised -> pixels on both sides: A_px = diag(f) J^-1 diag(f)^-1.
        A = np.stack([j22 * inv_det, -j12 * inv_det * (f0 / f1), -j12 * inv_det * (f1 / f0)])
        A = np.concatenate([A, (j11 * inv_det)[None]])
        return x * f0 + c0, y * f1 + c1, A

    def _undistort_opencv(self, px: NDArray[np.float64]) -> NDArray[np.float64]:
        """OpenCV's iterative inverse (fallback), normalised coordinates."""
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
        src = px.reshape(-1, 1, 2)
        # OpenCV 4 names the variant with termination criteria undistortPointsIter; OpenCV 5
        # folds the criteria into undistortPoints.
        iterate = getattr(cv2, "undistortPointsIter", None)
        if iterate is not None:
            out = iterate(src, self.K, self.D, None, None, criteria)
        else:
            out = cv2.undistortPoints(src, self.K, self.D, None, np.eye(3), np.eye(3), criteria)
        return np.asarray(out, dtype=np.float64).reshape(-1, 2)

    def undistort_pixels(
        self, uv: ArrayLike, guess: ArrayLike | None = None
    ) -> NDArray[np.float64]:
        """Map distorted pixels to the pixels an ideal camera with the same ``K`` sees.

        ``guess`` (``(N, 2)`` ideal pixels near the answer) only saves Newton iterations.
        """
        return self._undistort_rows(uv, guess, pixels=True)

    @classmethod
    def from_camera_info(
        cls,
        width: int,
        height: int,
        k: ArrayLike,
        distortion_model: str,
        d: ArrayLike,
    ) -> CameraModel:
        """Build from the fields of a ``sensor_msgs/CameraInfo`` (row-major ``k``, ``d``).

        An empty ``distortion_model`` with all-zero ``d`` is read as an ideal pinhole.
        """
        K = np.asarray(k, dtype=np.float64)
        if K.size != 9:
            raise CalibrationError(f"CameraInfo.k must have 9 elements, got {K.size}")
        model = distortion_model or "plumb_bob"
        D = np.asarray(d, dtype=np.float64).ravel()
        if model == "plumb_bob" and D.size == 8 and not np.any(D[5:]):
            D = D[:5]
        return cls(int(width), int(height), K.reshape(3, 3), model, D)

    @classmethod
    def from_yaml(cls, path: str | Path) -> CameraModel:
        """Load a camera_calibration YAML file, or the YAML file OpenCV's calibration writes
        (``cv2.FileStorage``: ``!!opencv-matrix`` entries ``image_width``, ``image_height``,
        ``camera_matrix`` / ``cameraMatrix``, ``distortion_coefficients`` / ``distCoeffs``).

        Raises
        ------
        CalibrationError
            If the file cannot be read or lacks, or has malformed, required fields.
        """
        try:
            with open(path, "rb") as f:
                head = f.read(1 << 16)
            # OpenCV's dialect: a "%YAML:1.0" directive (older) or !!opencv-matrix tags.
            opencv = head.startswith(b"%YAML:") or b"!!opencv-matrix" in head
        except OSError:
            opencv = False  # load_yaml names the problem
        if opencv:
            return cls._from_opencv_storage(Path(path))
        try:
            doc = load_yaml(path)
        except YamlFileError as err:
            raise CalibrationError(f"cannot read calibration {err}") from err
        if not isinstance(doc, dict):
            raise CalibrationError(f"calibration {path} is not a YAML mapping")
        try:
            return cls.from_dict(doc)
        except CalibrationError as err:
            raise CalibrationError(f"calibration {path}: {err}") from err

    @classmethod
    def _from_opencv_storage(cls, path: Path) -> CameraModel:
        """A ``cv2.FileStorage`` calibration (see :meth:`from_yaml`)."""
        try:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as err:  # OpenCV's parser error surfaces as either
            cause = err.__cause__ if isinstance(err, SystemError) and err.__cause__ else err
            msg = " ".join(str(cause).split())
            raise CalibrationError(f"cannot read calibration {path} (OpenCV YAML): {msg}") from err

        def node(*names: str, required: bool = True) -> Any:
            for name in names:
                found = fs.getNode(name)
                if not found.empty():
                    return found
            if required:
                raise CalibrationError(f"calibration {path}: missing field {' / '.join(names)}")
            return None

        try:
            width = node("image_width").real()
            height = node("image_height").real()
            k = node("camera_matrix", "cameraMatrix").mat()
            d_node = node("distortion_coefficients", "distCoeffs", required=False)
            d = np.zeros(5) if d_node is None else d_node.mat()
        except cv2.error as err:
            # A matrix whose rows x cols disagree with its data, most often.
            raise CalibrationError(
                f"calibration {path}: malformed OpenCV matrix (its rows x cols do not match "
                f"its data, or a field is not a matrix)"
            ) from err
        finally:
            fs.release()
        if k is None or d is None or np.asarray(k).size != 9:
            raise CalibrationError(f"calibration {path}: camera_matrix must be a 3x3 matrix")
        d = np.asarray(d, dtype=np.float64).ravel()
        models = {4: "plumb_bob", 5: "plumb_bob", 8: "rational_polynomial"}
        if d.size not in models:
            raise CalibrationError(
                f"calibration {path}: {d.size} distortion coefficients; plumb_bob (4 or 5) and "
                "rational_polynomial (8) are supported"
            )
        if d.size == 4:
            d = np.append(d, 0.0)  # k1 k2 p1 p2 without k3
        try:
            return cls.from_camera_info(int(width), int(height), k, models[d.size], d)
        except CalibrationError as err:
            raise CalibrationError(f"calibration {path}: {err}") from err

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> CameraModel:
        """Build from a parsed camera_calibration YAML mapping."""
        try:
            width = int(doc["image_width"])
            height = int(doc["image_height"])
            cm = doc["camera_matrix"]
            k = np.asarray(cm["data"], dtype=np.float64)
            if (int(cm.get("rows", 3)), int(cm.get("cols", 3))) != (3, 3):
                raise CalibrationError("camera_matrix must be 3x3")
            model = str(doc.get("distortion_model", "plumb_bob"))
            dist = doc.get("distortion_coefficients", {"data": []})
            d = np.asarray(dist["data"] if isinstance(dist, dict) else dist, dtype=np.float64)
        except CalibrationError:
            raise
        except (KeyError, TypeError, ValueError) as err:
            raise CalibrationError(f"missing or malformed field: {err}") from err
        return cls.from_camera_info(width, height, k, model, d)

    def to_dict(self, camera_name: str = "armourcam") -> dict[str, Any]:
        """The camera_calibration YAML mapping (round-trips with :meth:`from_dict`)."""
        return {
            "image_width": self.width,
            "image_height": self.height,
            "camera_name": camera_name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": self.K.ravel().tolist()},
            "distortion_model": self.distortion_model,
            "distortion_coefficients": {"rows": 1, "cols": len(self.D), "data": self.D.tolist()},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
            "projection_matrix": {
                "rows": 3,
                "cols": 4,
                "data": np.hstack([self.K, np.zeros((3, 1))]).ravel().tolist(),
            },
        }


def _newton_undistort(
    x0: NDArray[np.float64],
    y0: NDArray[np.float64],
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    D: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Ideal normalised points ``(x, y)`` whose distortion is ``(x0, y0)``, by Newton from the
    start ``(x, y)`` (updated in place), and the residual before the last step.

    The lens model (OpenCV's, ``D`` as in :class:`CameraModel`) and its analytic Jacobian, over
    whole arrays; stops when every residual is below 1e-14, checked before the Jacobian is
    formed, so a converged pass costs only the residual.
    """
    coeffs = _coefficients(D)
    p1, p2 = coeffs[2], coeffs[3]
    tangential = bool(p1 or p2)
    resid = np.full(np.shape(x), np.inf)
    for _ in range(30):
        xx, yy, xy = x * x, y * y, x * y
        rad, drad = _radial(xx + yy, coeffs)
        fx = x * rad - x0
        fy = y * rad - y0
        if tangential:
            r2 = xx + yy
            fx += 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
            fy += p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
        resid = np.abs(fx) + np.abs(fy)
        if resid.max(initial=0.0) < 1e-14:  # (an empty batch has converged)
            break
        j11, j12, j22 = _jacobian(x, y, xx, yy, xy, rad, drad, coeffs)
        inv_det = 1.0 / (j11 * j22 - j12 * j12)
        x -= (j22 * fx - j12 * fy) * inv_det
        y -= (j11 * fy - j12 * fx) * inv_det
    return x, y, resid


def _coefficients(D: NDArray[np.float64]) -> tuple[float, ...]:
    """``(k1, k2, p1, p2, k3, k4, k5, k6)`` of either model as floats (zeros where absent)."""
    coeffs = np.zeros(8)
    coeffs[: len(D)] = D
    return tuple(float(d) for d in coeffs)


def _radial(
    r2: NDArray[np.float64], coeffs: tuple[float, ...]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Radial factor of the lens model at squared radii ``r2`` and its derivative in ``r2``."""
    k1, k2, _, _, k3, k4, k5, k6 = coeffs
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    if k4 or k5 or k6:
        b = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        db = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        drad = (drad * b - rad * db) / (b * b)
        rad = rad / b
    return rad, drad


def _jacobian(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    xx: NDArray[np.float64],
    yy: NDArray[np.float64],
    xy: NDArray[np.float64],
    rad: NDArray[np.float64],
    drad: NDArray[np.float64],
    coeffs: tuple[float, ...],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Entries ``(j11, j12, j22)`` of the (symmetric) Jacobian of the lens model."""
    p1, p2 = coeffs[2], coeffs[3]
    drad2 = 2.0 * drad
    j11 = rad + drad2 * xx
    j12 = drad2 * xy
    j22 = rad + drad2 * yy
    if p1 or p2:
        j11 += 2.0 * p1 * y + 6.0 * p2 * x
        j12 += 2.0 * p1 * x + 2.0 * p2 * y
        j22 += 6.0 * p1 * y + 2.0 * p2 * x
    return j11, j12, j22
