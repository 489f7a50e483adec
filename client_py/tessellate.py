"""Tessellation of a ``NurbsSurface`` into a triangle ``Mesh`` held in flat ``array.array``s.

The arrays expose the buffer protocol, so Pyodide's ``PyProxy.getBuffer`` hands
them to JavaScript as ``Float32Array``/``Uint32Array`` without a copy.
"""

from __future__ import annotations

from array import array
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from . import _kernel
from .surface import NurbsSurface
from .trim import TrimMask

MAX_GRID = 8192  # vertices per side: 67 M vertices, far past any screen


@dataclass
class Mesh:
    """Indexed triangle mesh.

    Attributes
    ----------
    positions, normals : array('f'), ``3 * n_vertices``
        ``x, y, z`` and unit normal per vertex.
    uvs : array('f'), ``2 * n_vertices``
        Surface parameters ``(u, v)`` of each vertex.
    indices : array('I'), ``3 * n_triangles``
        Counter-clockwise seen from the side the normals point to.
    colors : array('B') or None, ``3 * n_vertices``
        Optional 8-bit RGB per vertex.
    """

    positions: array
    normals: array
    uvs: array
    indices: array
    colors: array | None = field(default=None)

    @property
    def vertex_count(self) -> int:
        return len(self.positions) // 3

    @property
    def triangle_count(self) -> int:
        return len(self.indices) // 3


def _samples(lo: float, hi: float, count: int) -> list[float]:
    step = (hi - lo) / (count - 1)
    return [lo + k * step for k in range(count - 1)] + [hi]


def _check_count(name: str, count: object) -> int:
    if isinstance(count, bool) or not isinstance(count, int):
        raise ValueError(f"{name} must be an integer, got {count!r}")
    if not 2 <= count <= MAX_GRID:
        raise ValueError(f"{name} = {count}; a grid needs 2 to {MAX_GRID} vertices per side")
    return count


def grid_indices(nu: int, nv: int, keep_cell=None, kernel: str | None = None) -> array:
    """Triangles of an ``nu x nv`` vertex grid (vertex ``k = i * nv + j``).

    Cell ``(i, j)`` gives ``(k, k + nv, k + 1)`` and ``(k + 1, k + nv, k + nv + 1)``:
    both turn counter-clockwise about ``S_u x S_v``. ``keep_cell(i, j)`` may
    leave cells out (trimming; called once per cell: a mask is far faster as a
    cover of :func:`client_py._kernel_python.cell_indices`, see
    :func:`trimmed_grid_indices`).
    """
    if keep_cell is None:
        return _kernel.backend(kernel).cell_indices(nu, nv)
    indices = array("I")
    for i in range(nu - 1):
        for j in range(nv - 1):
            if keep_cell(i, j):
                k = i * nv + j
                indices.extend((k, k + nv, k + 1, k + 1, k + nv, k + nv + 1))
    return indices


def mask_indices(centres: Sequence[float], count: int) -> list[int]:
    """The cell of a ``count``-cell mask side holding each normalised coordinate in ``centres``:
    ``min(int(t count), count - 1)`` (and ``>= 0``), as :meth:`TrimMask.covers` picks it."""
    last = count - 1
    return [max(min(int(t * count), last), 0) for t in centres]


def trimmed_grid_indices(nu: int, nv: int, trim: TrimMask, kernel: str | None = None) -> array:
    """:func:`grid_indices` without the cells whose centre ``trim`` does not cover.

    The same cells as ``grid_indices(nu, nv, keep)`` with ``keep(i, j) =
    trim.covers((i + 0.5) / (nu - 1), (j + 0.5) / (nv - 1))``: the mask row of
    each cell row and the mask column of each cell column, then the kernel's
    ``cell_indices`` (whole runs of cells in pure Python, one boolean array
    with numpy).
    """
    rows = mask_indices([(i + 0.5) / (nu - 1) for i in range(nu - 1)], trim.rows)
    cols = mask_indices([(j + 0.5) / (nv - 1) for j in range(nv - 1)], trim.cols)
    return _kernel.backend(kernel).cell_indices(nu, nv, [(0, 0, rows, cols, trim.flat,
                                                          trim.cols)])


def pole_normals(surface: NurbsSurface, normals: array, us: Sequence[float],
                 vs: Sequence[float], degenerate: Iterable[int]) -> None:
    """Replace the normals of the ``degenerate`` vertices of the grid ``us x vs`` (surface
    parameters, row-major in ``u``) with ``surface.normal``'s limit normal there."""
    n_cols = len(vs)
    for k in degenerate:
        normals[3 * k : 3 * k + 3] = array(normals.typecode,
                                           surface.normal(us[k // n_cols], vs[k % n_cols]))


def grid_uvs(us: Sequence[float], vs: Sequence[float]) -> array:
    """``array('f')`` of ``(u_i, v_j)`` pairs, row-major in ``i``."""
    nu, nv = len(us), len(vs)
    uvs = array("f", bytes(8 * nu * nv))
    for i, u in enumerate(us):
        uvs[2 * i * nv : 2 * (i + 1) * nv : 2] = array("f", [u]) * nv
    uvs[1::2] = array("f", vs) * nu
    return uvs


def tessellate_grid(
    surface: NurbsSurface, nu: int, nv: int, kernel: str | None = None
) -> Mesh:
    """Evaluate ``surface`` on a uniform ``nu x nv`` parameter grid and triangulate it.

    Vertex ``k = i * nv + j`` lies at ``(u_i, v_j)``, ``u_i = u_a + i (u_b - u_a) / (nu - 1)``;
    there are ``2 (nu - 1) (nv - 1)`` triangles, fewer when the surface's trim
    mask leaves cells out. Normals come from the analytic derivatives; at
    degenerate points (poles) they are the limit from inside the domain.

    Parameters
    ----------
    kernel : {'python', 'numpy'}, optional
        Force a kernel; default the one ``TESSERA_KERNEL`` or numpy's presence selects.
    """
    if not isinstance(surface, NurbsSurface):
        raise ValueError(f"surface must be a NurbsSurface, got {type(surface).__name__}")
    nu, nv = _check_count("nu", nu), _check_count("nv", nv)
    (u0, u1), (v0, v1) = surface.domain
    us, vs = _samples(u0, u1, nu), _samples(v0, v1, nv)
    positions, normals, degenerate = _kernel.backend(kernel).evaluate_grid(surface, us, vs)
    pole_normals(surface, normals, us, vs, degenerate)
    uvs = grid_uvs(us, vs)
    if surface.trim is None:
        indices = grid_indices(nu, nv, kernel=kernel)
    else:
        indices = trimmed_grid_indices(nu, nv, surface.trim, kernel)
    return Mesh(positions, normals, uvs, indices)
