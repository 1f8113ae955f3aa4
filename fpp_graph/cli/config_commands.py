"""``fpp-slam config dump | defaults``."""

from __future__ import annotations

import typer

from fpp_graph.cli.common import ConfigOption


def config_dump(config: ConfigOption = None) -> None:
    """Print the resolved configuration (defaults overridden by --config) as YAML."""
    from fpp_graph.config import dump_config, load_config

    typer.echo(dump_config(load_config(config)), nl=False)


def config_defaults() -> None:
    """Print the documented default configuration file, with its comments."""
    from fpp_graph.config import default_config_text

    typer.echo(default_config_text(), nl=False)
