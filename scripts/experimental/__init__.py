"""Algorithms the evaluation scripts still compare against but the product does not use.

Nothing under ``fpp_graph/`` or ``frontend/`` imports from here; a script imports it as
``scripts.experimental.<module>`` (the scripts put the repository root on ``sys.path``).
"""
