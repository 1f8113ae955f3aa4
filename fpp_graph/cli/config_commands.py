"""``fpp-slam config dump | defaults``."""

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
