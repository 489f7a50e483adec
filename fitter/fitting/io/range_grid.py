"""Range images: the Stanford range scans' ``range_grid`` element read and triangulated.

A raw range scan from the Stanford 3D Scanning Repository (e.g. ``happyStandRight_0.ply``)
is a ``vertex`` element followed by ``range_grid``: one record per pixel of the scanner's
``num_rows x num_cols`` image (``obj_info`` lines of the header), in row-major order, each
a list of zero or one vertex index (zero: no return at that pixel). The grid is the scan's
connectivity: neighbouring pixels are neighbouring samples of one surface, except across a
depth discontinuity (an occluding contour), where the scanner saw two surfaces side by side.

Triangulation (Turk & Levoy, *Zippered polygon meshes from range images*, SIGGRAPH 1994,
§3): every grid square with four samples gives two triangles, split along its shorter
diagonal; a square with three samples gives the one triangle they span; and a triangle
with an edge longer than :data:`EDGE_FACTOR` times the scan's sample spacing (the median
length of the grid's horizontal and vertical edges) is left out, since such an edge
crosses a depth discontinuity or a grazing view, where no surface was measured. The mesh
keeps the scan's open borders (the image's border, holes, occluding contours) as open
borders, so a fit does not bridge them with walls.

Orientation. Every triangle is wound the same way in the image, so all face the scanner or
all face away. The Stanford range images are stored in the scanner's frame, with the
scanner on the ``+z`` side looking down ``-z`` (the 15 Happy Buddha scans: 99.3-99.7 % of each
scan's triangle area faces one side of ``z``, and seen from ``+z`` scan 0 shows the
statue's front); the winding is chosen so that most of the area faces ``+z``, the scanner.

In a registration (``.conf``) the range images overlap: their triangles are not one surface,
and :func:`fitter.fitting.io.conf.load_conf` keeps the points only.
"""

from __future__ import annotations

import numpy as np

from .scan import ScanError

#: a triangle whose longest edge exceeds this many sample spacings is not made (it spans a
#: depth discontinuity); Turk & Levoy leave out edges "longer than a threshold" of a few
#: sample spacings
EDGE_FACTOR = 4.0


