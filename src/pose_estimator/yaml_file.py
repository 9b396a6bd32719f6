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


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` refusing a key given twice in one mapping.

    YAML says keys are unique, but PyYAML lets the last one win silently: a copied block in a
    unit map would drop a unit, a second ``distortion_coefficients`` replace the first.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        # Merge keys (<<) override by design; such a mapping is left to PyYAML.
        if isinstance(node, yaml.MappingNode) and not any(
            k.tag == "tag:yaml.org,2002:merge" for k, _ in node.value
        ):
            first: dict[Any, Any] = {}
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    seen = first.get(key)
                except TypeError:
                    continue  # an unhashable key: PyYAML's own error names it
                if seen is not None:
                    raise yaml.constructor.ConstructorError(
                        "while constructing a mapping",
                        node.start_mark,
                        f"key {key!r} given twice (first at line {seen.line + 1})",
                        key_node.start_mark,
                    )
                first[key] = key_node.start_mark
        return super().construct_mapping(node, deep=deep)


def load_yaml(path: str | Path) -> Any:
    """Parse a YAML file (``yaml.safe_load``, but a key given twice in one mapping is an error).

    Raises
    ------
    YamlFileError
        If the file cannot be read (``"PATH: reason"``), or is not valid YAML (``"PATH: not
        valid YAML at line L, column C: problem"``, also for a key given twice).
    """
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise YamlFileError(f"{path}: {reason}") from err
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader: no arbitrary objects
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
