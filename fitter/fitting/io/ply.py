"""PLY reader: header parser, a memory-mapped fast path for binary point clouds, trimesh for meshes.

The header (Turk's PLY format, as in the Stanford repository) is parsed here,
so the reader knows before touching the body which path fits:

* **binary point cloud** (``binary_little_endian`` / ``binary_big_endian``, the
  ``vertex`` element first with scalar properties, no faces): the vertex block
  is read as a structured numpy dtype built from the header (byte order,
  property types and order). Uncompressed files are memory-mapped
  (``numpy.memmap``) and walked once in chunks of ``CHUNK_VERTICES``: each chunk
  is hashed (SHA-256 over the map, in file order: header, vertex block, any
  trailing elements) and converted into preallocated float64 points in the same
  pass, so a file of any size is read once and peak memory is the output arrays
  plus one chunk. ``.ply.gz`` is streamed through gzip in the same chunks.
* **raw range scan** (the Stanford range scans: ``vertex`` then ``range_grid``, ASCII
  or binary): the vertex lines go through ``numpy.loadtxt`` (C parser: 23 ms for a
  78k-point Buddha scan against 1.5 s in trimesh's ASCII reader) and the range image
  is triangulated into the scan's faces (``fitter.fitting.io.range_grid``).
* **ASCII point cloud** (``vertex`` alone): the vertex lines through ``loadtxt``;
  later elements are hashed, not parsed.
* **ASCII triangle mesh** (``vertex`` then an all-triangle ``face`` list, e.g.
  the zippered bunny): vertex and face lines both through ``loadtxt``.
* **everything else** (binary meshes, polygons, vertex elements with list
  properties): trimesh's PLY loader on the bytes read once (``fitter.fitting.io.mesh``).

Before any of these allocates, the counts the header claims are checked
against the bytes the file can hold after the header (``check_claimed_counts``):
an ASCII record takes at least ``MIN_ASCII_PROPERTY_BYTES`` per property (a digit
and a separator), a binary one its record size (a list property at least its
count field), so a 300-byte file claiming 10^12 vertices is refused at once
instead of allocating 21.8 TiB. For ``.ply.gz`` the bound is the compressed size
times ``DEFLATE_MAX_RATIO``; the readers then allocate only as data arrives.

Recognised vertex properties: ``x y z`` (required), normals ``nx ny nz``, colours
``red green blue`` (or ``r g b``, ``diffuse_red ...``; uchar as is, floats taken
as 0..1). Others (``confidence``, ``intensity``, ``alpha``...) are listed in
``source["ignored_properties"]``. Units come from a header comment such as
``comment units mm``.
"""

from __future__ import annotations

import hashlib
import io
import itertools
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import range_grid
from .limits import InputBudget
from .points import PointStream
from .scan import Scan, ScanError, colors_to_uint8, make_scan, new_source, units_from_comments
from .source import CHUNK_BYTES, GZIP_ERRORS, HashedInput, file_record, read_exactly

#: vertices per chunk of the binary fast path (bounded memory, hashing and conversion per chunk)
CHUNK_VERTICES = 1 << 20
#: a header longer than this is not a PLY header
MAX_HEADER_BYTES = 1 << 20
#: fewest bytes one property of an ASCII record takes: a digit and a separator (``"0 "``)
MIN_ASCII_PROPERTY_BYTES = 2
#: deflate's largest expansion (RFC 1951: a 258-byte match in at most 2 bits, ~1032:1), so
#: a ``.gz`` of ``c`` bytes decompresses to at most ``DEFLATE_MAX_RATIO * c`` bytes
DEFLATE_MAX_RATIO = 1032

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))
COLOR_NAMES = (("red", "green", "blue"), ("r", "g", "b"),
               ("diffuse_red", "diffuse_green", "diffuse_blue"))
