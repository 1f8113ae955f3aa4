"""Synthetic inputs for tests and scripts (fast stand-ins for the simulator): frames rendered
from simple meshes, fringe captures of analytic surfaces. Not used by the product."""
