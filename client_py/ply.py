"""PLY writer for a ``Mesh``, in the layout 3DHOP 4.3's loader (``minimal/js/ply.js``) reads.

Vertices: float32 ``x y z``, ``nx ny nz``; with a texture, float32
``texture_u texture_v`` (the mesh's uvs) and a ``comment TextureFile NAME``
header line, which 3DHOP resolves next to the mesh URL; when the mesh has
colours, uchar ``red green blue``. Faces: ``property list uchar int
vertex_indices``, all triangles. Binary little-endian by default.

Texture coordinates are written only with a texture: 3DHOP's shader samples
its texture wherever a vertex has ``texture_u != 0``, so uvs without an image
render black.

Binary records are assembled with strided slice assignment into one
``bytearray`` (one C-level copy per byte column), not one ``struct`` call per
vertex: it is the browser's download path.
"""

from __future__ import annotations

import sys
from array import array

from .tessellate import Mesh

VERTEX_FLOATS = ("x", "y", "z", "nx", "ny", "nz")
TEXTURE_FLOATS = ("texture_u", "texture_v")


def _header(mesh: Mesh, binary: bool, texture_file: str | None, comments: list[str]) -> bytes:
    fmt = "binary_little_endian" if binary else "ascii"
    lines = ["ply", f"format {fmt} 1.0", "comment written by Tessera client_py"]
    lines += [f"comment {c}" for c in comments]
    if texture_file is not None:
        lines.append(f"comment TextureFile {texture_file}")
    lines.append(f"element vertex {mesh.vertex_count}")
    lines += [f"property float {name}" for name in VERTEX_FLOATS]
    if texture_file is not None:
        lines += [f"property float {name}" for name in TEXTURE_FLOATS]
    if mesh.colors is not None:
        lines += [f"property uchar {c}" for c in ("red", "green", "blue")]
    lines += [f"element face {mesh.triangle_count}", "property list uchar int vertex_indices",
              "end_header"]
    return ("\n".join(lines) + "\n").encode("ascii")


def _little_endian(values: array) -> bytes:
    if sys.byteorder == "big":
        values = array(values.typecode, values)
        values.byteswap()
    return values.tobytes()


def _interleave(columns: list[tuple[bytes, int]], count: int) -> bytearray:
    """Records of ``count`` rows from columns of ``(bytes, width)``, by strided copies."""
    stride = sum(width for _, width in columns)
    out = bytearray(stride * count)
    offset = 0
    for data, width in columns:
        for b in range(width):
            out[offset + b :: stride] = data[b::width]
        offset += width
    return out


def _check(mesh: Mesh, texture_file: str | None) -> None:
    if not isinstance(mesh, Mesh):
        raise ValueError(f"mesh must be a Mesh, got {type(mesh).__name__}")
    n = mesh.vertex_count
    for name, arr, per in (("positions", mesh.positions, 3), ("normals", mesh.normals, 3),
                           ("uvs", mesh.uvs, 2), ("colors", mesh.colors, 3)):
        if arr is not None and len(arr) != per * n:
            raise ValueError(f"mesh.{name} has {len(arr)} values; {n} vertices need {per * n}")
    if len(mesh.indices) % 3:
        raise ValueError(f"mesh.indices has {len(mesh.indices)} values, not a multiple of 3")
    if mesh.indices and max(mesh.indices) >= n:
        raise ValueError(f"mesh.indices refers to vertex {max(mesh.indices)} of {n}")
    # 3DHOP splits header lines at spaces and keeps the comment's first word only
    if texture_file is not None and (not texture_file or texture_file.split() != [texture_file]):
        raise ValueError(
            f"texture_file must be a file name without whitespace, got {texture_file!r}"
        )


def write_ply(mesh: Mesh, binary: bool = True, texture_file: str | None = None,
              comments: list[str] | None = None) -> bytes:
    """Serialise ``mesh`` as PLY bytes (3DHOP-ready).

    Parameters
    ----------
    binary : bool
        ``binary_little_endian`` (default) or ``ascii``.
    texture_file : str, optional
        Image name written as ``comment TextureFile NAME``; the mesh's uvs are
        then written as ``texture_u/texture_v`` to index it (and only then).
    comments : list of str, optional
        Extra header comments (provenance, units).
    """
    _check(mesh, texture_file)
    comments = [c.replace("\n", " ") for c in (comments or [])]
    header = _header(mesh, binary, texture_file, comments)
    n = mesh.vertex_count
    if not binary:
        return header + _ascii_body(mesh, texture_file is not None)
    pos = _little_endian(mesh.positions)
    nrm = _little_endian(mesh.normals)
    columns = [(pos, 12), (nrm, 12)]
    if texture_file is not None:
        columns.append((_little_endian(mesh.uvs), 8))
    if mesh.colors is not None:
        columns.append((bytes(mesh.colors), 3))
    vertices = _interleave(columns, n)
    indices = _little_endian(array("i", mesh.indices))
    faces = _interleave([(b"\x03" * mesh.triangle_count, 1), (indices, 12)], mesh.triangle_count)
    return header + bytes(vertices) + bytes(faces)


def _ascii_body(mesh: Mesh, with_uvs: bool) -> bytes:
    lines = []
    p, nrm, uv, col = mesh.positions, mesh.normals, mesh.uvs, mesh.colors
    for k in range(mesh.vertex_count):
        values = [*p[3 * k : 3 * k + 3], *nrm[3 * k : 3 * k + 3]]
        if with_uvs:
            values += uv[2 * k : 2 * k + 2]
        fields = [format(x, ".9g") for x in values]
        if col is not None:
            fields += [str(c) for c in col[3 * k : 3 * k + 3]]
        lines.append(" ".join(fields))
    idx = mesh.indices
    lines += [f"3 {idx[t]} {idx[t + 1]} {idx[t + 2]}" for t in range(0, len(idx), 3)]
    # Every value ends with a space, the last of a line too (as MeshLab writes): 3DHOP's
    # ASCII reader splits the body at spaces only, so "x\ny" would read as one token.
    return ("".join(line + " \n" for line in lines)).encode("ascii")
