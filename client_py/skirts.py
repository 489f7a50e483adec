"""Skirts: walls hung under a detail region's inner borders, so no crack shows beside it.

The viewer draws the refined surface as a patchwork of quadtree regions, each
tessellated on its own grid with the detail tiles of its own level and the
coarser ones (:func:`client_py.layers.tessellate_region`). Two neighbours of
different levels do not meet exactly on their common border: each applies its
own partial sum of the detail fields there. :func:`hang_skirts` adds, below
each border of a region that lies inside the domain, a wall deep enough to
hide the gap from the front.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterable, Sequence

from .layers import DetailTile, RegionSamples, sample_region
from .surface import NurbsSurface
from .tessellate import Mesh, _check_count


def hang_skirts(mesh: Mesh, surface: NurbsSurface, uv_rect: Sequence[float], n: int,
                tiles: Iterable[DetailTile], depth: float, kernel: str | None = None,
                samples: RegionSamples | None = None) -> Mesh:
    """Hang skirts (in the patch frame) from a region's borders inside the domain.

    Under each border vertex ``S`` (the base at the border's parameter, ``n``
    its unit normal) a wall runs from the region's own edge ``S + P_k n`` down to

        S + (min_l P_l - depth) n,    P_l = sum_{k' <= l} D_k',   l = -1 .. k,

    the partial sums of the region's tiles by level (``P_-1 = 0``: the base).
    A coarser neighbour shows some ``P_l`` there (tiles of one level agree on
    their borders), a finer one lies within about twice the region's remaining
    error (``depth``) of ``P_k``; whichever edge is higher, its wall hangs past
    the other, so no crack shows from the front. The walls never rise above the
    edge they hang from (no fins). Borders on the domain's outer edge get none
    (nothing to meet there), nor do segments whose inward grid cell the base's
    trim leaves out (or a tile's walls mask: ``client_py.layers.DetailTile``); where
    the base's analytic normal vanishes (a pole) the wall has no height.

    Parameters
    ----------
    mesh : Mesh
        The region's mesh from ``tessellate_region(surface, uv_rect, n, n,
        tiles)``, patch frame: ``n * n`` grid vertices, vertex ``k = a n + b``
        at ``(u_a, v_b)``. Extended in place.
    surface : NurbsSurface
        The base patch, in its own frame.
    uv_rect : (u0, v0, u1, v1)
        The region in the normalised domain ``[0, 1]^2``.
    n : int
        Vertices per side of the region's grid.
    tiles : iterable of DetailTile
        The tiles applied to the region (each covers it).
    depth : float
        How far (patch units, ``>= 0``) below the lowest partial sum the walls reach.
    kernel : str, optional
        ``'python'`` or ``'numpy'``; default the selected kernel.
    samples : RegionSamples, optional
        The region's samples the mesh was made from
        (:func:`client_py.layers.sample_region` with the same arguments): the base
        and the level fields at the border vertices are read from them instead
        of being evaluated again.

    Returns
    -------
    Mesh
        ``mesh`` with ``2 n`` vertices per skirted side appended (the wall's
        bottom, then its top, for each border vertex; normals, uvs and colours
        copied from the border vertex) and two triangles per kept segment.
    """
    u0, v0, u1, v1 = (float(x) for x in uv_rect)
    n = _check_count("n", n)
    depth = float(depth)
    if not math.isfinite(depth) or depth < 0.0:
        raise ValueError(f"depth must be a finite length >= 0, got {depth!r}")
    if mesh.vertex_count != n * n:
        raise ValueError(f"mesh has {mesh.vertex_count} vertices; an {n}x{n} grid has {n * n}")
    tiles = list(tiles)
    if samples is None:
        samples = sample_region(surface, uv_rect, n, n, tiles, kernel)
    elif (len(samples.us), len(samples.vs)) != (n, n) or \
            tuple(samples.uv_rect) != (u0, v0, u1, v1):
        raise ValueError(f"samples are of a {len(samples.us)}x{len(samples.vs)} grid over "
                         f"{samples.uv_rect}, not of the {n}x{n} grid over {tuple(uv_rect)}")
    us, vs = samples.us, samples.vs
    trim = surface.trim
    half_u, half_v = 0.5 * (u1 - u0) / (n - 1), 0.5 * (v1 - v0) / (n - 1)
    # (grid vertex (a, b) of the side's s-th vertex, inward cell centre of segment s,
    # the grid vertex that cell's triangles start from)
    sides = []
    if u0 > 0.0:
        sides.append((lambda s: (0, s), lambda s: (u0 + half_u, vs[s] + half_v),
                      lambda s: s))
    if u1 < 1.0:
        sides.append((lambda s: (n - 1, s), lambda s: (u1 - half_u, vs[s] + half_v),
                      lambda s: (n - 2) * n + s))
    if v0 > 0.0:
        sides.append((lambda s: (s, 0), lambda s: (us[s] + half_u, v0 + half_v),
                      lambda s: s * n))
    if v1 < 1.0:
        sides.append((lambda s: (s, n - 1), lambda s: (us[s] + half_u, v1 - half_v),
                      lambda s: s * n + n - 2))
    # a walls mask may leave out a cell the trim covers: then no skirt hangs from it either
    walled = any(t.walls is not None for t in tiles)
    drawn = set(mesh.indices[0::6]) if walled else None
    points, normals, poles = samples.positions, samples.normals, set(samples.degenerate)
    fields = [field for _, field in samples.levels]
    pos, nrm, uv, idx = mesh.positions, mesh.normals, mesh.uvs, mesh.indices
    for vertex, inward, cell in sides:
        first = len(pos) // 3
        walls = []
        for s in range(n):
            a, b = vertex(s)
            at = samples.vertex(a, b)
            partial = lowest = 0.0
            for f in fields:
                partial += f[at]
                lowest = min(lowest, partial)
            lo, hi = lowest - depth, partial
            p = points[3 * at : 3 * at + 3]
            q = (0.0, 0.0, 0.0) if at in poles else normals[3 * at : 3 * at + 3]
            walls += (p[0] + lo * q[0], p[1] + lo * q[1], p[2] + lo * q[2],
                      p[0] + hi * q[0], p[1] + hi * q[1], p[2] + hi * q[2])
            k = a * n + b
            nrm.extend(nrm[3 * k : 3 * k + 3] * 2)
            uv.extend(uv[2 * k : 2 * k + 2] * 2)
            if mesh.colors is not None:
                mesh.colors.extend(mesh.colors[3 * k : 3 * k + 3] * 2)
        pos.extend(array("f", walls))
        for s in range(n - 1):
            if trim is not None and not trim.covers(*inward(s)) \
                    or drawn is not None and cell(s) not in drawn:
                continue
            a, b = first + 2 * s, first + 2 * s + 2
            idx.extend(array("I", (a, b, b + 1, a, b + 1, a + 1)))
    return mesh