FACE_ELEMENTS = ("face", "tristrips")
#: how messages name the records of common elements
ELEMENT_NOUNS = {"vertex": "vertices", "face": "faces"}


@dataclass
class PlyProperty:
    """One property: numpy type code (``"f4"``...), and the count type for list properties."""

    name: str
    type: str
    list_count_type: str | None = None


@dataclass
class PlyElement:
    name: str
    count: int
    properties: list[PlyProperty] = field(default_factory=list)

    @property
    def is_scalar(self) -> bool:
        return all(p.list_count_type is None for p in self.properties)

    def min_record_bytes(self, binary: bool) -> int:
        """Fewest bytes one record of this element can take in the file.

        ASCII: ``MIN_ASCII_PROPERTY_BYTES`` per property (a list property at least
        its count); binary: the scalar types' sizes plus each list's count field
        (an empty list). An element without properties counts 1 byte (a line), so
        that its claimed count is bounded too.
        """
        if not binary:
            return max(1, MIN_ASCII_PROPERTY_BYTES * len(self.properties))
        sizes = [np.dtype(p.list_count_type or p.type).itemsize for p in self.properties]
        return max(1, sum(sizes))


@dataclass
class PlyHeader:
    """A parsed header; ``raw`` is its bytes, so the body starts at ``len(raw)``."""

    format: str
    elements: list[PlyElement]
    comments: list[str]
    raw: bytes
    warnings: list[str] = field(default_factory=list)

    @property
    def byte_order(self) -> str | None:
        return FORMATS[self.format]

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)

    def vertex_dtype(self) -> np.dtype:
        """Structured dtype of one vertex record of a binary file (scalar properties only)."""
        order = self.byte_order
        return np.dtype([(p.name, order + p.type) for p in self.elements[0].properties])


def parse_header(stream: io.BufferedIOBase, name: str) -> PlyHeader:
    """Read and parse a PLY header up to and including ``end_header``.

    Raises
    ------
    ScanError
        Not a PLY file, unknown format or type, malformed element/property line,
        duplicate property, or no ``end_header`` within ``MAX_HEADER_BYTES``.
    """
    raw = bytearray()
    elements: list[PlyElement] = []
    comments: list[str] = []
    ignored: list[str] = []
    fmt = None
    lineno = 0
    while True:
        line = stream.readline(MAX_HEADER_BYTES)
        lineno += 1
        raw += line
        if lineno == 1:
            if line.rstrip(b"\r\n") != b"ply":
                raise ScanError(f"{name}: not a PLY file: it starts with {bytes(line[:20])!r} "
                                "instead of the line 'ply'")
            continue
        if not line or len(raw) >= MAX_HEADER_BYTES:
            raise ScanError(f"{name}: PLY header has no 'end_header' line "
                            f"(read {len(raw)} bytes, {lineno - 1} lines)")
        try:
            text = line.decode("ascii").strip()
        except UnicodeDecodeError:
            raise ScanError(f"{name}: PLY header line {lineno} is not ASCII text") from None
        words = text.split()
        if not words:
            continue
        key = words[0]
        if key == "end_header":
            break
        if key in ("comment", "obj_info"):
            comments.append(text[len(key):].strip())
        elif key == "format":
            if len(words) != 3 or words[1] not in FORMATS:
                raise ScanError(f"{name}: PLY header line {lineno}: unknown format {text!r} "
                                f"(expected one of {', '.join(FORMATS)} with a version)")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise ScanError(f"{name}: PLY header line {lineno}: expected 'element NAME "
                                f"COUNT', got {text!r}")
            elements.append(PlyElement(words[1], int(words[2])))
        elif key == "property":
            if not elements:
                raise ScanError(f"{name}: PLY header line {lineno}: property before any element")
            elements[-1].properties.append(_parse_property(words, name, lineno, text))
            names = [p.name for p in elements[-1].properties]
            if len(set(names)) != len(names):
                raise ScanError(f"{name}: PLY header line {lineno}: duplicate property "
                                f"{names[-1]!r} in element {elements[-1].name!r}")
        else:  # e.g. the Stanford range scans' 'bye' lines: ignored, as other readers do
            ignored.append(f"PLY header line {lineno} ignored: {text[:60]!r}")
    if fmt is None:
        raise ScanError(f"{name}: PLY header has no 'format' line")
    return PlyHeader(fmt, elements, comments, bytes(raw), ignored)


