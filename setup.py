"""The compiled parts of armourcam: the detector's two kernels (Python.h only, no numpy headers),
the profile fit's and the boundary tracer's.

Everything else is declared in ``pyproject.toml``; ``pip install -e .`` builds the kernels in place,
beside :mod:`fiducial_detector.profile_fit` and :mod:`fiducial_detector.components`, with the gcc
and Python headers every machine here has.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "fiducial_detector._profile_kernel",
            sources=["src/fiducial_detector/_profile_kernel.c"],
            extra_compile_args=["-O3", "-fno-math-errno", "-fno-trapping-math"],
        ),
        Extension(
            "fiducial_detector._border_kernel",
            sources=["src/fiducial_detector/_border_kernel.c"],
            extra_compile_args=["-O3"],
        ),
    ]
)
