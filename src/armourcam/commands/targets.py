"""``armourcam targets``: printable fiducial targets (a vector PDF sheet, or one target as PNG)."""

from __future__ import annotations

import argparse
from typing import Any

from fiducial_detector.design import DESIGNS

from ..printing import MAX_SHEET_TARGETS, parse_codes, parse_copies, write_targets


def register(subparsers: Any) -> None:
    """Add the ``targets`` subcommand."""
    parser = subparsers.add_parser(
        "targets",
        help="make printable fiducial targets (PDF sheet or single-target PNG)",
        description=(
            "Write an A4 PDF sheet of vector targets with labels and crop marks (-o NAME.pdf, "
            "as many pages as needed), or one target as a grayscale PNG at the given dpi "
            "(-o NAME.png: exactly one code, one copy)."
        ),
    )
    parser.add_argument(
        "--design",
        choices=sorted(DESIGNS),
        default="ring",
        help="fiducial design (default ring: the outer annulus carries the pose, several times "
        "more precise in depth than the paper's dot)",
    )
    parser.add_argument(
        "--codes",
        default="0-63",
        help="codes to print, e.g. '0-63' or '3,5,10-12' (default 0-63); a code listed twice, "
        "also through overlapping ranges, is printed twice ('1,1,2': two of code 1, one of 2)",
    )
    parser.add_argument(
        "--copies",
        default="1",
        metavar="N",
        help="print every listed code N times, copies of a code side by side in code order "
        f"(default 1; at most {MAX_SHEET_TARGETS} targets in all); each label names its code",
    )
    parser.add_argument(
        "--diameter-mm",
        type=float,
        default=7.1,
        help="diameter of the outermost printed circle in mm (default 7.1, the paper's)",
    )
    parser.add_argument(
        "--dpi", type=float, default=600.0, help="printer / PNG resolution (default 600)"
    )
    parser.add_argument(
        "-o",
        "--output",
        required=True,
        help="output file: .pdf (sheet) or .png (one target: one code, --copies 1)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Write the targets and print a one-line summary."""
    codes = parse_codes(args.codes, unique=False)
    copies = parse_copies(args.copies)
    summary = write_targets(
        args.output, args.design, codes, args.diameter_mm, args.dpi, copies=copies
    )
    print(summary)
    return 0
