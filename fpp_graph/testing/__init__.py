"""Synthetic pose graphs with known truth for tests and benchmark scripts (not used by the product)."""
