"""What every ``fpp-slam`` command shares: options, logging set-up, progress bars, tables.

Module-level imports stay light (typer only) so that ``fpp-slam --help`` is instant.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Optional, TypeVar

import typer

ConfigOption = Annotated[
    Optional[Path],  # noqa: UP045 - typer needs Optional on 3.11
    typer.Option("--config", "-c", help="YAML file overriding the packaged defaults."),
]
OutOption = Annotated[Optional[Path], typer.Option("--out", "-o", help="Results folder (default: results/<sequence>-<time>).")]  # noqa: UP045


CommandFunction = TypeVar("CommandFunction", bound=Callable[..., Any])

#: The attribute :func:`examples` sets on a command function, read when the command is attached.
EXAMPLES_ATTRIBUTE = "fpp_slam_examples"


def examples(*command_lines: str) -> Callable[[CommandFunction], CommandFunction]:
    """Decorator: example invocations that ``fpp-slam COMMAND --help`` shows below the options.

    Each line is one whole command line as a user types it (``fpp-slam run DIR --out DIR``); a
    shell redirection or pipe may follow it. The line must parse against the command's options
    (``tests/test_cli_conventions.py`` checks every one). Front-end commands (the ``fpp_graph.cli``
    entry points) use it too.
    """

    def attach(command: CommandFunction) -> CommandFunction:
        setattr(command, EXAMPLES_ATTRIBUTE, tuple(command_lines))
        return command

    return attach


#: Examples longer than this are continued on further lines (`` \\`` then 4 spaces), so that they
#: stay whole, and can be pasted into a shell, in an 80-column terminal (the help's margins take 2).
EXAMPLE_WIDTH = 76


def examples_epilog(command: Callable[..., Any]) -> str | None:
    """The ``--help`` epilog listing a command's :func:`examples`, or None without any.

    Examples are separated by blank lines (typer's rich help shows each paragraph on lines of its
    own); a long one is broken between words with shell line continuations.
    """
    lines = getattr(command, EXAMPLES_ATTRIBUTE, ())
    return "\n\n".join(["Examples:", *map(continued_lines, lines)]) if lines else None


def continued_lines(command_line: str, width: int = EXAMPLE_WIDTH) -> str:
    """``command_line`` broken into lines of at most ``width`` characters where it can be, joined
    by `` \\`` + newline + 4 spaces as a shell reads them. Breaks fall before an option (which
    keeps its value on its line unless the two do not fit on one), a redirection or a positional
    argument, never inside a word."""
    units: list[str] = []
    for word in command_line.split():
        starts_unit = word.startswith("-") or word in {">", ">>", "|"} or not units or not units[-1].startswith(("-", ">", "|"))
        if starts_unit:
            units.append(word)
        else:
            units[-1] += " " + word
    rows: list[str] = []
    for unit in units:
        if rows and len(rows[-1]) + 1 + len(unit) + 2 <= width:
            rows[-1] += " " + unit
        elif rows and len(unit) + 6 > width:  # an option with a long value: the value on its own line
            rows.extend("    " + word for word in unit.split(" "))
        else:
            rows.append("    " + unit if rows else unit)
    return " \\\n".join(rows)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program is, so that clean-up runs as for Ctrl-C."""

    signal_number = signal.SIGTERM


_stop_signal: int | None = None  # the signal that is stopping the command, once one came


def on_stop_signal(signum: int, frame: object) -> None:
    """Handler for SIGTERM (and the record of Ctrl-C): raise where the program is."""
    global _stop_signal
    _stop_signal = signum
    if signum == signal.SIGINT:
        raise KeyboardInterrupt()
    raise Terminated()


def stop_signal() -> int | None:
    """The signal that is stopping the command, if any. A signal can land inside a C extension's
    import or call, which then reports its own error (``ImportError: initialization failed``)
    instead of the KeyboardInterrupt: the command is being stopped all the same."""
    return _stop_signal


def setup_logging(level: str = "INFO", log_file: Path | None = None) -> None:
    """Configure logging for the CLI: rich console handler on stderr, optional file handler."""
    from rich.console import Console
    from rich.logging import RichHandler

    # stderr: stdout carries results (--json) that log lines must not corrupt
    handlers: list[logging.Handler] = [RichHandler(console=Console(stderr=True), show_path=False, rich_tracebacks=False)]
    if log_file is not None:
        log_file.parent.mkdir(parents=True, exist_ok=True)
        file_handler = logging.FileHandler(log_file, encoding="utf-8")
        file_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        handlers.append(file_handler)
    logging.basicConfig(level=level, handlers=handlers, format="%(message)s", force=True)


def default_out(sequence: Path) -> Path:
    """``results/<sequence name>-<local time>``."""
    return Path("results") / f"{sequence.stem or sequence.name}-{time.strftime('%Y%m%d-%H%M%S')}"


class RichProgress:
    """Progress bars per stage with items/s: a ``fpp_graph.slam.pipeline.ProgressCallback`` for the CLI."""

    def __init__(self) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
        )

        self.progress = Progress(
            TextColumn("{task.description:>9}"), BarColumn(), MofNCompleteColumn(),
            TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), transient=False,
        )
        self.tasks: dict[str, Any] = {}
        self.started: dict[str, float] = {}

    def __enter__(self) -> RichProgress:
        self.progress.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.progress.__exit__(*exc)

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage not in self.tasks:
            self.tasks[stage] = self.progress.add_task(stage, total=total, rate="")
            self.started[stage] = time.perf_counter()
        elapsed = max(time.perf_counter() - self.started[stage], 1e-9)
        self.progress.update(self.tasks[stage], completed=done, total=total, rate=f"{done / elapsed:.2f}/s")


def print_metrics_table(metrics: dict[str, Any], title: str = "fpp-slam evaluation") -> None:
    """A two-column table of figures (floats to 4 decimals) on stdout."""
    from rich.console import Console
    from rich.table import Table

    def shown(value: Any) -> str:
        if isinstance(value, float):
            return f"{value:.4f}"
        if isinstance(value, list):
            return ", ".join(shown(v) for v in value)
        if isinstance(value, dict):
            return ", ".join(f"{k}={shown(v)}" for k, v in value.items())
        return str(value)

    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key, value in metrics.items():
        table.add_row(key, shown(value))
    Console().print(table)
