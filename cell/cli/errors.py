"""How a ``cell`` command fails: one line ``error: <reason>`` on standard error, then its exit code; and how
it warns of something it went on without: one line ``warning: <what>`` on standard error."""

from __future__ import annotations

import typer
from rich.console import Console

err_console = Console(stderr=True)


def print_error(reason: object) -> None:
    """``error: <reason>`` on standard error, on one line however wide the terminal."""
    err_console.print(f"error: {reason}", markup=False, highlight=False, soft_wrap=True)


def print_warning(what: object) -> None:
    """``warning: <what>`` on standard error, on one line however wide the terminal."""
    err_console.print(f"warning: {what}", markup=False, highlight=False, soft_wrap=True)


def fail(reason: object, code: int = 1) -> typer.Exit:
    """Print ``reason`` (:func:`print_error`) and return the exit to raise."""
    print_error(reason)
    return typer.Exit(code=code)
