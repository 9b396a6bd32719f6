"""The ``armourcam`` command line: subcommands are discovered from :mod:`armourcam.commands`.

Each command module defines ``register(subparsers)`` that adds its parser and sets ``func`` to a
callable taking the parsed arguments and returning the exit status. Errors that the cores raise for
bad input (``ValueError`` subclasses such as ``DetectorError``) end the command with a one-line
message and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import signal
import sys
from collections.abc import Sequence

from . import __version__, commands
from .blas import one_blas_thread
from .heap import keep_freed_memory


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every discovered subcommand."""
    parser = argparse.ArgumentParser(
        prog="armourcam",
        description="Measure 3-D displacement of armour-unit models from circular fiducials.",
    )
    parser.add_argument("--version", action="version", version=f"armourcam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit status."""
    one_blas_thread()  # before any command imports numpy
    keep_freed_memory()  # per-frame temporaries stay in the process (armourcam.heap)
    args = build_parser().parse_args(argv)
    try:
        status = args.func(args)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader went away (``armourcam detect --json ... | head``): stop quietly with the
        # status a process killed by SIGPIPE has in a shell, and keep Python from reporting the
        # failed flush of stdout at exit.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except (ValueError, OSError) as err:
        print(f"armourcam {args.command}: error: {err}", file=sys.stderr)
        return 2
    return int(status or 0)


if __name__ == "__main__":
    sys.exit(main())
