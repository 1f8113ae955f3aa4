"""What a user expects of ``fpp-slam`` as a command-line tool: ``--version`` prints the installed
version, and every command's ``--help`` shows example invocations that parse against the command.

The commands are discovered from the assembled application (built-ins, the ``config`` group's
subcommands and every ``fpp_graph.cli`` entry point), not listed here.
"""

from __future__ import annotations

import shlex
import subprocess
import sys
from importlib.metadata import entry_points, version
from pathlib import Path
from typing import Any

import pytest
import typer

from fpp_graph.cli.app import COMMANDS, DISTRIBUTION, PLUGIN_GROUP, add_commands, app, main
from fpp_graph.cli.common import EXAMPLE_WIDTH, continued_lines

EXE = Path(sys.executable).parent / "fpp-slam"
SHELL_OPERATORS = {">", ">>", "<", "|", "||", "&", "&&", ";"}


def _root_command() -> Any:
    add_commands()  # every command: built-ins, the config group, the plug-ins
    return typer.main.get_command(app)


def _leaf_commands(command: Any, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], Any]]:
    """(name path, click command) of every runnable command under ``command``."""
    subcommands = getattr(command, "commands", None)
    if not subcommands:
        return [(path, command)]
    return [leaf for name, sub in subcommands.items() for leaf in _leaf_commands(sub, (*path, name))]


COMMAND_PATHS = [path for path, _ in _leaf_commands(_root_command())]


def _command_at(path: tuple[str, ...]) -> Any:
    command = _root_command()
    for name in path:
        command = command.commands[name]
    return command


def example_lines(command: Any) -> list[str]:
    """The example invocations a command's help text and epilog hold: each line that starts with
    ``fpp-slam``, with its shell line continuations joined."""
    text = "\n".join(part for part in (command.help, command.epilog) if part).replace("\\\n", " ")
    return [" ".join(line.split()) for line in text.splitlines() if line.strip().startswith("fpp-slam ")]


def shell_words(command_line: str) -> list[str]:
    """The words of a command line as a POSIX shell splits them (a backslash-newline continues the
    line), up to a redirection or pipe."""
    lexer = shlex.shlex(command_line.replace("\\\n", ""), posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    words = []
    for word in lexer:
        if word in SHELL_OPERATORS:
            break
        words.append(word)
    return words


def parse_example(command_line: str) -> tuple[tuple[str, ...], dict[str, Any]]:
    """The command an example runs and the parameter values it parses to, without running it.

    Raises the command-line parser's usage error when the example names an option the command
    does not have, misses a required one, gives a bad value or too many arguments.
    """
    words = shell_words(command_line)
    assert words[:1] == ["fpp-slam"], command_line
    command, args, path = _root_command(), words[1:], ()
    while getattr(command, "commands", None):
        assert args and args[0] in command.commands, f"{command_line!r}: no command {args[:1]} under {' '.join(('fpp-slam', *path))}"
        path = (*path, args[0])
        command, args = command.commands[args[0]], args[1:]
    with command.make_context(" ".join(("fpp-slam", *path)), args) as ctx:
        return path, dict(ctx.params)


def test_version_prints_the_installed_distribution_version():
    expected = f"fpp-slam {version(DISTRIBUTION)}\n"
    for flag in ("--version", "-V"):
        proc = subprocess.run([str(EXE), flag], capture_output=True, text=True)
        assert (proc.returncode, proc.stdout, proc.stderr) == (0, expected, "")


def test_version_attaches_no_command_and_imports_nothing_heavy():
    probe = (
        "import importlib, sys\n"
        "app = importlib.import_module('fpp_graph.cli.app')\n"
        "code = app.main(['--version'])\n"
        "heavy = sorted(m for m in ('numpy', 'gtsam', 'open3d', 'cv2', 'frontend') if m in sys.modules)\n"
        "print(code, sorted(app._added), app._plugins_added, heavy)\n"
    )
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert proc.stdout.splitlines() == [f"fpp-slam {version(DISTRIBUTION)}", "0 [] False []"]


def test_version_without_an_installed_distribution_is_a_one_line_error(monkeypatch, capsys):
    import importlib.metadata

    def not_installed(name: str) -> str:
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", not_installed)
    assert main(["--version"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("fpp-slam: error: the fpp-graph distribution is not installed") and "pip install -e ." in captured.err
    assert len(captured.err.strip().splitlines()) == 1


def test_every_command_is_discovered():
    top_level = {path[0] for path in COMMAND_PATHS}
    assert {ep.name for ep in entry_points(group=PLUGIN_GROUP)} <= top_level
    assert set(COMMANDS) <= top_level
    assert {("config", "dump"), ("config", "defaults")} <= set(COMMAND_PATHS)


@pytest.mark.parametrize("path", COMMAND_PATHS, ids=" ".join)
def test_help_shows_examples_that_parse(path, capsys):
    assert main([*path, "--help"]) == 0
    shown = capsys.readouterr().out
    invocation = " ".join(("fpp-slam", *path))
    lines = example_lines(_command_at(path))
    assert lines, f"`{invocation} --help` shows no example invocation (a line starting with '{invocation}')"
    for line in lines:
        first_row = continued_lines(line).split(" \\\n")[0]
        assert first_row in shown, f"{line!r} is not in `{invocation} --help`"
        parsed_path, _ = parse_example(line)
        assert parsed_path == path, f"the example {line!r} in `{invocation} --help` runs another command"


def test_parse_example_refuses_an_example_the_command_would_refuse():
    # the check above can fail: an unknown option, a missing required one, a bad value, an extra argument
    path, params = parse_example("fpp-slam optimize graph.g2o --out 'my graph.g2o' --json > summary.json")
    assert path == ("optimize",)
    assert (params["graph_file"], params["out"], params["as_json"]) == (Path("graph.g2o"), Path("my graph.g2o"), True)
    for bad in (
        "fpp-slam optimize graph.g2o --output opt.g2o",
        "fpp-slam eval results/chess",
        "fpp-slam batch a --workers two",
        "fpp-slam config dump extra",
    ):
        with pytest.raises(Exception) as info:
            parse_example(bad)
        assert hasattr(info.value, "exit_code") and info.value.exit_code == 2, bad
    with pytest.raises(AssertionError):
        parse_example("fpp-slam config")


def test_long_examples_are_continued_between_options():
    line = (
        "fpp-slam import ../shared/data/real_fpp/procam_calibration --frames 'capture_*'"
        " --patterns datasets/patterns/procam_graycode_1024x768.yaml"
        " --calibration ../shared/data/real_fpp/procam_calibration/calibration_result.xml --reference --out out/procam"
    )
    continued = continued_lines(line)
    rows = continued.split("\n")
    assert all(len(row) <= EXAMPLE_WIDTH for row in rows), rows
    assert all(row.startswith("    ") for row in rows[1:])
    assert "    --frames 'capture_*' \\" in rows
    assert shell_words(continued) == shell_words(line)  # a shell reads the same words
    assert continued_lines("fpp-slam config defaults > my.yaml") == "fpp-slam config defaults > my.yaml"


def test_frontend_command_modules_import_light():
    # the examples decorator must not make the plug-in modules heavy (fpp-slam --help imports them)
    probe = (
        "import sys\n"
        "for name in ('frontend.commands.capture', 'frontend.commands.localize', 'frontend.commands.simulate'):\n"
        "    __import__(name)\n"
        "print(sorted(m for m in ('numpy', 'gtsam', 'open3d', 'cv2') if m in sys.modules))\n"
    )
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert proc.stdout.strip() == "[]"