def grid_shape(comments: list[str], count: int, name: str) -> tuple[int, int]:
    """``(rows, cols)`` of a range grid of ``count`` records, from the header's
    ``obj_info num_cols C`` and ``num_rows R`` (``rows = count / cols`` when only the
    columns are given)."""
    info: dict[str, int] = {}
    for comment in comments:
        words = comment.split()
        if len(words) == 2 and words[0] in ("num_cols", "num_rows") and words[1].isdigit():
            info[words[0]] = int(words[1])
    cols = info.get("num_cols")
    if not cols:
        raise ScanError(f"{name}: the PLY has a range_grid of {count} records but no "
                        "'obj_info num_cols' line giving the grid's width")
    rows = info.get("num_rows", count // cols)
    if rows * cols != count:
        raise ScanError(f"{name}: the range_grid has {count} records, not num_rows x num_cols "
                        f"= {rows} x {cols} = {rows * cols}")
    return rows, cols


def ascii_grid_indices(text: bytes, count: int, n_points: int, name: str) -> np.ndarray:
    """The vertex index of each of ``count`` ASCII ``range_grid`` records (``-1`` where the
    list is empty; the first index where it holds several), checked against ``n_points``."""
    try:
        tokens = np.array(text.split(), dtype=np.int64)
    except (ValueError, OverflowError):
        raise ScanError(f"{name}: unreadable range_grid record (not integers)") from None
    return _walk(tokens, count, n_points, name)


def binary_grid_indices(data: bytes, count: int, count_type: str, index_type: str,
                        byte_order: str, n_points: int, name: str) -> np.ndarray:
    """As :func:`ascii_grid_indices` for binary records: a list count of numpy type
    ``count_type`` then that many indices of ``index_type``, in ``byte_order``."""
    ct, it = np.dtype(byte_order + count_type), np.dtype(byte_order + index_type)
    out = np.full(count, -1, np.int64)
    position = 0
    for k in range(count):
        if position + ct.itemsize > len(data):
            raise ScanError(f"{name}: truncated range_grid: the data ends at record {k} of "
                            f"{count}")
        m = int(np.frombuffer(data, ct, 1, position)[0])
        position += ct.itemsize
        if m < 0 or position + m * it.itemsize > len(data):
            raise ScanError(f"{name}: range_grid record {k} lists {m} indices, more than the "
                            "file holds")
        if m:
            out[k] = int(np.frombuffer(data, it, 1, position)[0])
        position += m * it.itemsize
    return _checked(out, n_points, name)


def _walk(tokens: np.ndarray, count: int, n_points: int, name: str) -> np.ndarray:
    """Records ``m i_1 .. i_m`` from a token stream."""
    out = np.full(count, -1, np.int64)
    position, size = 0, len(tokens)
    listed = tokens.tolist()  # plain ints: the walk is sequential
    for k in range(count):
        if position >= size:
            raise ScanError(f"{name}: truncated range_grid: the data ends at record {k} of "
                            f"{count}")
        m = listed[position]
        if m < 0 or position + m >= size:
            raise ScanError(f"{name}: range_grid record {k} lists {m} indices, more than the "
                            "file holds")
        if m:
            out[k] = listed[position + 1]
        position += 1 + m
    return _checked(out, n_points, name)


def _checked(indices: np.ndarray, n_points: int, name: str) -> np.ndarray:
    bad = (indices < -1) | (indices >= n_points)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise ScanError(f"{name}: range_grid record {k} names vertex {int(indices[k])}, but "
                        f"the scan has {n_points} vertices")
    return indices


def triangulate(points: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Triangles ``(T, 3)`` of a range image: ``grid (rows, cols)`` holds the vertex index
    of each pixel (``-1``: no sample) of ``points (N, 3)``; see the module docstring."""
    a, b = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel()  # a b
    c, d = grid[1:, :-1].ravel(), grid[1:, 1:].ravel()    # c d
    spacing = _spacing(points, grid)
    if spacing == 0.0:
        return np.zeros((0, 3), np.int64)

    def length(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        return np.linalg.norm(points[i] - points[j], axis=1)

    full = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    short_ad = np.zeros(len(a), bool)
    short_ad[full] = length(a[full], d[full]) <= length(b[full], c[full])
    split_ad, split_bc = full & short_ad, full & ~short_ad
    candidates = [
        np.column_stack([a, c, d])[split_ad], np.column_stack([a, d, b])[split_ad],
        np.column_stack([a, c, b])[split_bc], np.column_stack([b, c, d])[split_bc],
    ]
    three = ((a >= 0).astype(int) + (b >= 0) + (c >= 0) + (d >= 0)) == 3
    for corners, missing in (((a, c, d), b), ((a, d, b), c), ((a, c, b), d), ((b, c, d), a)):
        candidates.append(np.column_stack(corners)[three & (missing < 0)])
    tri = np.concatenate(candidates)
    if len(tri) == 0:
        return tri.astype(np.int64)
    longest = np.max([length(tri[:, 0], tri[:, 1]), length(tri[:, 1], tri[:, 2]),
                      length(tri[:, 2], tri[:, 0])], axis=0)
    tri = tri[longest <= EDGE_FACTOR * spacing]
    p = points[tri]
    facing = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2].sum()
    return (tri if facing >= 0 else tri[:, ::-1]).astype(np.int64)


def _spacing(points: np.ndarray, grid: np.ndarray) -> float:
    """Median length of the grid's horizontal and vertical edges between samples."""
    pairs = [(grid[:, :-1].ravel(), grid[:, 1:].ravel()), (grid[:-1].ravel(), grid[1:].ravel())]
    lengths = [np.linalg.norm(points[i[(i >= 0) & (j >= 0)]] - points[j[(i >= 0) & (j >= 0)]],
                              axis=1) for i, j in pairs]
    joined = np.concatenate(lengths)
    return float(np.median(joined)) if len(joined) else 0.0
