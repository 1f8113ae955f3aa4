"""``fpp-slam`` commands the FPP front-end contributes (entry-point group ``fpp_graph.cli``).

The back-end package must not import the front-end, so these register as plug-ins, as
``fpp-slam demo`` does. Module-level imports stay light (typer) so ``fpp-slam --help`` is instant.
"""
