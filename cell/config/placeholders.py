"""Values of a cell file still to be measured: the ``# MEASURE: <what>`` marks of a template.

A hardware template (``cell init``) carries example values for what only the cell itself can tell (the
robot's address, the sensor's port, the hand-eye mount, the station). Each such line ends in a comment
``# MEASURE: <what to measure>``; the integrator measures the value, writes it and deletes the mark. A
mark is a comment so that the file stays plain YAML that validates as it is: a dry run and a
calibration run with the marks still in place, but a real cell does not scan (:func:`require_measured`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import yaml

from drivers.errors import ConfigError

MARK = re.compile(r"#\s*MEASURE:\s*(?P<what>.*?)\s*$")


@dataclass(frozen=True)
class Placeholder:
    """A marked value: its dotted ``field``, its 1-based ``line`` in the file and ``what`` to measure."""

    field: str
    line: int
    what: str


def _key_lines(node: yaml.Node, prefix: str, out: dict[int, str]) -> None:
    """Map each mapping key's 0-based line to its dotted field path, depth first."""
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            path = f"{prefix}.{key.value}" if prefix else str(key.value)
            out.setdefault(key.start_mark.line, path)
            _key_lines(value, path, out)
    elif isinstance(node, yaml.SequenceNode):
        for index, item in enumerate(node.value):
            _key_lines(item, f"{prefix}[{index}]", out)


def find_placeholders(text: str) -> list[Placeholder]:
    """The marked values of a cell file's ``text``, in file order. A mark on a line that holds no key (a
    comment line) marks nothing. ``yaml.YAMLError`` if the text is not YAML."""
    root = yaml.compose(text)
    keys: dict[int, str] = {}
    if root is not None:
        _key_lines(root, "", keys)
    found = []
    for index, line in enumerate(text.splitlines()):
        mark = MARK.search(line)
        if mark and index in keys:
            found.append(Placeholder(field=keys[index], line=index + 1, what=mark.group("what")))
    return found


def require_measured(path: Path, mode: str) -> None:
    """Refuse to run a ``real`` cell whose file at ``path`` still has a marked value (``ConfigError``
    naming them); other modes move nothing real on a wrong mount or station and may run."""
    if mode != "real":
        return
    left = find_placeholders(path.read_text())
    if left:
        names = ", ".join(p.field for p in left)
        raise ConfigError(f"still to measure: {names} (marked '# MEASURE:'; measure each, write it and "
                          f"delete the mark; cell config check {path} lists them)", file=str(path))
