"""The ``fpp-slam`` command line (:mod:`fpp_graph.cli.app`) and what its commands share
(:mod:`fpp_graph.cli.common`), for front-ends that contribute commands."""

from fpp_graph.cli.app import app, main
from fpp_graph.cli.common import RichProgress, print_metrics_table, setup_logging

__all__ = ["RichProgress", "app", "main", "print_metrics_table", "setup_logging"]
