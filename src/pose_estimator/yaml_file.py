"""YAML files read with one-line errors (calibrations here, unit maps in the matcher).

PyYAML's own messages span several lines (the problem, a context line, the offending text with a
caret); a command line answers bad input in one line naming the file and the place.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml


class YamlFileError(ValueError):
    """A YAML file that cannot be read or parsed (one-line message naming file and place)."""


def load_yaml(path: str | Path) -> Any:
    """Parse a YAML file (``yaml.safe_load``).

    Raises
    ------
    YamlFileError
        If the file cannot be read (``"PATH: reason"``), or is not valid YAML (``"PATH: not
        valid YAML at line L, column C: problem"``).
    """
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise YamlFileError(f"{path}: {reason}") from err
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise YamlFileError(f"{path}: {_one_line(err)}") from err


def _one_line(err: yaml.YAMLError) -> str:
    """The problem and its place (1-based line and column) of a PyYAML error, on one line."""
    if isinstance(err, yaml.MarkedYAMLError):
        mark = err.problem_mark or err.context_mark
        problem = err.problem or err.context or "not valid YAML"
        if mark is not None:
            return f"not valid YAML at line {mark.line + 1}, column {mark.column + 1}: {problem}"
        return f"not valid YAML: {problem}"
    return "not valid YAML: " + " ".join(str(err).split())
