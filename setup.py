"""The one compiled part of armourcam: the profile fit's kernel (Python.h only, no numpy headers).

Everything else is declared in ``pyproject.toml``; ``pip install -e .`` builds the kernel in place,
beside :mod:`fiducial_detector.profile_fit`, with the gcc and Python headers every machine here has.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "fiducial_detector._profile_kernel",
            sources=["src/fiducial_detector/_profile_kernel.c"],
            extra_compile_args=["-O3", "-fno-math-errno", "-fno-trapping-math"],
        )
    ]
)
