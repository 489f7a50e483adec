"""The PLY writer of Tessera: triangle meshes in the layout 3DHOP 4.3's loader
(``minimal/js/ply.js``) reads, and point clouds (generated scans, error reports).

Vertex properties, in this order: float32 ``x y z``; for a mesh, float32
``nx ny nz``, and with a texture float32 ``texture_u texture_v`` (the mesh's
uvs) and a ``comment TextureFile NAME`` header line, which 3DHOP resolves next
to the mesh URL; when there are colours, uchar ``red green blue``; then the
caller's extra float32 properties, one value per vertex each (MeshLab's
``quality`` is one). Faces, meshes only: ``property list uchar int
vertex_indices``, all triangles; a point cloud has no face element. Binary
little-endian by default.

Texture coordinates are written only with a texture: 3DHOP's shader samples
its texture wherever a vertex has ``texture_u != 0``, so uvs without an image
render black.

Binary records are assembled with strided slice assignment into one
``bytearray`` (one C-level copy per byte column), not one ``struct`` call per
vertex: it is the browser's download path, and error reports have millions of
points. Values come in through the buffer protocol, so ``array('f')`` /
``array('B')`` and C-ordered numpy ``float32`` / ``uint8`` arrays of any shape
are read without a copy; other number sequences are converted first (one
C-level pass over the values).
"""

from __future__ import annotations

import sys
from array import array
from collections.abc import Mapping
from dataclasses import dataclass

from .tessellate import Mesh

POSITION_FLOATS = ("x", "y", "z")
NORMAL_FLOATS = ("nx", "ny", "nz")
TEXTURE_FLOATS = ("texture_u", "texture_v")
COLOR_BYTES = ("red", "green", "blue")
FACE_PROPERTY = "property list uchar int vertex_indices"
_PLY_TYPE = {"f": "float", "B": "uchar"}  # array typecode -> PLY property type
INTERLEAVE_ROWS = 16_384  # rows per block of _interleave: a few 100 kB, in L2 cache


@dataclass(frozen=True)
class _Column:
    """Consecutive vertex properties of one type: ``values`` holds ``len(names)`` values per
    vertex, flat, as a memoryview of format ``f`` (float32) or ``B`` (uint8)."""

    names: tuple[str, ...]
    values: memoryview


def _flat_values(values: object, typecode: str, what: str) -> memoryview:
    """``values`` as a flat memoryview of ``typecode`` (``f``: float32, ``B``: uint8, ``i``:
    int32): the buffer itself when it already holds such values in C order, else a copy."""
    try:
        view = memoryview(values)
    except TypeError:
        view = None
    if view is not None and view.nbytes == 0:  # a (0, 3) array cannot be cast
        return memoryview(array(typecode))
    if view is not None:
        fmt = view.format.lstrip("@=")
        native = "<" if sys.byteorder == "little" else ">"
        if fmt[:1] in ("<", ">", "!"):
            order, fmt = ("<" if fmt[0] == "<" else ">"), fmt[1:]
        else:
            order = native
        try:
            flat = memoryview(view.tobytes(order="C") if not view.c_contiguous else view)
            flat = flat.cast("B").cast(fmt)
        except (TypeError, ValueError):
            raise ValueError(f"{what} must hold numbers, got buffer format "
                             f"{view.format!r}") from None
        if order != native:  # a foreign byte order: swap into a native copy
            swapped = array(fmt, flat)
            swapped.byteswap()
            flat = memoryview(swapped)
        if fmt == typecode:
            return flat
        values = flat
    try:
        return memoryview(array(typecode, values))
    except (TypeError, OverflowError) as exc:
        kind = {"f": "float32", "B": "0..255 integer", "i": "int32"}[typecode]
        raise ValueError(f"{what} must be {kind} values: {exc}") from None


def _little_endian(values: memoryview) -> memoryview:
    """The bytes of ``values`` in little-endian order (no copy on a little-endian machine)."""
    if sys.byteorder == "big" and values.itemsize > 1:
        swapped = array(values.format, values)
        swapped.byteswap()
        values = memoryview(swapped)
    return values.cast("B")


