"""Putting calibration results into a cell file without losing what a person wrote there.

Only the characters of the values named change: ruamel.yaml's round-trip loader finds where each value
is written (line and column), and the value's text there is replaced by the new one, a flow sequence
(``[0.0, 0.04, 0.03]``) or a scalar on one line, with a trailing comment kept in its column where the new
text leaves room. A key that is missing is added as the first entry of its (existing, block) mapping.
A ``# MEASURE: ...`` mark of a template on an edited line (``cell.config.placeholders``) is replaced by
the note given (e.g. ``calibrated by cell calibrate mount, 2026-11-24``): the value is measured now.
Everything else, comments, blank lines, flow mappings spread over lines, anchors, stays byte for byte
(dumping the whole document would re-flow such mappings and drop the comments inside them). The new text
must still load as a cell file (``cell.config.load.parse_config``) before it replaces the old one.
"""

from __future__ import annotations

import difflib
import json
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml
from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq

from cell.config.load import parse_config
from cell.config.placeholders import MARK
from drivers.errors import ConfigError

KeyPath = tuple[str, ...]
_COMMENT = re.compile(r"(\s+)#")


def _flow(value: Any) -> str:
    """``value`` as YAML flow text: a list as ``[a, b, c]``, a scalar as JSON (valid YAML)."""
    if isinstance(value, Sequence) and not isinstance(value, str):
        return "[" + ", ".join(_flow(v) for v in value) + "]"
    return json.dumps(value)


def _scalar_end(line: str, col: int) -> int:
    """Where a plain or quoted scalar starting at ``col`` ends: before a comment or the line's end."""
    m = _COMMENT.search(line, col)
    return m.start() if m else len(line.rstrip("\r\n"))


def _replace(line: str, start: int, end: int, new: str, note: str) -> str:
    """``line`` with ``[start, end)`` replaced by ``new``, a comment after it kept in its column when the
    spaces before it allow, a ``MEASURE`` mark replaced by ``note``."""
    body = line[end:].rstrip("\r\n")
    rest = MARK.sub(f"# {note}", body) + line[end + len(body):]
    m = _COMMENT.match(rest)
    if m:
        grow = len(new) - (end - start)
        spaces = max(len(m.group(1)) - grow, 1)
        rest = " " * spaces + rest[m.end(1):]
    return line[:start] + new + rest


def _node(data: CommentedMap, path: KeyPath, file: str) -> CommentedMap:
    node = data
    for i, key in enumerate(path[:-1]):
        child = node.get(key)
        if not isinstance(child, CommentedMap):
            raise ConfigError("is not a mapping in the file; add the value by hand", file=file,
                              field=".".join(path[:i + 1]))
        node = child
    return node


def _edit(lines: list[str], data: CommentedMap, path: KeyPath, value: Any, file: str, note: str) -> None:
    node, key, new = _node(data, path, file), path[-1], _flow(value)
    field = ".".join(path)
    if key not in node:
        if not node:
            raise ConfigError("has no entry to add the value beside; add it by hand", file=file,
                              field=".".join(path[:-1]))
        first_line, indent = node.lc.key(next(iter(node)))
        lines.insert(first_line, f"{' ' * indent}{key}: {new}  # {note}\n")
        return
    line_no, col = node.lc.value(key)
    line, old = lines[line_no], node[key]
    if isinstance(old, CommentedSeq):
        end = line.find("]", col) + 1
        if line[col] != "[" or end == 0:
            raise ConfigError("is not a one-line flow sequence; edit it by hand", file=file, field=field)
    elif isinstance(old, CommentedMap):
        raise ConfigError("is a mapping, not a value", file=file, field=field)
    else:
        end = _scalar_end(line, col)
    lines[line_no] = _replace(line, col, end, new, note)


def updated_text(text: str, updates: Mapping[KeyPath, Any], file: str, note: str) -> str:
    """``text`` (a cell file) with the values at each key path of ``updates`` set, ``note`` the comment of
    an added key or of a replaced ``MEASURE`` mark (see the module docstring); raises ``ConfigError``
    when a value cannot be edited in place or the result is no longer a valid cell file."""
    for path, value in updates.items():
        data = YAML(typ="rt").load(text)
        if not isinstance(data, CommentedMap):
            raise ConfigError("is not a YAML mapping", file=file)
        lines = text.splitlines(keepends=True)
        _edit(lines, data, path, value, file, note)
        text = "".join(lines)
    parse_config(yaml.safe_load(text), file=file)
    return text


def change_diff(old: str, new: str, file: str) -> str:
    """A unified diff of the change, for the user to see before it is written."""
    return "".join(difflib.unified_diff(old.splitlines(keepends=True), new.splitlines(keepends=True),
                                        fromfile=file, tofile=f"{file} (calibrated)"))


def update_cell_file(path: Path, updates: Mapping[KeyPath, Any], note: str,
                     show: Callable[[str], None]) -> None:
    """Write ``updates`` into the cell file at ``path`` (:func:`updated_text`), after passing the change
    (a unified diff) to ``show``."""
    old = path.read_text()
    new = updated_text(old, updates, str(path), note)
    show(change_diff(old, new, str(path)))
    path.write_text(new)
