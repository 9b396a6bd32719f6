"""Subcommands of ``armourcam``: each module defines ``register(subparsers)``.

Every module in this package is discovered and registered by :mod:`armourcam.cli`; a command module
only parses its arguments and calls the cores.
"""

from __future__ import annotations

import argparse


def add_ros_args(parser: argparse.ArgumentParser, help_text: str) -> None:
    """``--ros-args``: it ends the command's own options and the rest goes to rclpy (remaps,
    ``-p`` parameters, ``--log-level``), as ``args.ros_args`` (a list, empty without it)."""
    parser.add_argument(
        "--ros-args", nargs=argparse.REMAINDER, default=[], metavar="ARG", help=help_text
    )
