"""Subcommands of ``armourcam``: each module defines ``register(subparsers)``.

Every module in this package is discovered and registered by :mod:`armourcam.cli`; a command module
only parses its arguments and calls the cores.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_ros_args(parser: argparse.ArgumentParser, help_text: str) -> None:
    """``--ros-args``: it ends the command's own options and the rest goes to rclpy (remaps,
    ``-p`` parameters, ``--log-level``), as ``args.ros_args`` (a list, empty without it)."""
    parser.add_argument(
        "--ros-args", nargs=argparse.REMAINDER, default=[], metavar="ARG", help=help_text
    )


def output_path(text: str) -> Path:
    """An ``--out`` value: a path, not an empty string (an unset shell variable), which
    ``Path`` would take for the working directory and write the outputs over what is there."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; give the output's name")
    return Path(text)
