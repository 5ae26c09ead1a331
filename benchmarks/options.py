"""The benchmarks' command line (a helper module of theirs, not a benchmark: running it does nothing).

A benchmark's parser (:class:`BenchmarkParser`) refuses bad input as the ``cell`` command does: one line,
``<script>: error: <what is wrong>``, on standard error and exit code 1 (``EXIT_INPUT_ERROR``; argparse
exits 2 after its usage). Its option types refuse a count or a time that a run cannot use (zero frames,
a negative budget) before anything runs.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from cell.cli.commands import EXIT_INPUT_ERROR


class BenchmarkParser(argparse.ArgumentParser):
    """An ``argparse`` parser whose errors, its own (an unknown option, a value its type refuses) and
    those a benchmark finds (``parser.error``), print one line and exit with ``EXIT_INPUT_ERROR``."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_INPUT_ERROR, f"{self.prog}: error: {message}\n")


def first_paragraph(doc: str | None) -> str:
    """A script's docstring up to its first blank line: the description its ``--help`` shows (its first
    line alone ends mid-sentence where the sentence goes on)."""
    return (doc or "").split("\n\n")[0]


def at_least(minimum: int) -> Callable[[str], int]:
    """An option type: a whole number of at least ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected at least {minimum}, got {value}")
        return value

    return parse


count = at_least(1)
"""An option type: a count of at least 1 (frames, repeats, ticks)."""


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


def positive(text: str) -> float:
    """An option type: a number above 0 (a time [s], a rate)."""
    value = _number(text)
    if not value > 0.0:  # also refuses nan
        raise argparse.ArgumentTypeError(f"expected a number above 0, got {text}")
    return value


def non_negative(text: str) -> float:
    """An option type: a number of at least 0 (a largest error, where none at all is a case too)."""
    value = _number(text)
    if not value >= 0.0:  # also refuses nan
        raise argparse.ArgumentTypeError(f"expected a number of at least 0, got {text}")
    return value


def checkout(text: str) -> Path:
    """An option type: another checkout of the cell (a folder with ``cell/`` and ``config/``), resolved."""
    path = Path(text).resolve()
    if not ((path / "cell").is_dir() and (path / "config").is_dir()):
        raise argparse.ArgumentTypeError(f"{text} is not a checkout of the cell (no cell/ and config/ in it)")
    return path


def seed_list(text: str) -> list[int]:
    """An option type: comma-separated seeds, whole numbers of at least 0 (``0,1,2``)."""
    parse = at_least(0)
    try:
        return [parse(part) for part in text.split(",")]
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated seeds (0,1,2): {exc}") from None

