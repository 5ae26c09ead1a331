"""The cell file's reference (``docs/config.md``) is generated from the models and kept up to date: every
key of every section is in it with its type, unit, default and constraints."""

from __future__ import annotations

import re

from typer.testing import CliRunner

from cell.cli.config_check import config_app
from cell.config.reference import NOT_STATED, reference_markdown, sections
from tests.service_process import REPO

DOC = REPO / "docs" / "config.md"


def _row(text: str, section: str, key: str) -> list[str]:
    """The table cells of ``key`` in the section headed ``section``."""
    part = text.split(f"# {section}\n", 1)[1].split("\n#", 1)[0]
    line = next(line for line in part.splitlines() if line.startswith(f"| `{key}` |"))
    return [cell.strip() for cell in line.strip("|").split(" | ")]


def test_docs_config_md_is_the_models_reference():
    assert DOC.read_text() == reference_markdown(), (
        "docs/config.md is out of date with the cell file's models: run "
        "`.venv/bin/cell config reference --out docs/config.md` and commit it")


def test_every_key_of_every_section_has_a_row():
    text = reference_markdown()
    for section in sections():
        title = section.title if section.path else "The whole file"
        for key in section.model.model_fields:
            assert _row(text, title, key)[0] == f"`{key}`"


def test_a_row_holds_type_unit_default_and_constraints():
    text = reference_markdown()
    assert _row(text, "`service`", "shutdown_timeout_s") == [
        "`shutdown_timeout_s`", "number (> 0.0, not quoted)", "s", "`20.0`", ""]
    assert _row(text, "`service`", "max_upload_mb")[2:4] == ["MB (10⁶ bytes)", "`50.0`"]
    assert _row(text, "`line.dio`", "poll_hz")[1:4] == ["number (> 0.0, <= 1000.0)", "Hz", "`200.0`"]
    assert _row(text, "`arm` (type: ur5e)", "watchdog_min_hz")[1:4] == [
        "number (> 0.0, <= 500.0, not quoted)", "Hz", "required"]
    assert _row(text, "`arm` (type: ur5e)", "busy_output")[1] == "integer (>= 0, <= 7) or null"
    # a unit from the docstring under the field, shown once
    assert _row(text, "`sensor` (type: sim-rgbd)", "fx")[2:] == [
        "px", "required", "the focal length along x."]
    # a number whose unit no model states says so
    assert _row(text, "`planners.lrnbv`", "w_e")[2] == NOT_STATED


def test_cell_config_reference_prints_or_writes_it(tmp_path):
    printed = CliRunner().invoke(config_app, ["reference"])
    assert printed.exit_code == 0 and printed.stdout == reference_markdown()
    out = tmp_path / "config.md"
    written = CliRunner().invoke(config_app, ["reference", "--out", str(out)])
    assert written.exit_code == 0 and out.read_text() == reference_markdown()
    assert re.search(r"wrote .*config\.md", written.stdout)
