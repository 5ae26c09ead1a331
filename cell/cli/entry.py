"""The ``cell`` program's entry point: loads the command it runs, ending quietly on Ctrl-C meanwhile.

Loading a command takes up to a few seconds (numpy, SciPy, Open3D, FastAPI, ...); Ctrl-C meanwhile would
print the traceback of whichever import it interrupted, or worse, an ``ImportError`` from an extension
whose initialisation it broke (Open3D's turns the interrupt into "initialization failed"). This module
imports nothing heavy and, while the command line loads, answers SIGINT by ending the process at once
with exit code 130 and no output: nothing has happened yet that needs finishing. Once loaded, Ctrl-C is
Python's again (``cell scan`` stops its arm and finishes its job folder).

Only the command named on the command line is loaded (:mod:`cell.cli.commands`); none when none is
(``cell --help`` lists them all from their sources) or the name is none of theirs (click then says so).
"""

from __future__ import annotations

import os
import signal
import sys
from types import FrameType

EXIT_INTERRUPTED = 130
"""Exit code after Ctrl-C (128 + SIGINT), as a shell reports a program that SIGINT ended."""


def _exit_interrupted(signum: int, frame: FrameType | None) -> None:
    os._exit(EXIT_INTERRUPTED)


def main() -> None:
    previous = signal.getsignal(signal.SIGINT)
    # Python's own handler only: a program started in the background keeps ignoring SIGINT
    quiet = previous is signal.default_int_handler
    if quiet:
        signal.signal(signal.SIGINT, _exit_interrupted)
    from cell.cli.commands import COMMANDS, cell_app, listing_app

    named = sys.argv[1] if len(sys.argv) > 1 else None
    app = cell_app([named]) if named in COMMANDS else listing_app()
    if quiet:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    app(prog_name="cell")


if __name__ == "__main__":
    main()
