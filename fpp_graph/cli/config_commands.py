"""``fpp-slam config dump | defaults | plugins``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from fpp_graph.cli.common import ConfigOption, examples

SequenceOption = Annotated[
    Optional[Path],  # noqa: UP045 - typer reads the annotation at runtime
    typer.Option(
        "--sequence", "-s",
        help="Resolve for this sequence's sensor: the values a run on it uses (its noise model where the config leaves it null).",
    ),
]


@examples(
    "fpp-slam config dump --config my.yaml",
    "fpp-slam config dump --sequence ../shared/data/rgbd/tum_fr1_rpy_subset",
)
def config_dump(config: ConfigOption = None, sequence: SequenceOption = None) -> None:
    """Print the resolved configuration (defaults overridden by --config) as YAML."""
    from fpp_graph.config import dump_config, load_config

    cfg = load_config(config)
    if sequence is not None:
        from fpp_graph.slam.sources import open_source

        cfg = open_source(sequence, cfg).resolve_config(cfg)
    typer.echo(dump_config(cfg), nl=False)


@examples("fpp-slam config defaults > my.yaml")
def config_defaults() -> None:
    """Print the documented default configuration file, with its comments."""
    from fpp_graph.config import default_config_text

    typer.echo(default_config_text(), nl=False)


@examples(
    "fpp-slam config plugins",
    "fpp-slam config plugins --config my.yaml",
)
def config_plugins(config: ConfigOption = None) -> None:
    """List the names each plug-in point takes (plugins.loop_detector, .registrar, .map_fuser):
    null and the names registered under its entry-point group; * marks the one in use. With
    --config, the plug-ins it selects are loaded (one that cannot be is an error)."""
    from fpp_graph.config import load_config
    from fpp_graph.plugins import POINTS, check_plugins, registered_plugins

    cfg = load_config(config)
    if config is not None:
        check_plugins(cfg)  # a selection that cannot load: one line, exit 2
    for key, names in registered_plugins().items():
        chosen = getattr(cfg.plugins, key)
        typer.echo(f"plugins.{key}: entry points {POINTS[key].group}")
        rows = {"null": f"built-in: {POINTS[key].builtin}", **dict(sorted(names.items()))}
        if chosen is not None and chosen not in names:
            rows[chosen] = "module:attribute"
        for name, value in rows.items():
            typer.echo(f"  {'*' if name == (chosen or 'null') else ' '} {name} = {value}")
