"""ASPRS LAS and LAZ point clouds through ``laspy`` (LAZ decompressed by ``lazrs``).

A LAS file (ASPRS LAS 1.0-1.4) stores each point's coordinates as 32-bit integers
``X, Y, Z`` with a per-file scale and offset in the header; the coordinates are

    x = X s_x + o_x,   y = Y s_y + o_y,   z = Z s_z + o_z

(laspy's ``ScaledArrayView``, computed in float64). LAZ is the same records compressed
with LASzip (Isenburg 2013, "LASzip: lossless compression of LiDAR data"); laspy
decompresses it through its ``lazrs`` backend. Point formats 2, 3, 5, 7, 8 and 10 carry
RGB, 16-bit by the specification, kept as ``Scan.colors`` (uint8, ``round(255 c /
65535)``); since many writers put 8-bit values in those fields, colours whose maximum is
at most 255 are taken as 8-bit (CloudCompare and PDAL do the same) and
``source["rgb_bits"]`` says which was read. Intensity is read but not kept (``Scan`` has
no intensity channel): its range is in ``source["intensity"]``.

Units come from the coordinate reference system the header's VLRs state
(``LASF_Projection``): the OGC WKT (record 2112; WKT1 ``UNIT`` or WKT2 ``LENGTHUNIT`` of
the projected CRS, by its factor to metres), else the GeoTIFF keys (record 34735:
``ProjLinearUnitsGeoKey`` 3076 or ``GeogLinearUnitsGeoKey`` 2052, EPSG unit codes 9001
metre, 9002 foot, 9003 US survey foot; GeoTIFF 1.0 section 6.3.1.3). A geographic CRS
(degrees), a unit these do not name, or no CRS at all gives ``units = "unknown"``; the
CRS found is recorded in ``source["crs"]``. The WKT is read by the small parser
here rather than by pyproj (laspy's ``parse_crs``): only the linear unit is needed, and
pyproj would add the PROJ database to the dependencies for it.

Bounded reading: the point count the header states is counted against the read's
``InputLimits`` before any point is read (and, for an uncompressed LAS, checked against
the file's size); the points are read through ``laspy.open(...).chunk_iterator`` in
blocks of ``BLOCK_POINTS`` into arrays of that count. laspy reads the file by path, so
the SHA-256 of the stored file is taken in a separate streamed pass
(``fitter.fitting.io.source.HashedInput``); a gzip-compressed LAS is refused (LAZ is the
compressed form).

Streamed reading (the out-of-core fit, ``fitter.fitting.stream``): :func:`open_las_stream`
checks the same header and returns a :class:`LasStream`, which reads the points through
the same :func:`las_blocks` as :func:`load_las` (the same points, bit for bit), seeking to
the block asked for; only the coordinates are read there (no colour, no intensity).

Every failure is a ``ScanError`` naming the file: the ``LASF`` signature is checked here
first, and a LAZ file's chunk table is bounded before lazrs reads it
(:func:`check_laz_chunk_table`); what laspy and lazrs raise on a corrupt or truncated file
(:func:`_las_errors`) is reported with its reason.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .limits import InputBudget
from .points import ReaderStream
from .scan import Scan, ScanError, colors_to_uint8, make_scan, new_source
from .source import HashedInput, file_record

#: the first bytes of every LAS and LAZ file (the header's ``File Signature``)
LAS_SIGNATURE = b"LASF"
#: points read at a time (about 30 MB of records and converted coordinates)
BLOCK_POINTS = 1 << 20
#: factor to metres -> unit (EPSG 9001, 9002, 9003, and the metric sub-units)
UNITS_BY_FACTOR = {1.0: "m", 0.3048: "ft", 1200 / 3937: "us-ft", 0.001: "mm", 0.01: "cm"}
#: EPSG unit of measure code -> factor to metres (the GeoTIFF linear units)
EPSG_LINEAR_UNITS = {9001: 1.0, 9002: 0.3048, 9003: 1200 / 3937, 1025: 0.001, 1033: 0.01}
GEO_KEY_MODEL, GEO_KEY_GEOG_LINEAR_UNITS = 1024, 2052
GEO_KEY_PROJECTED_CS, GEO_KEY_PROJ_LINEAR_UNITS, GEO_KEY_VERTICAL_UNITS = 3072, 3076, 4099
#: characters of a WKT kept in ``source["crs"]``
MAX_WKT_CHARS = 4000
_WKT_TOKEN = re.compile(r'\s*(?:("(?:[^"]|"")*")|([\[\]\(\),])|([^\s\[\]\(\),"]+))')
PROJECTED_KEYWORDS = ("PROJCS", "PROJCRS", "PROJECTEDCRS")
GEOGRAPHIC_KEYWORDS = ("GEOGCS", "GEOGCRS", "GEOGRAPHICCRS", "GEODCRS", "GEODETICCRS")
GEOCENTRIC_KEYWORDS = ("GEOCCS",)
VERTICAL_KEYWORDS = ("VERT_CS", "VERTCRS", "VERTICALCRS")


def _las_errors() -> tuple[type[BaseException], ...]:
    """What laspy and lazrs raise on a corrupt or truncated file: ``LaspyException``
    (bad signature, a header too short, an unknown version or point format),
    ``LazrsError`` (a truncated or corrupt LAZ chunk), ``ValueError`` (a record buffer
    cut short), ``OSError`` and ``EOFError`` (reads past the end)."""
    from laspy.errors import LaspyException
    from lazrs import LazrsError

    return (LaspyException, LazrsError, ValueError, OSError, EOFError)


def parse_wkt(text: str) -> tuple[str, list]:
    """The tree ``(KEYWORD, [arguments])`` of an OGC WKT string (WKT1 or WKT2).

    Arguments are numbers (float), strings (quotes removed) or nested
    ``(KEYWORD, [...])``; either bracket pair is accepted.

    Raises
    ------
    ValueError
        Text that is not WKT: an unbalanced bracket, a missing keyword.
    """
    tokens = []
    pos = 0
    while pos < len(text):
        match = _WKT_TOKEN.match(text, pos)
        if match is None or match.end() == pos:
            if text[pos:].strip():
                raise ValueError(f"wkt: cannot read {text[pos:pos + 20]!r} at character {pos}")
            break
        pos = match.end()
        tokens.append(match.group(1) or match.group(2) or match.group(3))

    def node(i: int) -> tuple[tuple[str, list], int]:
        keyword = tokens[i]
        if i + 1 >= len(tokens) or tokens[i + 1] not in "[(":
            raise ValueError(f"wkt: keyword {keyword!r} is not followed by a bracket")
        args: list = []
        i += 2
        while i < len(tokens) and tokens[i] not in "])":
            token = tokens[i]
            if token == ",":
                i += 1
            elif token.startswith('"'):
                args.append(token[1:-1].replace('""', '"'))
                i += 1
            elif i + 1 < len(tokens) and tokens[i + 1] in "[(":
                child, i = node(i)
                args.append(child)
            else:
                try:
                    args.append(float(token))
                except ValueError:
                    args.append(token)  # an enumeration such as Cartesian or north
                i += 1
        if i >= len(tokens):
            raise ValueError(f"wkt: {keyword}[ is never closed")
        return (keyword.upper(), args), i + 1

    if not tokens:
        raise ValueError("wkt: the text is empty")
    tree, end = node(0)
    if end != len(tokens):
        raise ValueError(f"wkt: text after the closing bracket of {tree[0]}")
    return tree


def _find(tree: tuple[str, list], keywords: tuple[str, ...]) -> tuple[str, list] | None:
    """The first node (depth first) whose keyword is one of ``keywords``."""
    if tree[0] in keywords:
        return tree
    for arg in tree[1]:
        if isinstance(arg, tuple) and (found := _find(arg, keywords)) is not None:
            return found
    return None


def _direct_unit(tree: tuple[str, list]) -> tuple[str, float] | None:
    """``(name, factor to metres)`` of the ``UNIT``/``LENGTHUNIT`` directly under ``tree``,
    or inside its ``AXIS`` nodes (WKT2)."""
    children = [a for a in tree[1] if isinstance(a, tuple)]
    for child in children + [u for a in children if a[0] == "AXIS" for u in a[1]
                             if isinstance(u, tuple)]:
        if child[0] in ("UNIT", "LENGTHUNIT") and len(child[1]) >= 2 \
                and isinstance(child[1][0], str) and isinstance(child[1][1], float):
            return child[1][0], child[1][1]
    return None


def unit_of_factor(factor: float | None) -> str:
    """The unit of a length factor to metres (:data:`UNITS_BY_FACTOR`), ``"unknown"``
    for any other (within a relative 1e-9)."""
    if factor is None:
        return "unknown"
    for known, unit in UNITS_BY_FACTOR.items():
        if abs(factor - known) <= 1e-9 * known:
            return unit
    return "unknown"


def units_of_wkt(text: str) -> tuple[str, dict, list[str]]:
    """``(units, CRS record, warnings)`` of a WKT coordinate system (see the module
    docstring); a WKT that does not parse is a warning, not an error."""
    record: dict = {"source": "wkt", "wkt": text[:MAX_WKT_CHARS]}
    try:
        tree = parse_wkt(text)
    except ValueError as exc:
        return "unknown", record, [f"the WKT coordinate system does not parse ({exc})"]
    record["kind"] = tree[0]
    warnings: list[str] = []
    crs = _find(tree, PROJECTED_KEYWORDS) or _find(tree, GEOCENTRIC_KEYWORDS)
    if crs is None:
        if _find(tree, GEOGRAPHIC_KEYWORDS) is not None:
            return "unknown", record, ["the CRS is geographic: x and y are degrees, not "
                                       "lengths; units left unknown"]
        return "unknown", record, [f"the WKT ({tree[0]}) names no projected CRS"]
    unit = _direct_unit(crs)
    if unit is None:
        return "unknown", record, [f"the WKT's {crs[0]} names no length unit"]
    record["unit"], record["unit_to_metre"] = unit
    units = unit_of_factor(unit[1])
    vertical = _find(tree, VERTICAL_KEYWORDS)
    vertical_unit = _direct_unit(vertical) if vertical is not None else None
    if vertical_unit is not None and unit_of_factor(vertical_unit[1]) != units:
        warnings.append(f"the vertical unit ({vertical_unit[0]}) differs from the horizontal "
                        f"one ({unit[0]}); z is used as stored")
    if units == "unknown":
        warnings.append(f"the length unit {unit[0]!r} ({unit[1]:g} m) is not one Tessera "
                        "names; units left unknown")
    return units, record, warnings


def units_of_geo_keys(keys: dict[int, int]) -> tuple[str, dict, list[str]]:
    """``(units, CRS record, warnings)`` of GeoTIFF keys ``{key id: value}`` (the values
    stored in the directory itself)."""
    record: dict = {"source": "geotiff", "keys": {str(k): v for k, v in sorted(keys.items())}}
    if GEO_KEY_PROJECTED_CS in keys:
        record["epsg"] = keys[GEO_KEY_PROJECTED_CS]
    code = keys.get(GEO_KEY_PROJ_LINEAR_UNITS, keys.get(GEO_KEY_GEOG_LINEAR_UNITS))
    if code is None:
        if keys.get(GEO_KEY_MODEL) == 2:
            return "unknown", record, ["the CRS is geographic: x and y are degrees, not "
                                       "lengths; units left unknown"]
        return "unknown", record, ["the GeoTIFF keys name no linear unit "
                                   "(ProjLinearUnitsGeoKey); units left unknown"]
    record["unit_code"] = code
    units = unit_of_factor(EPSG_LINEAR_UNITS.get(code))
    warnings = [] if units != "unknown" else [f"the GeoTIFF linear unit code {code} is not "
                                              "one Tessera names; units left unknown"]
    vertical = keys.get(GEO_KEY_VERTICAL_UNITS)
    if vertical is not None and vertical != code:
        warnings.append(f"the vertical unit code ({vertical}) differs from the horizontal "
                        f"one ({code}); z is used as stored")
    return units, record, warnings


def units_of_header(header: Any) -> tuple[str, dict | None, list[str]]:
    """``(units, CRS record or None, warnings)`` from a laspy header's projection VLRs
    (and EVLRs): the WKT first, else the GeoTIFF keys."""
    from laspy.vlrs.known import GeoKeyDirectoryVlr, WktCoordinateSystemVlr

    records = list(header.vlrs) + list(header.evlrs or [])
    for vlr in records:
        if isinstance(vlr, WktCoordinateSystemVlr) and vlr.string.strip():
            return units_of_wkt(vlr.string.strip())
    for vlr in records:
        if isinstance(vlr, GeoKeyDirectoryVlr):
            keys = {int(k.id): int(k.value_offset) for k in vlr.geo_keys
                    if k.tiff_tag_location == 0 and k.id}
            if keys:
                return units_of_geo_keys(keys)
    return "unknown", None, []


def check_laz_chunk_table(path: Path, header: Any, size: int) -> None:
    """Check the LASzip chunk table of a LAZ file before lazrs reads it.

    LASzip (Isenburg 2013) cuts the points into chunks and stores, at an offset given by
    the 8 bytes at the start of the point data (or, when those are -1, by the file's last
    8 bytes), ``version`` (uint32), ``number_of_chunks`` (uint32) and the compressed
    ``(points, bytes)`` of each chunk. lazrs allocates what these state without a bound: a
    corrupt count made it ask for 67 GB and abort the process. So here: the offset must
    lie in the file, ``number_of_chunks`` can be at most ``ceil(N / chunk_size)`` (``N``
    for variable-size chunks), and the chunks' bytes must fit in the file.

    Raises
    ------
    ScanError
        No LASzip VLR, or a chunk table outside these bounds.
    """
    import lazrs

    name, count, start = path.name, int(header.point_count), int(header.offset_to_point_data)
    record = next((v.record_data for v in header.vlrs
                   if v.user_id == "laszip encoded" and v.record_id == 22204), None)
    if record is None:
        raise ScanError(f"{name}: corrupt LAZ file: compressed points but no LASzip VLR")
    laz = lazrs.LazVlr(record)
    with open(path, "rb") as fh:
        fh.seek(start)
        (offset,) = struct.unpack("<q", fh.read(8).ljust(8, b"\0"))
        if offset == -1:
            fh.seek(max(size - 8, 0))
            (offset,) = struct.unpack("<q", fh.read(8).ljust(8, b"\0"))
        if not start + 8 <= offset <= size - 8:
            raise ScanError(f"{name}: corrupt or truncated LAZ file: its chunk table offset "
                            f"{offset:,} lies outside the file's point data ({start + 8:,}.."
                            f"{size - 8:,})")
        fh.seek(offset)
        _, chunks = struct.unpack("<II", fh.read(8))
        variable = laz.uses_variable_size_chunks()
        most = count if variable else -(-count // max(int(laz.chunk_size()), 1))
        if chunks > most:
            raise ScanError(f"{name}: corrupt LAZ file: its chunk table counts {chunks:,} "
                            f"chunks, more than the {most:,} that {count:,} points fill")
        fh.seek(start)
        table = lazrs.read_chunk_table(fh, laz)
    if table is not None:
        stored = sum(int(b) for _, b in table)
        if stored > size - start:
            raise ScanError(f"{name}: corrupt LAZ file: its chunks claim {stored:,} bytes, the "
                            f"file holds {size - start:,} after the header")


def _has_rgb(header: Any) -> bool:
    return {"red", "green", "blue"} <= set(header.point_format.dimension_names)


def las_blocks(reader: Any, name: str, count: int, first: int | None = None,
               rgb: bool = False) -> Iterator[tuple[np.ndarray, np.ndarray | None, np.ndarray]]:
    """Points ``first..count`` of an open ``laspy`` reader (sought to ``first``; None: from
    where the reader stands, a new reader's first point) in blocks of ``BLOCK_POINTS``
    (the one reading :func:`load_las` and :class:`LasStream` share): ``(points (m, 3)
    float64 = X s + o, RGB (m, 3) uint16 or None, intensity (m,))``.

    Raises
    ------
    ScanError
        The file holds fewer points than ``count`` (laspy returns what it could read).
    """
    if first is not None:
        reader.seek(first)
    done = reader.points_read
    while done < count:
        want = min(BLOCK_POINTS, count - done)
        chunk = reader.read_points(want)
        m = len(chunk)
        if m < want:
            raise ScanError(f"{name}: truncated: the header claims {count:,} points, the file "
                            f"holds {done + m:,}")
        points = np.empty((m, 3), np.float64)
        points[:, 0] = np.asarray(chunk.x, np.float64)
        points[:, 1] = np.asarray(chunk.y, np.float64)
        points[:, 2] = np.asarray(chunk.z, np.float64)
        colours = (np.column_stack([chunk.red, chunk.green, chunk.blue]).astype(np.uint16)
                   if rgb else None)
        yield points, colours, np.asarray(chunk.intensity)
        done += m


@contextmanager
def _as_scan_errors(path: Path) -> Iterator[None]:
    """What laspy and lazrs raise on a corrupt or truncated file, as a ``ScanError``."""
    try:
        yield
    except ScanError:  # a ValueError too: ours, already worded
        raise
    except _las_errors() as exc:
        kind = "LAZ" if path.suffix.lower() == ".laz" else "LAS"
        raise ScanError(f"{path.name}: corrupt or truncated {kind} file: "
                        f"{type(exc).__name__}: {exc}") from None


@dataclass
class _LasFile:
    """What the header of a checked LAS/LAZ file states."""

    count: int
    compressed: bool
    rgb: bool
    units: str
    crs: dict | None
    warnings: list[str]
    version: str
    point_format: int
    scales: list[float]
    offsets: list[float]


def _check_las(path: Path, budget: InputBudget, header: Any) -> _LasFile:
    """Check the header of the file at ``path`` (points against ``budget``, the file's
    length or LAZ chunk table) and return what it states."""
    name = path.name
    count = int(header.point_count)
    compressed = bool(header.are_points_compressed)
    if count == 0:
        raise ScanError(f"{name}: the file contains no points (its header counts 0)")
    budget.take_points(name, count)  # refused before a point is read
    size = path.stat().st_size
    needed = int(header.offset_to_point_data) + count * header.point_format.size
    if compressed:
        check_laz_chunk_table(path, header, size)
    elif size < needed:
        raise ScanError(f"{name}: truncated LAS file: the header claims {count:,} "
                        f"points of {header.point_format.size} bytes from byte "
                        f"{header.offset_to_point_data:,} ({needed:,} bytes), the "
                        f"file has {size:,}")
    units, crs, warnings = units_of_header(header)
    return _LasFile(count, compressed, _has_rgb(header), units, crs, warnings,
                    f"{header.version.major}.{header.version.minor}",
                    int(header.point_format.id), header.scales.tolist(),
                    header.offsets.tolist())


def _open_las(path: Path, gzipped: bool) -> Any:
    """``laspy.open`` of a file whose signature is checked first."""
    import laspy

    name = path.name
    if gzipped:
        raise ScanError(f"{name}: a gzip-compressed LAS file is not read; decompress it, or "
                        "compress it as LAZ")
    with open(path, "rb") as fh:
        head = fh.read(len(LAS_SIGNATURE))
    if head != LAS_SIGNATURE:
        raise ScanError(f"{name}: not a LAS/LAZ file: it starts with {head!r}, a LAS or LAZ "
                        f"file starts with {LAS_SIGNATURE.decode()!r}")
    return laspy.open(str(path))


def _las_source(path: Path, info: _LasFile, file: dict, reader: str) -> dict:
    fmt = "laz" if info.compressed else "las"
    source = new_source(path.name, str(path), fmt, "laszip" if info.compressed else None,
                        reader)
    source.update(bytes=file["bytes"], sha256=file["sha256"], files=[file],
                  las_version=info.version, point_format=info.point_format,
                  scales=info.scales, offsets=info.offsets, crs=info.crs)
    source["warnings"] += info.warnings
    return source


def load_las(path: Path, gzipped: bool, budget: InputBudget | None = None) -> Scan:
    """Read a ``.las`` or ``.laz`` point cloud (see the module docstring); ``budget``
    (default: the default ``InputLimits``) bounds the points the header claims.

    Raises
    ------
    ScanError
        Not a LAS/LAZ file, truncated or corrupt, gzip-compressed, no points, more
        points claimed than ``max_points``.
    """
    name = path.name
    budget = budget if budget is not None else InputBudget()
    with _as_scan_errors(path), _open_las(path, gzipped) as reader:
        info = _check_las(path, budget, reader.header)
        points = np.empty((info.count, 3), np.float64)
        colours16 = np.empty((info.count, 3), np.uint16) if info.rgb else None
        low, high = np.inf, -np.inf
        done = 0
        for block, rgb, intensity in las_blocks(reader, name, info.count, rgb=info.rgb):
            end = done + len(block)
            points[done:end] = block
            if colours16 is not None:
                colours16[done:end] = rgb
            low, high = min(low, float(intensity.min())), max(high, float(intensity.max()))
            done = end
    colours, rgb_bits = None, None
    if colours16 is not None:
        rgb_bits = 8 if int(colours16.max(initial=0)) <= 255 else 16
        colours = np.empty(colours16.shape, np.uint8)
        for start in range(0, len(colours), BLOCK_POINTS):  # float temporaries of a block only
            block = colours16[start:start + BLOCK_POINTS]
            colours[start:start + BLOCK_POINTS] = (block if rgb_bits == 8
                                                   else colors_to_uint8(block))
        del colours16
    with HashedInput(path, False, budget) as inp:
        file = inp.finish()
    source = _las_source(path, info, file, "laspy")
    source.update(rgb_bits=rgb_bits, intensity=[low, high],
                  hash_method="sha256 of the stored file, streamed in a separate pass "
                              "(laspy reads the file itself)")
    source["warnings"].append("intensity read but not kept (Scan has no intensity channel); "
                              "its range is in 'intensity'")
    return make_scan(name, points, colors=colours, units=info.units, source=source)


class LasStream(ReaderStream):
    """The points of a LAS or LAZ file read block by block for the out-of-core fit
    (``fitter.fitting.io.points.ReaderStream``): one segment, which laspy seeks into (a
    LAS record by its offset, a LAZ point by the LASzip chunk table: the chunk holding it
    is decompressed from its start), read by :func:`las_blocks` as :func:`load_las` reads
    it. The file is opened lazily in each process.
    """

    seekable = True

    def __init__(self, path: Path, count: int) -> None:
        super().__init__(Path(path).name, path, [count])

    def open_file(self) -> Any:
        """The file through ``laspy.open``."""
        with _as_scan_errors(self.path):
            return _open_las(self.path, False)

    def open_segment(self, segment: int, first: int) -> tuple[int, Iterator[np.ndarray]]:
        """The points from ``first`` on (laspy seeks to it)."""
        return first, self._points_from(first)

    def _points_from(self, first: int) -> Iterator[np.ndarray]:
        with _as_scan_errors(self.path):
            for points, _, _ in las_blocks(self.file(), self.name, self.count, first):
                yield points


def open_las_stream(path: Path, budget: InputBudget | None = None, stream_above: int = 0
                    ) -> tuple[LasStream, dict, str] | None:
    """A :class:`LasStream` over a LAS/LAZ file, its provenance record (without ``sha256``:
    the out-of-core passes hash the file beside their first pass) and its units; ``None``
    when its header counts at most ``stream_above`` points (then read it whole with
    :func:`load_las`).

    Raises
    ------
    ScanError
        As :func:`load_las`, for what the header shows.
    """
    with _as_scan_errors(path), _open_las(path, False) as reader:
        info = _check_las(path, budget or InputBudget(), reader.header)
    if info.count <= stream_above:
        return None
    file = file_record(path.name, nbytes=path.stat().st_size, sha256=None)
    source = _las_source(path, info, file, "laspy-stream")
    source["hash_method"] = "sha256 of the stored file, read in chunks beside the bounds pass"
    if info.rgb:
        source["warnings"].append("colours are not kept by the out-of-core fit (no texture)")
    source["warnings"].append("intensity not read by the out-of-core fit (Scan has no "
                              "intensity channel)")
    return LasStream(path, info.count), source, info.units
