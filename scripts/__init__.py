"""Evaluation and benchmark scripts; each prints its figures. Run from the repository root,
either as files (``.venv/bin/python scripts/NAME.py``) or as modules (``.venv/bin/python -m
scripts.NAME``; needed by the scripts that import ``scripts.experimental``)."""
