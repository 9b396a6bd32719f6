"""Result types of the detector.

Pixel convention everywhere: ``(u, v)`` = (x, y) = (column, row), with pixel centres at integer
coordinates (OpenCV's convention); the top-left pixel covers ``[-0.5, 0.5] x [-0.5, 0.5]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, slots=True, eq=False)
class Ellipse:
    """An ellipse fitted to one printed circle of a fiducial, in pixels.

    Attributes
    ----------
    center_px : (float, float)
        Centre ``(u, v)`` of the ellipse (not, in general, the image of the circle's centre).
    semi_major, semi_minor : float
        Semi-axes in pixels, ``semi_major >= semi_minor > 0``.
    angle : float
        Angle of the major axis from +u towards +v, radians in ``[0, pi)``.
    covariance : (5, 5) ndarray
        Covariance of ``(u, v, semi_major, semi_minor, angle)`` from the fit's residuals.
    radius : float
        Nominal radius of the printed circle it was fitted to, as a fraction of the outer radius.
    rms_residual : float
        The fit's root-mean-square residual, for diagnostics; its unit is the method's: the
        dual conic's algebraic residual, the edge model's over the image noise, the edge
        profiles' edge-position residual in pixels.
    systematic_px : float
        Standard deviation, pixels, of a systematic error the fit's method is known to make here
        and ``covariance`` leaves out (a bias, the same in every image of the scene, not
        scatter): the gradient dual conic wherever it gives the pose circle (standing in where
        the other fits failed, and the ``dot`` design's dot below the edge model's size;
        :data:`fiducial_detector.detect.DUAL_CONIC_SYSTEMATIC_PX`); 0 for the other fits. The
        pose estimator reports the error it makes in the pose's own systematic covariance
        (``FiducialPose.systematic_mm2``), not in its covariance or in the fit's weight.
    """

    center_px: tuple[float, float]
    semi_major: float
    semi_minor: float
    angle: float
    covariance: NDArray[np.float64]
    radius: float
    rms_residual: float = 0.0
    systematic_px: float = 0.0

    def conic(self) -> NDArray[np.float64]:
        """Symmetric 3x3 conic matrix ``C`` with ``[u v 1] C [u v 1]^T = 0`` on the ellipse.

        Normalised so that ``det(C[:2, :2]) = 1 / (a^2 b^2)`` (the geometric scale).
        """
        return conic_from_parameters(
            self.center_px[0], self.center_px[1], self.semi_major, self.semi_minor, self.angle
        )


# The slots' setters in field order, once: ellipses_from_rows sets an Ellipse's fields through
# them (a field added to Ellipse makes its unpacking there fail, loudly).
_ELLIPSE_SETTERS = tuple(getattr(Ellipse, f.name).__set__ for f in fields(Ellipse))


def ellipses_from_rows(
    good: list[bool],
    params: list[list[float]],
    covariance: list[NDArray[np.float64]],
    radius: float,
    rms_residual: list[float],
) -> list[Ellipse | None]:
    """``Ellipse((u, v), a, b, angle, covariance, radius, rms)`` for each row ``(u, v, a, b,
    angle)`` of ``params`` where ``good``, None elsewhere (``systematic_px`` 0).

    The same objects the constructor makes, at 0.6 of its cost: a frame's 1,600 fitted
    circles took 2 ms through the frozen dataclass' ``__init__`` (a named ``object.__setattr__``
    per field), here each field goes straight through its slot's setter.
    """
    new = object.__new__
    s0, s1, s2, s3, s4, s5, s6, s7 = _ELLIPSE_SETTERS
    out: list[Ellipse | None] = []
    for g, (u, v, a, b, angle), cov, rms in zip(
        good, params, covariance, rms_residual, strict=True
    ):
        if not g:
            out.append(None)
            continue
        e = new(Ellipse)
        s0(e, (u, v))
        s1(e, a)
        s2(e, b)
        s3(e, angle)
        s4(e, cov)
        s5(e, radius)
        s6(e, rms)
        s7(e, 0.0)
        out.append(e)
    return out


def conic_from_parameters(
    u: float, v: float, a: float, b: float, angle: float
) -> NDArray[np.float64]:
    """Conic matrix of the ellipse with centre ``(u, v)``, semi-axes ``a``, ``b`` and ``angle``."""
    c, s = np.cos(angle), np.sin(angle)
    # Quadratic form of the centred ellipse: R diag(1/a^2, 1/b^2) R^T.
    rot = np.array([[c, -s], [s, c]])
    q = rot @ np.diag([1.0 / (a * a), 1.0 / (b * b)]) @ rot.T
    centre = np.array([u, v])
    conic = np.empty((3, 3))
    conic[:2, :2] = q
    conic[:2, 2] = conic[2, :2] = -q @ centre
    conic[2, 2] = centre @ q @ centre - 1.0
    return conic


@dataclass(frozen=True, slots=True, eq=False)
class FiducialDetection:
    """One fiducial found in an image.

    Attributes
    ----------
    code : int
        Code number in the codebook.
    hamming : int
        Hamming distance between the sectors read and the code (0 or 1 are accepted).
    center_px : (float, float)
        Centre ``(u, v)`` of the pose ellipse, pixels.
    ellipses : tuple of Ellipse
        Ellipses fitted to the design's printed circles, largest first (``ellipses[0]`` is the
        pose circle's), then to its coding-track arcs where fitted (the ``dot`` design's track's
        outer edge, radius 1.0, larger than its pose circle; see
        :func:`fiducial_detector.detect.fit_arcs`).
    contrast : float
        White level minus black level around the fiducial, as a fraction of the image's full scale.
    design : str
        Name of the fiducial design (``"dot"`` or ``"ring"``).
    rotation : float
        In-plane orientation: image angle (radians, from +u towards +v) of the boundary between
        sectors 15 and 0 as read, for diagnostics and unit rotation.
    """

    code: int
    hamming: int
    center_px: tuple[float, float]
    ellipses: tuple[Ellipse, ...]
    contrast: float
    design: str
    rotation: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def pose_ellipse(self) -> Ellipse:
        """The ellipse of the pose circle."""
        return self.ellipses[0]