def check_claimed_counts(header: PlyHeader, available: int, name: str,
                         where: str = "") -> None:
    """Refuse a header whose element counts cannot fit in ``available`` body bytes.

    With ``b_e`` the fewest bytes of one record of element ``e``
    (:meth:`PlyElement.min_record_bytes`) and ``n_e`` its claimed count, the body
    needs at least ``sum_e n_e b_e <= available`` bytes; this is checked element by
    element, before anything is allocated from the counts.

    Parameters
    ----------
    header : PlyHeader
        The parsed header.
    available : int
        Upper bound on the bytes that follow the header.
    name : str
        File name for the message.
    where : str
        How ``available`` was found, for the message (e.g. the gzip bound).

    Raises
    ------
    ScanError
        Naming the element, its claimed count, the bytes that needs and how many
        records of it the file can hold.
    """
    binary = header.byte_order is not None
    remaining = available
    for element in header.elements:
        per_record = element.min_record_bytes(binary)
        need = element.count * per_record
        if need > remaining:
            kind = "binary" if binary else "ASCII"
            noun = ELEMENT_NOUNS.get(element.name, f"{element.name!r} elements")
            room = remaining // per_record
            raise ScanError(
                f"{name}: truncated {kind} PLY: the header promises {element.count} {noun} "
                f"but the file holds only {room} at most: {remaining} bytes are left for them "
                f"after the header{where}, and one takes at least {per_record} bytes "
                f"({room} whole {noun})")
        remaining -= need


def _body_bytes_bound(path: Path, gzipped: bool, header: PlyHeader) -> tuple[int, str]:
    """Upper bound on the bytes after the header, and how it was found (for messages)."""
    size = path.stat().st_size
    if not gzipped:
        return max(0, size - len(header.raw)), ""
    return (size * DEFLATE_MAX_RATIO,
            f" (a {size}-byte gzip file decompresses to at most {DEFLATE_MAX_RATIO} times "
            f"its size)")


def _parse_property(words: list[str], name: str, lineno: int, text: str) -> PlyProperty:
    if len(words) == 3 and words[1] in PLY_TYPES:
        return PlyProperty(words[2], PLY_TYPES[words[1]])
    if len(words) == 5 and words[1] == "list" and words[2] in PLY_TYPES and words[3] in PLY_TYPES:
        return PlyProperty(words[4], PLY_TYPES[words[3]], PLY_TYPES[words[2]])
    raise ScanError(f"{name}: PLY header line {lineno}: cannot parse {text!r} (expected "
                    f"'property TYPE NAME' or 'property list TYPE TYPE NAME', TYPE one of "
                    f"{', '.join(sorted(set(PLY_TYPES)))})")


@dataclass
class _VertexLayout:
    """Which vertex properties the reader uses."""

    xyz: tuple[str, str, str]
    normals: tuple[str, str, str] | None
    colors: tuple[str, str, str] | None
    ignored: list[str]

    @classmethod
    def of(cls, element: PlyElement, name: str) -> _VertexLayout:
        names = [p.name for p in element.properties]
        if not {"x", "y", "z"} <= set(names):
            raise ScanError(f"{name}: the PLY vertex element has no x, y, z properties "
                            f"(it has {', '.join(names) or 'none'})")
        normals = next((t for t in NORMAL_NAMES if set(t) <= set(names)), None)
        colors = next((t for t in COLOR_NAMES if set(t) <= set(names)), None)
        used = {"x", "y", "z", *(normals or ()), *(colors or ())}
        return cls(("x", "y", "z"), normals, colors, [n for n in names if n not in used])


class _VertexArrays:
    """Output arrays, filled chunk by chunk from structured vertex records."""

    def __init__(self, layout: _VertexLayout, n: int) -> None:
        self.layout = layout
        self.points = np.empty((n, 3), np.float64)
        self.normals = np.empty((n, 3), np.float32) if layout.normals else None
        self.colors = np.empty((n, 3), np.uint8) if layout.colors else None

    def fill(self, start: int, records: np.ndarray) -> None:
        stop = start + len(records)
        self.points[start:stop] = _columns(records, self.layout.xyz)
        if self.normals is not None:
            self.normals[start:stop] = _columns(records, self.layout.normals)
        if self.colors is not None:
            self.colors[start:stop] = colors_to_uint8(_columns(records, self.layout.colors))


def _columns(records: np.ndarray, names: tuple[str, str, str]) -> np.ndarray:
    """Three fields of contiguous structured records as an ``(m, 3)`` array.

    When the fields are adjacent and of one type (``x y z`` almost always are)
    this is a strided view on the records, so the caller's assignment is one
    2-D converting copy instead of three 1-D ones; otherwise a stacked copy.
    """
    fields = [records.dtype.fields[n] for n in names]
    ftype, offset = fields[0]
    step = ftype.itemsize
    adjacent = all(f[0] == ftype and f[1] == offset + i * step for i, f in enumerate(fields))
    if adjacent and records.flags.c_contiguous:
        raw = records.view(np.uint8)
        return np.ndarray((len(records), 3), ftype, buffer=raw, offset=offset,
                          strides=(records.dtype.itemsize, step))
    return np.column_stack([records[n] for n in names])


def _is_point_cloud(header: PlyHeader) -> bool:
    if not header.elements or header.elements[0].name != "vertex":
        return False
    faces = sum(e.count for e in header.elements if e.name in FACE_ELEMENTS)
    return header.elements[0].is_scalar and faces == 0


def _is_range_image(header: PlyHeader) -> bool:
    """``vertex`` (scalar properties) then ``range_grid`` with one list property: a raw
    range scan (``fitter.fitting.io.range_grid``)."""
    els = header.elements
    return (len(els) >= 2 and els[0].name == "vertex" and els[0].is_scalar
            and els[1].name == "range_grid" and len(els[1].properties) == 1
            and els[1].properties[0].list_count_type is not None
            and els[1].count > 0 and not any(e.name in FACE_ELEMENTS for e in els))


def _parse_range_image(body: bytes, header: PlyHeader,
                       name: str) -> tuple[_VertexArrays, np.ndarray]:
    """Vertices and the triangulated ``range_grid`` of a raw range scan
    (:func:`fitter.fitting.io.range_grid.triangulate`)."""
    vertex, grid = header.elements[0], header.elements[1]
    shape = range_grid.grid_shape(header.comments, grid.count, name)
    layout = _VertexLayout.of(vertex, name)
    prop = grid.properties[0]
    if header.byte_order is None:
        newlines = np.flatnonzero(np.frombuffer(body, np.uint8) == ord("\n"))
        if len(newlines) < vertex.count:
            raise ScanError(f"{name}: truncated ASCII PLY: the header promises {vertex.count} "
                            f"vertices but the file holds only {len(newlines)} lines")
        end = newlines[vertex.count - 1] + 1 if vertex.count else 0
        arrays = _read_ascii(io.BytesIO(body[:end]), header, layout, name)
        indices = range_grid.ascii_grid_indices(body[end:], grid.count, vertex.count, name)
    else:
        end = vertex.count * header.vertex_dtype().itemsize
        arrays = _read_binary_stream(io.BytesIO(body[:end]), header, layout, name)
        indices = range_grid.binary_grid_indices(body[end:], grid.count, prop.list_count_type,
                                                 prop.type, header.byte_order, vertex.count,
                                                 name)
    return arrays, range_grid.triangulate(arrays.points, indices.reshape(shape))