def _interleave(columns: list[tuple[memoryview, int]], count: int) -> bytearray:
    """Records of ``count`` rows from columns of ``(bytes, width)``, by strided copies.

    Blocks of ``INTERLEAVE_ROWS`` rows keep the output block in cache through its
    passes, one per byte column; each column block is copied to ``bytes`` first, whose
    strided slice is a tight C loop (a memoryview's is several times slower)."""
    stride = sum(width for _, width in columns)
    out = bytearray(stride * count)
    for first in range(0, count, INTERLEAVE_ROWS):
        last = min(count, first + INTERLEAVE_ROWS)
        end = last * stride
        offset = first * stride
        for data, width in columns:
            block = bytes(data[first * width : last * width])
            for b in range(width):
                out[offset + b : end : stride] = block[b::width]
            offset += width
    return out


def _check_length(what: str, values: memoryview, per_vertex: int, count: int) -> None:
    if len(values) != per_vertex * count:
        raise ValueError(f"{what} has {len(values)} values; {count} vertices need "
                         f"{per_vertex * count}")


def _extra_columns(properties: Mapping[str, object] | None, used: set[str],
                   count: int) -> list[_Column]:
    """One float32 column per entry of ``properties`` (name -> one value per vertex)."""
    if properties is None:
        return []
    if not isinstance(properties, Mapping):
        raise ValueError(f"properties must map names to values, got "
                         f"{type(properties).__name__}")
    columns = []
    for name, values in properties.items():
        if not (isinstance(name, str) and name.isascii() and name.isidentifier()):
            raise ValueError(f"property name must be an ASCII identifier, got {name!r}")
        if name in used:
            raise ValueError(f"property {name!r} is already written as a standard property")
        flat = _flat_values(values, "f", f"properties[{name!r}]")
        _check_length(f"properties[{name!r}]", flat, 1, count)
        columns.append(_Column((name,), flat))
    return columns


