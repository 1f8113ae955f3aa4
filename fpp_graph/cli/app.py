"""The ``fpp-slam`` application: its commands, and :func:`main`, which turns user errors into
one line.

Each command is a thin wrapper over a library function, defined in a module of this package
that does not import this one (dependencies run one way: app -> commands -> common). Heavy
modules (numpy, gtsam, Open3D, OpenCV) are imported inside the commands so that ``fpp-slam
--help`` stays instant. User errors (:class:`~fpp_graph.errors.FppError`) print one line on
stderr and exit 2, and so does an OSError on a path (:func:`~fpp_graph.outputs.os_error`). Front-ends add commands through the ``fpp_graph.cli`` entry-point group
(``fpp-slam demo`` is one). Every command gives example invocations with
:func:`~fpp_graph.cli.common.examples`, shown at the end of its ``--help``. ``fpp-slam
--version`` reads the installed distribution's metadata and attaches no command.
"""

from __future__ import annotations

import signal
import sys
import threading
from typing import Annotated

import typer

from fpp_graph.cli.common import examples_epilog, on_stop_signal, stop_signal
from fpp_graph.cli.config_commands import config_defaults, config_dump, config_plugins
from fpp_graph.cli.optimize import optimize_graph
from fpp_graph.cli.report import report
from fpp_graph.cli.run import batch, eval_, run
from fpp_graph.errors import FppError
from fpp_graph.outputs import os_error

PLUGIN_GROUP = "fpp_graph.cli"
DISTRIBUTION = "fpp-graph"
VERSION_OPTIONS = ("--version", "-V")

app = typer.Typer(
    name="fpp-slam",
    help="Millimetre-accurate indoor SLAM on fringe projection profilometry (FPP) sensors.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
config_app = typer.Typer(help="Inspect the configuration.", no_args_is_help=True)
config_app.command("dump", epilog=examples_epilog(config_dump))(config_dump)
config_app.command("defaults", epilog=examples_epilog(config_defaults))(config_defaults)
config_app.command("plugins", epilog=examples_epilog(config_plugins))(config_plugins)


def version_text() -> str:
    """``fpp-slam <version>``, the installed distribution's version.

    Raises
    ------
    FppError
        The ``fpp-graph`` distribution is not installed (the package imported from a source tree).
    """
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"fpp-slam {version(DISTRIBUTION)}"
    except PackageNotFoundError:
        raise FppError(f"the {DISTRIBUTION} distribution is not installed, so it has no version; install it with `pip install -e .` in the repository") from None


def _show_version(value: bool) -> None:
    if value:
        typer.echo(version_text())
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(*VERSION_OPTIONS, callback=_show_version, is_eager=True, help="Print the version and exit."),
    ] = False,
) -> None:
    """Millimetre-accurate indoor SLAM on fringe projection profilometry (FPP) sensors."""


#: The built-in commands, in the order ``--help`` lists them.
COMMANDS = {"optimize": optimize_graph, "run": run, "eval": eval_, "report": report, "batch": batch}
_added: set[str] = set()


def add_commands(names: list[str] | None = None) -> None:
    """Attach built-in commands (all by default, with the ``config`` group and the plug-ins).

    Typer turns every attached command's signature into a parser (with a pydantic validator
    per option) at each call, so a run attaches only the command it runs (``fpp-slam optimize``
    on a small graph is a process of about half a second).
    """
    for name in names if names is not None else [*COMMANDS, "config"]:
        if name in _added:
            continue
        _added.add(name)
        if name == "config":
            app.add_typer(config_app, name="config")
        else:
            app.command(name, epilog=examples_epilog(COMMANDS[name]))(COMMANDS[name])
    if names is None:
        add_plugin_commands()


_plugins_added = False


def add_plugin_commands() -> None:
    """Attach the commands front-ends register under the ``fpp_graph.cli`` entry points, once."""
    global _plugins_added
    if _plugins_added:
        return
    _plugins_added = True
    from importlib.metadata import entry_points

    for ep in entry_points(group=PLUGIN_GROUP):
        command = ep.load()
        app.command(ep.name, epilog=examples_epilog(command))(command)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``fpp-slam`` (and ``python -m fpp_graph.cli``): runs the app, turning
    FppError into one line + exit 2."""
    args = sys.argv[1:] if argv is None else list(argv)
    # only the command that runs (see add_commands); none for --version; everything for --help
    # or a plug-in command
    if args and args[0] in VERSION_OPTIONS:
        add_commands([])
    else:
        add_commands([args[0]] if args and args[0] in {*COMMANDS, "config"} else None)
    # SIGTERM (a scheduler, `kill`) takes the same path as Ctrl-C: the command's clean-up runs
    # (worker processes end, outputs stay whole) instead of the process vanishing mid-write
    # (only the main thread may set handlers: main() called from a worker thread runs without)
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = {sig: signal.signal(sig, on_stop_signal) for sig in (signal.SIGTERM, signal.SIGINT)} if in_main_thread else {}
    try:
        return _run_app(args)
    finally:  # main() called in-process (tests, scripts) leaves the caller's handlers as they were
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _run_app(args: list[str]) -> int:
    """The app on ``args``, with user errors, usage errors and stops turned into exit codes."""
    try:
        app(args=args, prog_name="fpp-slam", standalone_mode=False)
    except FppError as exc:
        typer.echo(f"fpp-slam: error: {exc}", err=True)
        return exc.exit_code
    except KeyboardInterrupt as exc:
        typer.echo("fpp-slam: interrupted", err=True)
        return 128 + getattr(exc, "signal_number", signal.SIGINT)
    except typer.Exit as exc:  # raised by --help and typer.Exit(code)
        return int(exc.exit_code or 0)
    except OSError as exc:  # a path the command did not translate itself: still one line naming it
        if stop_signal() is not None:
            typer.echo("fpp-slam: interrupted", err=True)
            return 128 + stop_signal()
        error = os_error(exc, reading=None)
        typer.echo(f"fpp-slam: error: {error}", err=True)
        return error.exit_code
    except Exception as exc:
        if stop_signal() is not None:  # stopped inside a C extension, which raised its own error
            typer.echo("fpp-slam: interrupted", err=True)
            return 128 + stop_signal()
        # Usage errors of the click engine under typer (vendored in recent typer releases, so
        # matched by behaviour rather than by class): they know how to show themselves.
        if callable(getattr(exc, "show", None)) and isinstance(getattr(exc, "exit_code", None), int):
            exc.show()
            return int(exc.exit_code)
        if type(exc).__name__ == "Abort":  # the click engine's wrapper of KeyboardInterrupt
            typer.echo("fpp-slam: interrupted", err=True)
            return 128 + getattr(exc.__context__, "signal_number", signal.SIGINT)
        raise
    return 0