def _is_ascii_triangle_mesh(header: PlyHeader) -> bool:
    """ASCII ``vertex`` (scalar properties) then ``face`` with one list property."""
    els = header.elements
    return (header.byte_order is None and len(els) >= 2 and els[0].name == "vertex"
            and els[0].is_scalar and els[1].name == "face" and len(els[1].properties) == 1
            and els[1].properties[0].list_count_type is not None)


def load_ply(path: Path, gzipped: bool, budget: InputBudget | None = None) -> Scan:
    """Read a ``.ply`` or ``.ply.gz`` file (see the module docstring for the paths taken);
    ``budget`` (``fitter.fitting.io.limits``) bounds the gzip stream and the vertex count."""
    name = path.name
    with HashedInput(path, gzipped, budget) as inp:
        try:
            header = parse_header(inp.stream, name)
            available, where = _body_bytes_bound(path, gzipped, header)
            check_claimed_counts(header, available, name, where)
            if budget is not None:  # the declared vertices, before any is allocated
                budget.take_points(name, sum(e.count for e in header.elements
                                             if e.name == "vertex"))
            units = units_from_comments(header.comments)
            if _is_range_image(header):
                body = inp.stream.read()
                record = inp.finish()
                reader = "ply-range-grid"
                arrays, faces = _parse_range_image(body, header, name)
                layout = arrays.layout
            elif _is_point_cloud(header) and header.byte_order and not gzipped:
                inp.close()
                return _load_memmap(path, header, units)
            elif _is_point_cloud(header):
                reader = "ply-stream" if header.byte_order else "ply-ascii"
                read = _read_binary_stream if header.byte_order else _read_ascii
                layout = _VertexLayout.of(header.elements[0], name)
                arrays = read(inp.stream, header, layout, name)
                faces = None
                record = inp.finish()
            else:
                body = inp.stream.read()
                record = inp.finish()
                parsed = _parse_ascii_mesh(body, header, name)
                if parsed is None:
                    return _via_trimesh(path, gzipped, header, body, record, units)
                reader, (arrays, faces) = "ply-ascii", parsed
                layout = arrays.layout
        except GZIP_ERRORS as exc:
            raise ScanError(f"{name}: corrupt gzip data: {exc}") from None
    source = _source(path, gzipped, reader, record, header, layout)
    return make_scan(name, arrays.points, normals=arrays.normals, colors=arrays.colors,
                     faces=faces, units=units, source=source)


def _via_trimesh(path: Path, gzipped: bool, header: PlyHeader, body: bytes, record: dict,
                 units: str) -> Scan:
    from .mesh import scan_from_trimesh

    scan = scan_from_trimesh(path, "ply", header.raw + body, record, gzipped, units=units,
                             extra_source={"ply_format": header.format,
                                           "elements": {e.name: e.count
                                                        for e in header.elements}})
    scan.source["warnings"] += header.warnings
    return scan


def _source(path: Path, gzipped: bool, reader: str, record: dict, header: PlyHeader,
            layout: _VertexLayout) -> dict:
    source = new_source(path.name, str(path), "ply", "gzip" if gzipped else None, reader)
    source.update(bytes=record["bytes"], sha256=record["sha256"], files=[record],
                  hash_method="sha256 of the stored file, streamed in chunks while parsing",
                  ply_format=header.format,
                  elements={e.name: e.count for e in header.elements},
                  ignored_properties=layout.ignored)
    source["warnings"] += header.warnings
    return source


