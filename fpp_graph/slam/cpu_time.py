"""CPU time of this process and of its children that have ended (Unix ``getrusage``): what a run
with its own worker pool spent on all its cores, once the pool has been shut down."""

from __future__ import annotations


def process_tree_cpu_s() -> float | None:
    """User + system seconds of this process and its waited-for children (None without
    ``resource``: not Unix). A pool's workers count once it has joined them."""
    try:
        import resource
    except ImportError:
        return None
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime
