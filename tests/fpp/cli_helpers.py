"""Running the capture commands of `fpp-slam` in-process, as a user would from the shell."""

from __future__ import annotations

import contextlib
import importlib
import io
from pathlib import Path

import yaml

from frontend.commands import capture as capture_commands
from frontend.fpp.pattern_file import FORMAT
from frontend.fpp.patterns import PatternSpec

app_module = importlib.import_module("fpp_graph.cli.app")  # the module (the package exports the Typer app under that name)

COMMANDS = {
    "patterns": capture_commands.patterns,
    "decode": capture_commands.decode,
    "calibrate": capture_commands.calibrate,
    "import": capture_commands.import_captures,
}


def _register() -> None:
    """The commands are entry-point plug-ins; attach them here too when the installed metadata
    predates them (an editable install made before they existed)."""
    app_module.add_commands()
    present = {c.name for c in app_module.app.registered_commands}
    for name, command in COMMANDS.items():
        if name not in present:
            app_module.app.command(name)(command)


def run_cli(*args: str) -> tuple[int, str, str]:
    """``fpp-slam ARGS``: (exit code, stdout, stderr)."""
    _register()
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = app_module.main(list(args))
    return code, out.getvalue(), err.getvalue()


def write_pattern_file(path: Path, spec: PatternSpec) -> Path:
    """A pattern file of ``spec`` with its explicit image order spelled out."""
    document = {"format": FORMAT, "description": "test capture", **spec.to_dict(), "order": [im.token() for im in spec.layout()]}
    for key in ("with_reference", "gray_inverse", "reference_position", "gray_order"):
        document.pop(key, None)
    path.write_text(yaml.safe_dump(document))
    return path