def _load_memmap(path: Path, header: PlyHeader, units: str) -> Scan:
    """Binary point cloud, uncompressed: memory map, hash and convert in one pass."""
    name = path.name
    element = header.elements[0]
    layout = _VertexLayout.of(element, name)
    dtype = header.vertex_dtype()
    start = len(header.raw)
    need = element.count * dtype.itemsize  # the file holds it: check_claimed_counts
    size = path.stat().st_size
    hasher = hashlib.sha256()
    mapped = np.memmap(path, dtype=np.uint8, mode="r")
    try:
        hasher.update(mapped[:start])
        records = mapped[start:start + need].view(dtype)
        arrays = _VertexArrays(layout, element.count)
        for first in range(0, element.count, CHUNK_VERTICES):
            last = min(first + CHUNK_VERTICES, element.count)
            hasher.update(mapped[start + first * dtype.itemsize:start + last * dtype.itemsize])
            arrays.fill(first, records[first:last])
        for pos in range(start + need, size, CHUNK_BYTES):
            hasher.update(mapped[pos:min(pos + CHUNK_BYTES, size)])
    finally:
        del mapped
    record = file_record(name, nbytes=size, sha256=hasher.hexdigest())
    source = _source(path, False, "ply-memmap", record, header, layout)
    source["hash_method"] = "sha256 over the memory map, chunk by chunk in the conversion pass"
    trailing = size - start - need
    if trailing and len(header.elements) == 1:
        source["warnings"].append(f"{trailing} bytes after the vertex block were ignored")
    return make_scan(name, arrays.points, normals=arrays.normals, colors=arrays.colors,
                     units=units, source=source)


def _read_binary_stream(stream: io.BufferedIOBase, header: PlyHeader, layout: _VertexLayout,
                        name: str) -> _VertexArrays:
    """Binary point cloud from a stream (``.ply.gz``): read the vertex block in chunks."""
    element = header.elements[0]
    dtype = header.vertex_dtype()
    chunk = np.empty(min(CHUNK_VERTICES, max(element.count, 1)), dtype)
    parts: list[_VertexArrays] = []
    done = 0
    while done < element.count:
        want = min(len(chunk), element.count - done)
        got = read_exactly(stream, memoryview(chunk.view(np.uint8))[:want * dtype.itemsize])
        whole = got // dtype.itemsize
        part = _VertexArrays(layout, whole)
        part.fill(0, chunk[:whole])
        parts.append(part)
        done += whole
        if whole < want:
            raise ScanError(f"{name}: truncated binary PLY: the header promises {element.count} "
                            f"vertices ({dtype.itemsize} bytes each) but the data ends after "
                            f"{done} whole vertices")
    out = _VertexArrays(layout, 0)
    out.points = np.concatenate([p.points for p in parts]) if parts else out.points
    if layout.normals and parts:
        out.normals = np.concatenate([p.normals for p in parts])
    if layout.colors and parts:
        out.colors = np.concatenate([p.colors for p in parts])
    return out


def _read_ascii(stream: io.BufferedIOBase, header: PlyHeader, layout: _VertexLayout,
                name: str) -> _VertexArrays:
    """ASCII point cloud: the first ``count`` body lines through ``numpy.loadtxt``."""
    element = header.elements[0]
    props = [p.name for p in element.properties]
    arrays = _VertexArrays(layout, 0)
    if element.count == 0:
        return arrays
    text = io.TextIOWrapper(stream, encoding="ascii", newline=None)
    try:
        # islice, not max_rows: loadtxt preallocates max_rows rows, and a gzip body's
        # claimed count is bounded only loosely; this way memory follows the lines read
        with warnings.catch_warnings():  # no lines at all: reported below as truncated
            warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
            values = np.loadtxt(itertools.islice(text, element.count), dtype=np.float64,
                                comments=None, ndmin=2)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ScanError(f"{name}: unreadable ASCII PLY vertex data: {exc}") from None
    finally:
        text.detach()
    if values.shape[0] < element.count:
        raise ScanError(f"{name}: truncated ASCII PLY: the header promises {element.count} "
                        f"vertices but the file holds only {values.shape[0]} vertex lines")
    if values.shape[1] != len(props):
        raise ScanError(f"{name}: ASCII PLY vertex lines have {values.shape[1]} values, the "
                        f"header declares {len(props)} properties ({' '.join(props)})")
    columns = {p: values[:, i] for i, p in enumerate(props)}
    arrays.points = np.column_stack([columns[p] for p in layout.xyz])
    if layout.normals:
        arrays.normals = np.column_stack([columns[p] for p in layout.normals]).astype(np.float32)
    if layout.colors:
        types = {p.name: p.type for p in element.properties}
        rgb = np.column_stack([columns[p] for p in layout.colors])
        rgb = rgb.astype(types[layout.colors[0]]) if types[layout.colors[0]][0] in "iu" else rgb
        arrays.colors = colors_to_uint8(rgb)
    return arrays


