"""Algorithms the evaluation scripts still compare against but the product does not use.

Nothing under ``fpp_graph/`` or ``frontend/`` imports from here; a script imports it as
``scripts.experimental.<module>``: run the scripts that use it as modules from the repository root (``python -m scripts.registration_acceptance``); the tests find it through pytest's ``pythonpath``.
"""
