"""Structural checks of a pose graph before it reaches the solver.

GTSAM reports an under-constrained problem as ``IndeterminantLinearSystemException`` naming one
"nearby variable", which says little about the cause. Every such case in a pose graph is
structural: a part of the graph that no edge ties to an anchor (a fixed pose or a prior). This
module finds those parts (scipy's csgraph) and says which poses they hold, so the error names them
all and says what to do.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Iterable, Sequence

import numpy as np

from fpp_graph.errors import GraphError

log = logging.getLogger(__name__)


def connected_parts(keys: Iterable[int], edges: Iterable[tuple[int, int]]) -> list[list[int]]:
    """Connected parts of the graph, each a sorted list of keys, ordered by their smallest key."""
    # scipy's csgraph, not networkx: this runs before every solve, and networkx costs ~70 ms of
    # import in a command that otherwise takes well under a second on small graphs
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    key_list = list(dict.fromkeys(int(k) for k in keys))
    index = {k: n for n, k in enumerate(key_list)}
    pairs = np.array([(index[int(u)], index[int(v)]) for u, v in edges], dtype=np.int64).reshape(-1, 2)
    n = len(key_list)
    adjacency = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(adjacency, directed=False)
    parts: dict[int, list[int]] = {}
    for key, label in zip(key_list, labels, strict=True):
        parts.setdefault(int(label), []).append(key)
    return sorted((sorted(part) for part in parts.values()), key=lambda part: part[0])


def _describe(part: Sequence[int], limit: int = 6) -> str:
    if len(part) == 1:
        return f"pose {part[0]}"
    if len(part) <= limit:
        return "poses " + ", ".join(str(k) for k in part)
    return f"{len(part)} poses {part[0]}..{part[-1]}"


def check_constrained(
    keys: Sequence[int],
    edges: Iterable[tuple[int, int]],
    anchored: Collection[int],
) -> int | None:
    """Check that every pose is tied to an anchor; return a key to fix for the gauge, if needed.

    Parameters
    ----------
    keys : sequence of int
        All pose keys of the graph.
    edges : iterable of (int, int)
        Key pairs of the relative-pose edges (full-rank information is assumed, checked on add).
    anchored : collection of int
        Keys with a hard anchor (fixed pose) or a full-rank prior.

    Returns
    -------
    int or None
        When the graph has no anchor at all but is connected, the smallest key: fixing it removes
        the 6-DoF gauge freedom without changing the optimum. ``None`` when anchors are present.

    Raises
    ------
    GraphError
        The graph is empty, or some part has no anchor while the graph is not one connected part
        (the message names every unconstrained part and its poses).
    """
    if not keys:
        raise GraphError("the pose graph has no poses; add poses (and constraints) before optimising")
    parts = connected_parts(keys, edges)
    anchored_set = set(anchored)
    floating = [part for part in parts if not anchored_set.intersection(part)]
    if not floating:
        return None
    if len(parts) == 1:
        log.debug("pose graph has no anchor: fixing pose %d to remove the gauge freedom", parts[0][0])
        return parts[0][0]
    isolated = [part[0] for part in floating if len(part) == 1]
    groups = [part for part in floating if len(part) > 1]
    problems = []
    if isolated:
        shown = ", ".join(str(k) for k in isolated[:20]) + (" ..." if len(isolated) > 20 else "")
        problems.append(f"{len(isolated)} unconstrained pose(s) with no edge and no prior: {shown}")
    if groups:
        shown = "; ".join(_describe(part) for part in groups[:10]) + (" ..." if len(groups) > 10 else "")
        problems.append(f"{len(groups)} part(s) not tied to any anchor: {shown}")
    anchored_parts = len(parts) - len(floating)
    raise GraphError(
        f"the pose graph is not fully constrained: it has {len(parts)} disconnected parts "
        f"({anchored_parts} anchored); " + "; ".join(problems)
        + "; connect the parts with constraints, anchor each part (fix_pose or add_prior), "
        "or optimise the parts separately"
    )
