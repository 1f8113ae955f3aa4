"""Structural checks of a pose graph before it reaches the solver.

GTSAM reports an under-constrained problem as ``IndeterminantLinearSystemException`` naming one
"nearby variable", which says little about the cause. Every such case in a pose graph is
structural: a part of the graph that no edge ties to an anchor (a fixed pose or a prior). This
module finds those parts (:func:`component_labels`) and says which poses they hold, so the error
names them all and says what to do.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Iterable, Sequence

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import GraphError

log = logging.getLogger(__name__)


def component_labels(n: int, ends: NDArray[np.int64]) -> NDArray[np.int64]:
    """Connected components of an undirected graph on nodes ``0..n-1`` with edges ``ends`` (m, 2):
    each node's label is the smallest node of its component.

    A union-find with path halving, written out rather than taken from
    ``scipy.sparse.csgraph``: that package imports ``scipy.sparse.linalg`` and ``scipy.linalg``
    (~65 ms), a tenth of a whole ``fpp-slam optimize`` process on a small graph, and this runs
    before every solve. Linear in the edges (~1 us per edge).
    """
    root = list(range(n))

    def find(x: int) -> int:
        while root[x] != x:
            root[x] = root[root[x]]
            x = root[x]
        return x

    for a, b in np.asarray(ends, dtype=np.int64).reshape(-1, 2).tolist():
        ra, rb = find(a), find(b)
        if ra != rb:  # the smaller node becomes the root, so a root is its component's minimum
            root[max(ra, rb)] = min(ra, rb)
    return np.array([find(x) for x in range(n)], dtype=np.int64)


def connected_parts(keys: Iterable[int], edges: Iterable[tuple[int, int]]) -> list[list[int]]:
    """Connected parts of the graph, each a sorted list of keys, ordered by their smallest key."""
    key_list = list(dict.fromkeys(int(k) for k in keys))
    index = {k: n for n, k in enumerate(key_list)}
    pairs = np.array([(index[int(u)], index[int(v)]) for u, v in edges], dtype=np.int64).reshape(-1, 2)
    labels = component_labels(len(key_list), pairs)
    parts: dict[int, list[int]] = {}
    for key, label in zip(key_list, labels.tolist(), strict=True):
        parts.setdefault(label, []).append(key)
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
        the gauge freedom (6 degrees of freedom; 3 in a planar graph) without changing the optimum.
        ``None`` when anchors are present.

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