def _header(columns: list[_Column], count: int, triangles: int | None, binary: bool,
            comments: list[str]) -> bytes:
    fmt = "binary_little_endian" if binary else "ascii"
    lines = ["ply", f"format {fmt} 1.0", "comment written by Tessera client_py"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element vertex {count}")
    for column in columns:
        kind = _PLY_TYPE[column.values.format]
        lines += [f"property {kind} {name}" for name in column.names]
    if triangles is not None:
        lines += [f"element face {triangles}", FACE_PROPERTY]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def _serialise(columns: list[_Column], count: int, indices: memoryview | None, binary: bool,
               comments: list[str]) -> bytes:
    """Header and body of ``count`` vertices (``columns``) and, unless ``indices`` is None, the
    triangles it lists (flat int32, three per triangle)."""
    triangles = None if indices is None else len(indices) // 3
    header = _header(columns, count, triangles, binary, comments)
    if not binary:
        return header + _ascii_body(columns, count, indices)
    vertices = _interleave([(_little_endian(c.values), len(c.names) * c.values.itemsize)
                            for c in columns], count)
    if indices is None:
        return b"".join((header, vertices))
    faces = _interleave([(b"\x03" * triangles, 1), (_little_endian(indices), 12)],
                        triangles)
    return b"".join((header, vertices, faces))


def _ascii_body(columns: list[_Column], count: int, indices: memoryview | None) -> bytes:
    texts = []
    for column in columns:
        if column.values.format == "f":
            texts.append(([format(x, ".9g") for x in column.values], len(column.names)))
        else:
            texts.append(([str(c) for c in column.values], len(column.names)))
    lines = []
    for k in range(count):
        fields: list[str] = []
        for text, width in texts:
            fields += text[width * k : width * k + width]
        lines.append(" ".join(fields))
    if indices is not None:
        lines += [f"3 {indices[t]} {indices[t + 1]} {indices[t + 2]}"
                  for t in range(0, len(indices), 3)]
    # Every value ends with a space, the last of a line too (as MeshLab writes): 3DHOP's
    # ASCII reader splits the body at spaces only, so "x\ny" would read as one token.
    return ("".join(line + " \n" for line in lines)).encode("ascii")


def _clean_comments(comments: list[str] | None) -> list[str]:
    return [c.replace("\n", " ") for c in (comments or [])]


def write_ply(mesh: Mesh, binary: bool = True, texture_file: str | None = None,
              comments: list[str] | None = None,
              properties: Mapping[str, object] | None = None) -> bytes:
    """Serialise ``mesh`` as PLY bytes (3DHOP-ready).

    Parameters
    ----------
    mesh : Mesh
        ``n`` vertices (positions and normals ``3 n`` floats, uvs ``2 n``, colours
        ``3 n`` bytes or None) and ``m`` triangles (indices ``3 m``).
    binary : bool
        ``binary_little_endian`` (default) or ``ascii``.
    texture_file : str, optional
        Image name written as ``comment TextureFile NAME``; the mesh's uvs are
        then written as ``texture_u/texture_v`` to index it (and only then).
    comments : list of str, optional
        Extra header comments (provenance, units).
    properties : mapping of str to float values, optional
        Extra float32 vertex properties after the standard ones, ``n`` values each.
    """
    if not isinstance(mesh, Mesh):
        raise ValueError(f"mesh must be a Mesh, got {type(mesh).__name__}")
    n = mesh.vertex_count
    positions = _flat_values(mesh.positions, "f", "mesh.positions")
    normals = _flat_values(mesh.normals, "f", "mesh.normals")
    uvs = _flat_values(mesh.uvs, "f", "mesh.uvs")
    colors = None if mesh.colors is None else _flat_values(mesh.colors, "B", "mesh.colors")
    for what, values, per in (("mesh.positions", positions, 3), ("mesh.normals", normals, 3),
                              ("mesh.uvs", uvs, 2), ("mesh.colors", colors, 3)):
        if values is not None:
            _check_length(what, values, per, n)
    indices = _flat_values(mesh.indices, "i", "mesh.indices")
    if len(indices) % 3:
        raise ValueError(f"mesh.indices has {len(indices)} values, not a multiple of 3")
    if len(indices) and max(indices) >= n:
        raise ValueError(f"mesh.indices refers to vertex {max(indices)} of {n}")
    if len(indices) and min(indices) < 0:
        raise ValueError(f"mesh.indices refers to vertex {min(indices)}; indices start at 0")
    # 3DHOP splits header lines at spaces and keeps the comment's first word only
    if texture_file is not None and (not isinstance(texture_file, str) or not texture_file
                                     or texture_file.split() != [texture_file]):
        raise ValueError(
            f"texture_file must be a file name without whitespace, got {texture_file!r}"
        )
    columns = [_Column(POSITION_FLOATS, positions), _Column(NORMAL_FLOATS, normals)]
    if texture_file is not None:
        columns.append(_Column(TEXTURE_FLOATS, uvs))
    if colors is not None:
        columns.append(_Column(COLOR_BYTES, colors))
    used = {name for column in columns for name in column.names}
    columns += _extra_columns(properties, used, n)
    comments = _clean_comments(comments)
    if texture_file is not None:
        comments.append(f"TextureFile {texture_file}")
    return _serialise(columns, n, indices, binary, comments)


def write_points_ply(positions: object, colors: object | None = None,
                     properties: Mapping[str, object] | None = None, binary: bool = True,
                     comments: list[str] | None = None) -> bytes:
    """Serialise a point cloud of ``n`` points as PLY bytes: vertices only, no faces.

    Parameters
    ----------
    positions : float values, ``3 n``
        ``x, y, z`` per point: ``array('f')``, a numpy array of shape ``(n, 3)``
        (``float32`` is read in place; other dtypes are converted) or a sequence.
    colors : 0..255 values, ``3 n``, optional
        ``red, green, blue`` per point (``array('B')``, numpy ``uint8`` ``(n, 3)``).
    properties : mapping of str to float values, optional
        Extra float32 vertex properties after the colours, ``n`` values each, e.g.
        ``{"quality": d}``.
    binary : bool
        ``binary_little_endian`` (default) or ``ascii``.
    comments : list of str, optional
        Extra header comments (provenance, units).
    """
    flat = _flat_values(positions, "f", "positions")
    if len(flat) % 3:
        raise ValueError(f"positions has {len(flat)} values, not a multiple of 3")
    n = len(flat) // 3
    columns = [_Column(POSITION_FLOATS, flat)]
    if colors is not None:
        rgb = _flat_values(colors, "B", "colors")
        _check_length("colors", rgb, 3, n)
        columns.append(_Column(COLOR_BYTES, rgb))
    used = {name for column in columns for name in column.names}
    columns += _extra_columns(properties, used, n)
    return _serialise(columns, n, None, binary, _clean_comments(comments))