def _parse_ascii_mesh(body: bytes, header: PlyHeader,
                      name: str) -> tuple[_VertexArrays, np.ndarray] | None:
    """Vertices and triangles of an ASCII mesh by ``loadtxt``; None to defer to trimesh.

    Only the common layout (``vertex`` then an all-triangle ``face`` list) is
    taken here (``bun_zipper.ply``: 0.1 s against 0.4 s in trimesh); polygons,
    extra face properties or irregular line structure return None.
    """
    if not _is_ascii_triangle_mesh(header):
        return None
    nv, nf = header.elements[0].count, header.elements[1].count
    newlines = np.flatnonzero(np.frombuffer(body, np.uint8) == ord("\n"))
    if len(newlines) < nv + nf or nv == 0:
        return None
    vertex_end, face_end = newlines[nv - 1] + 1, newlines[nv + nf - 1] + 1
    layout = _VertexLayout.of(header.elements[0], name)
    arrays = _read_ascii(io.BytesIO(body[:vertex_end]), header, layout, name)
    try:
        faces = np.loadtxt(io.BytesIO(body[vertex_end:face_end]), dtype=np.int64, ndmin=2,
                           comments=None)
    except ValueError:  # polygons of mixed sizes: trimesh triangulates them
        return None
    if faces.shape != (nf, 4) or np.any(faces[:, 0] != 3):
        return None
    return arrays, faces[:, 1:]


def open_ply_stream(path: Path, budget: InputBudget | None = None
                    ) -> tuple[PointStream, dict, str] | None:
    """A :class:`~fitter.fitting.io.points.PointStream` over an uncompressed binary PLY
    point cloud (the memory-mapped path of :func:`load_ply`), its provenance record (without
    ``sha256`` and ``bytes``: the out-of-core passes hash the file once,
    ``fitter.fitting.stream``) and its units; ``None`` for any other PLY, which
    :func:`load_ply` reads whole.

    Raises
    ------
    ScanError
        A malformed header, counts the file cannot hold, or more vertices than ``budget``.
    """
    name = path.name
    with open(path, "rb") as fh:
        header = parse_header(fh, name)
    if not (_is_point_cloud(header) and header.byte_order):
        return None
    available, where = _body_bytes_bound(path, False, header)
    check_claimed_counts(header, available, name, where)
    element = header.elements[0]
    if budget is not None:
        budget.take_points(name, element.count)
    layout = _VertexLayout.of(element, name)
    stream = PointStream.from_ply(path, len(header.raw), header.vertex_dtype(), element.count,
                                  layout.normals or ())
    record = file_record(name, nbytes=path.stat().st_size, sha256=None)
    source = _source(path, False, "ply-memmap-stream", record, header, layout)
    source["hash_method"] = "sha256 of the stored file, read in chunks beside the bounds pass"
    if layout.colors:
        source["warnings"].append("colours are not kept by the out-of-core fit (no texture)")
    return stream, source, units_from_comments(header.comments)
