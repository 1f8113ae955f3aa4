"""Accuracy against ground truth: trajectory and map metrics (``metrics``), loop candidates
(``loops``), a results folder evaluated (``results``, behind ``fpp-slam eval``) and plots."""
