"""The ``cell`` command line, built with the commands it is asked for.

Each command lives in a module of its own (:data:`COMMANDS`) and is imported only when it runs: a scan
needs Open3D, SciPy and the planners, seconds of imports, which ``cell stop``, ``cell jobs`` (a client of
the service) or ``cell keys`` must not wait for. ``cell.cli.entry`` builds the command line with the one
command named on it (:func:`cell_app`), or, for ``cell --help``, no command or a mistyped name, with the
list of all of them (:func:`listing_app`): each command's help is read from its module's source, none is
imported (all of them took seconds).
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn, TypeVar

# Typer carries its own copy of Click (typer._click); its usage errors are of that copy's classes.
import typer
from typer._click import Context, Parameter
from typer._click.exceptions import UsageError
from typer.core import TyperCommand, TyperGroup

# Each command's name and where it lives (module:attribute), a function or a group of commands. ``cell
# --help`` lists them in this order, the single commands first and then the groups (Typer's order).
COMMANDS: dict[str, str] = {
    "scan": "cell.cli.scan:scan",
    "stop": "cell.cli.stop:stop",
    "reprocess": "cell.cli.reprocess:reprocess",
    "planners": "cell.cli.catalog:planners",
    "objects": "cell.cli.catalog:objects",
    "config": "cell.cli.config_check:config_app",
    "sensor": "cell.cli.sensor:sensor_app",
    "arm": "cell.cli.arm:arm_app",
    "calibrate": "cell.cli.calibrate:calibrate_app",
    "serve": "cell.cli.serve:serve",
    "jobs": "cell.cli.jobs:jobs_app",
    "line": "cell.cli.line:line_app",
    "keys": "cell.cli.keys:keys_app",
    "init": "cell.cli.init_cell:init",
    "backup": "cell.cli.backup:backup",
    "doctor": "cell.cli.doctor:doctor",
    "deploy": "cell.cli.deploy:deploy_app",
    "eval": "cell.cli.eval:eval_app",
}


EXIT_INPUT_ERROR = 1
"""The exit code of every ``cell`` command for an error in its input, a usage error of its command line
(unknown option, a value of the wrong type, a missing argument) as well as one the command finds: Click's
own code for a usage error, 2, is what ``cell scan`` documents for a scan that found no object."""

F = TypeVar("F", bound=Callable[..., Any])


@contextmanager
def _usage_errors_as_input_errors() -> Iterator[None]:
    """Give a usage error that passes through the exit code of an input error (``EXIT_INPUT_ERROR``);
    Typer still prints its message, with the usage line, to standard error."""
    try:
        yield
    except UsageError as exc:
        exc.exit_code = EXIT_INPUT_ERROR
        raise


def _flags_without_a_type(params: list[Parameter]) -> list[Parameter]:
    """``params`` with the flags' type column left empty in the help: Typer shows ``<bool>`` beside
    ``--help``, ``--wait`` or ``--all``, which reads as an option that takes a value (``--wait true``)."""
    for param in params:
        if isinstance(param, typer.core.TyperOption) and param.is_flag and param.metavar is None:
            param.metavar = ""  # what the help's type column shows instead of the type
    return params


class CellGroup(TyperGroup):
    """A ``cell`` command group: a usage error of its command line or of a command under it exits with
    ``EXIT_INPUT_ERROR``. Parsing happens in ``make_context`` (the group's own options) and, for the
    commands under it, in ``invoke``. Its flags show no type in the help (:func:`_flags_without_a_type`)."""

    def get_params(self, ctx: Context) -> list[Parameter]:
        return _flags_without_a_type(super().get_params(ctx))

    def make_context(self, info_name: str | None, args: list[str], parent: Context | None = None,
                     **extra: Any) -> Context:
        with _usage_errors_as_input_errors():
            return super().make_context(info_name, args, parent, **extra)

    def invoke(self, ctx: Context) -> Any:
        with _usage_errors_as_input_errors():
            return super().invoke(ctx)


class CellCommand(TyperCommand):
    """A ``cell`` command: an option that takes one value and is given more than once is refused (Click
    would keep the last one, silently: ``--planner vs-local --planner vs-global`` ran vs-global). Its
    flags show no type in the help (:func:`_flags_without_a_type`)."""

    def get_params(self, ctx: Context) -> list[Parameter]:
        return _flags_without_a_type(super().get_params(ctx))

    def parse_args(self, ctx: Context, args: list[str]) -> list[str]:
        given = list(args)  # Click's parser consumes the list it is given
        rest = super().parse_args(ctx, args)
        _, _, order = self.make_parser(ctx).parse_args(args=given)
        for param in dict.fromkeys(order):
            if isinstance(param, typer.core.TyperOption) and not (param.multiple or param.count
                                                                   or param.is_flag) \
                    and order.count(param) > 1:
                raise UsageError(f"option {param.opts[0]} was given {order.count(param)} times; it takes one "
                                 "value: give it once", ctx=ctx)
        return rest


class CellTyper(typer.Typer):
    """A Typer whose commands are :class:`CellCommand` s."""

    def command(self, name: str | None = None, *, cls: type[TyperCommand] | None = None,
                **options: Any) -> Callable[[F], F]:
        return super().command(name, cls=cls or CellCommand, **options)


DB_ENVVAR = "CELL_DB"
"""The environment variable a ``--db`` option is read from when not given: a store URL with a password
stays out of the process list (and a systemd unit's command line) when it is passed this way."""


def command_group(help: str, **options: Any) -> typer.Typer:
    """A command group (:class:`CellGroup` of :class:`CellCommand` s: a usage error exits with
    ``EXIT_INPUT_ERROR``, an option of one value given twice is refused) with ``help`` and typer's other
    ``options``, its commands' help read as Markdown:
    each paragraph wrapped to the terminal, units in brackets ("[m]", "[s]") kept. The commands' help
    is their docstrings, wrapped at the source's width, and rich's markup took the units for style tags
    and dropped them from the help."""
    return CellTyper(help=help, rich_markup_mode="markdown", cls=CellGroup, **options)


def _app() -> typer.Typer:
    app = command_group("Autonomous active-vision scanning cell.", no_args_is_help=True,
                        pretty_exceptions_enable=False)

    @app.callback()
    def cell() -> None:
        """Autonomous active-vision scanning cell."""

    return app


def command_help(location: str) -> tuple[str, bool]:
    """The help of the command at ``location`` (module:attribute, :data:`COMMANDS`) and whether it is a
    group, read from the module's source without importing it: the docstring of a function, or the
    ``help`` of a group's ``command_group(help=...)``. Raises ``LookupError`` when the source has neither."""
    module, attribute = location.split(":")
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        raise LookupError(f"{location}: no module {module}")
    for node in ast.parse(Path(spec.origin).read_text()).body:
        if isinstance(node, ast.FunctionDef) and node.name == attribute:
            return ast.get_docstring(node) or "", False
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call) \
                and any(isinstance(target, ast.Name) and target.id == attribute for target in node.targets):
            for keyword in node.value.keywords:
                if keyword.arg == "help" and isinstance(keyword.value, ast.Constant):
                    return str(keyword.value.value), True
    raise LookupError(f"{location}: neither a function with a docstring nor a command_group(help=...)")


def _not_loaded() -> NoReturn:
    raise RuntimeError("a command of the listing ran: cell.cli.entry loads a command before running it")


def listing_app() -> typer.Typer:
    """The ``cell`` command line that lists every command of :data:`COMMANDS` with its help
    (:func:`command_help`) and loads none: for ``cell --help``, no command or a name none of them has. A
    command named on the command line runs from :func:`cell_app`, never from here."""
    app = _app()
    for name, location in COMMANDS.items():
        text, group = command_help(location)
        if group:
            app.add_typer(command_group(text), name=name)
        else:
            app.command(name, help=text)(_not_loaded)
    return app


def cell_app(names: Iterable[str]) -> typer.Typer:
    """The ``cell`` command line with the commands ``names`` (keys of :data:`COMMANDS`), their modules
    imported."""
    app = _app()
    for name in names:
        module, attribute = COMMANDS[name].split(":")
        target = getattr(importlib.import_module(module), attribute)
        if isinstance(target, typer.Typer):
            app.add_typer(target, name=name)
        else:
            app.command(name)(target)
    return app
