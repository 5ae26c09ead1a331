"""Values of a cell file still to be measured: the ``# MEASURE: <what>`` marks of a template.

A hardware template (``cell init``) carries example values for what only the cell itself can tell (the
robot's address, the sensor's port, the hand-eye mount, the station). Each such line ends in a comment
``# MEASURE: <what to measure>``; the integrator measures the value, writes it and deletes the mark. A
mark is a comment so that the file stays plain YAML that validates as it is: a dry run and a
calibration run with the marks still in place, but a real cell does not scan (:func:`require_measured`),
and no command connects to an arm whose own values are still marked (:func:`require_arm_measured`).
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


ARM_MODES = ("real", "dry-run")
"""The modes (``CellConfig.mode``) of a cell whose arm is hardware."""


def require_arm_measured(path: Path, mode: str) -> None:
    """Refuse to connect to the hardware arm of a cell in ``mode`` while a value of its ``arm`` section in
    the file at ``path`` is still marked (``ConfigError`` naming each, its line and what to measure): the
    template's example address (``arm.host: 192.168.1.10``) is another machine's or nobody's, and the
    connection would fail with a diagnosis of its handshake that never says so. The other marked values
    (the mount, the station; the sensor's port or serial, whose examples are the usual ones) are measured
    with the arm connected, and may stay marked meanwhile."""
    if mode not in ARM_MODES:
        return
    left = [p for p in find_placeholders(path.read_text()) if p.field.split(".", 1)[0] == "arm"]
    if left:
        names = "; ".join(f"{p.field} at line {p.line}, {p.what}" for p in left)
        raise ConfigError(f"still to measure before connecting to the arm, its value the template's "
                          f"example: {names}; measure it, write it and delete its '# MEASURE:' mark (cell "
                          f"config check {path} lists every mark left)", file=str(path))


def require_measured(path: Path, mode: str) -> None:
    """Refuse to run a ``real`` cell whose file at ``path`` still has a marked value (``ConfigError``
    naming them); other modes move nothing real on a wrong mount or station and may run, but a dry run
    connects to its arm (:func:`require_arm_measured`)."""
    if mode != "real":
        require_arm_measured(path, mode)
        return
    left = find_placeholders(path.read_text())
    if left:
        names = ", ".join(p.field for p in left)
        raise ConfigError(f"still to measure: {names} (marked '# MEASURE:'; measure each, write it and "
                          f"delete the mark; cell config check {path} lists them)", file=str(path))
