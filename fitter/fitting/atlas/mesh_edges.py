"""The directed edges of a triangle mesh, each paired with its twin by one sort.

Face ``t = (a, b, c)`` has the directed edges ``a→b``, ``b→c``, ``c→a`` in slots 0, 1, 2;
edge ``e = j M + t`` (``M`` faces) is slot ``j`` of face ``t``, and is also the *corner*
``(t, j)`` at its tail ``faces[t, j]``. Sorting the edges by their undirected key
``min(a, b) N + max(a, b)`` (``N`` vertices) with the direction as the lowest bit groups
each undirected edge's uses: one use is a border edge, more than two a non-manifold edge,
two uses the same way a misoriented pair, and two opposite uses are twins.

Around a vertex ``v`` of an edge-manifold, coherently oriented mesh, the corner ``(t, j)``
whose edge runs ``v→w`` is followed by the corner at ``v`` of the face across that edge
(the face holding ``w→v``): :func:`vertex_fans` follows these links, by pointer jumping
(each pass doubles the steps taken; Wyllie's list ranking), to count the fans of faces
that meet at each vertex. One fan per used vertex and no bad edge is a 2-manifold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MeshEdges:
    """The directed edges of ``faces`` grouped by undirected edge (module docstring).

    Attributes
    ----------
    faces : ndarray, shape (M, 3), int64
    tails : ndarray, shape (3 M,), int64
        The vertex each directed edge (and corner) starts at.
    uses : ndarray, shape (3 M,), int64
        How many directed edges share each one's undirected edge.
    twins : ndarray, shape (3 M,), int64
        The twin of each directed edge (the other face's use, run the other way) where its
        undirected edge has exactly two uses run opposite ways, else ``-1``.
    problems : dict
        ``nonmanifold_edges`` (undirected edges of more than two faces), ``misoriented_edges``
        (directed edges used more than once, each counted once), ``border_edges`` (of one
        face) and ``edges`` (undirected).
    """

    faces: np.ndarray
    tails: np.ndarray
    uses: np.ndarray
    twins: np.ndarray
    problems: dict

    @property
    def border(self) -> np.ndarray:
        """Which directed edges are the only use of their undirected edge, shape (3 M,)."""
        return self.uses == 1


def mesh_edges(faces: np.ndarray) -> MeshEdges:
    """:class:`MeshEdges` of ``faces (M, 3)``: one stable argsort of the ``3 M`` keys."""
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    m = len(faces)
    tails = faces.T.reshape(-1)
    heads = faces[:, [1, 2, 0]].T.reshape(-1)
    n = int(faces.max(initial=-1)) + 1
    key = (np.minimum(tails, heads) * n + np.maximum(tails, heads)) * 2 + (tails > heads)
    order = np.argsort(key)
    ranked = key[order]
    undirected = ranked >> 1
    starts = np.flatnonzero(np.r_[True, undirected[1:] != undirected[:-1]]) if m else \
        np.zeros(0, np.int64)
    sizes = np.diff(np.r_[starts, len(ranked)])
    uses = np.empty(3 * m, np.int64)
    uses[order] = np.repeat(sizes, sizes)
    same = ranked[1:] == ranked[:-1]  # a directed edge used again
    misoriented = int(np.count_nonzero(same & ~np.r_[False, same[:-1]]))
    twins = np.full(3 * m, -1, np.int64)
    pair = starts[(sizes == 2)]
    pair = pair[ranked[pair] != ranked[pair + 1]]
    twins[order[pair]] = order[pair + 1]
    twins[order[pair + 1]] = order[pair]
    problems = {"nonmanifold_edges": int(np.count_nonzero(sizes > 2)),
                "misoriented_edges": misoriented,
                "border_edges": int(np.count_nonzero(sizes == 1)), "edges": len(starts)}
    return MeshEdges(faces, tails, uses, twins, problems)


def vertex_fans(table: MeshEdges, n_vertices: int) -> np.ndarray:
    """The fans of faces meeting at each vertex, shape ``(n_vertices,)`` (0 where no face
    is), of an edge-manifold, coherently oriented mesh (``table.problems`` with no
    non-manifold or misoriented edge; else the counts mean nothing).

    A fan is a cycle of corners (an inner vertex) or a chain ending at a border edge.
    Pointer jumping gives each corner the smallest corner of its cycle, or its chain's
    last corner, in ``ceil(log2(largest valence)) + 1`` passes; each fan is counted at the
    one corner that is its own label."""
    m = len(table.faces)
    corner = np.arange(3 * m, dtype=np.int64)
    across = table.twins
    has = across >= 0
    # the corner at the same vertex of the face across: that face's slot after the twin's
    follow = np.where(has, ((across // max(m, 1)) + 1) % 3 * m + across % max(m, 1), corner)
    valence = np.bincount(table.tails, minlength=n_vertices)
    passes = int(np.ceil(np.log2(max(int(valence.max(initial=1)), 1)))) + 1
    label, step = corner.copy(), follow
    for _ in range(passes):
        label = np.minimum(label, label[step])
        step = step[step]
    chain = ~has[step]  # the corner reached is a chain's end (no face across)
    label = np.where(chain, step, label)
    own = label == corner
    return np.bincount(table.tails[own], minlength=n_vertices)
