"""ASTM E57 scans through ``pye57`` (libE57Format): every scan of the file in one frame.

An E57 file (ASTM E2807-11, "Standard Specification for 3D Imaging Data Exchange")
holds any number of scans under ``/data3D``; each has a point prototype (which fields
every point carries), a compressed vector of points and a ``pose``, the rigid-body
transform from the scan's own frame to the file's frame:

    p_file = R(q) p_scan + t,   q = (w, x, y, z) a unit quaternion,

with ``R(q)`` the rotation of column vectors (``fitter.fitting.io.conf.quaternion_matrix``,
given ``(x, y, z, w)``). A scan without a pose is already in the file's frame. Points are
cartesian (``cartesianX/Y/Z``) or spherical (``sphericalRange``, ``sphericalAzimuth``,
``sphericalElevation``, radians), converted by ``pye57.utils.convert_spherical_to_cartesian``:

    x = r cos(el) cos(az),   y = r cos(el) sin(az),   z = r sin(el).

A point whose ``cartesianInvalidState`` / ``sphericalInvalidState`` is non-zero (1: only a
direction, 2: no measurement) is dropped. Lengths are metres by the standard, so
``units = "m"``. The per-point flags ``isColorInvalid`` and ``isIntensityInvalid`` are not
read (pye57 reads neither); such points keep the colour the file stores.

Colour (``colorRed/Green/Blue``, any integer or float range) becomes ``Scan.colors``
(uint8), mapped from the scan's ``colorLimits`` (or the prototype's bounds) onto 0..255;
when only some scans have colour, none is kept and ``source["warnings"]`` says so.
``Scan`` has no intensity channel: each scan's intensity range is recorded in
``source["scans"]`` and the intensity itself is not kept. ``source["scans"]`` lists every
scan with its name, guid, the points its header claims, the points kept, the invalid
points dropped, its coordinate system and pose.

Bounded reading: the point counts the headers claim are counted against the read's
``InputLimits`` before any point is read; the points are read scan by scan through
libE57Format's compressed-vector reader in blocks of ``BLOCK_POINTS`` into arrays of the
claimed size, shrunk in place to the points kept. libE57Format reads the file itself (by
path, with random access), so the SHA-256 of the stored file is taken in a separate
streamed pass (``fitter.fitting.io.source.HashedInput``), and a gzip-compressed E57 is
refused: decompress it first.

Streamed reading (the out-of-core fit, ``fitter.fitting.stream``): :func:`open_e57_stream`
checks the same headers, counts the valid points of each scan that has an invalid-state
field (a pass decoding that field only) and returns an :class:`E57Stream`, which
decodes the points scan by scan, block by block, through the same :func:`scan_blocks` as
:func:`load_e57` (the same points in the same order, bit for bit), holding a few blocks.
Only the coordinates are read there: the out-of-core fit keeps no colour and no intensity.

Every failure is a ``ScanError`` naming the file: the signature (``ASTM-E57``) and the
file length the header states are checked here first, for a clear message on a file that
is not E57 or is truncated; what libE57Format raises (``libe57.E57Exception``) is
reported with its reason.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .conf import quaternion_matrix
from .limits import InputBudget
from .points import ReaderStream
from .scan import Scan, ScanError, make_scan, new_source
from .source import HashedInput, file_record

#: the first bytes of every E57 file (ASTM E2807, file header ``fileSignature``)
E57_SIGNATURE = b"ASTM-E57"
#: the file header: signature, major and minor version (uint32), physical length, XML
#: offset, XML length, page size (uint64), little-endian
_HEADER = struct.Struct("<8sIIQQQQ")
#: points read from a scan at a time (about 60 MB of buffers with every field)
BLOCK_POINTS = 1 << 20
CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
COLOURS = ("colorRed", "colorGreen", "colorBlue")
#: characters of the file's ``coordinateMetadata`` (a CRS description) kept in the source
MAX_METADATA_CHARS = 2000


def check_e57_header(path: Path, size: int) -> tuple[int, int]:
    """``(major, minor)`` version of the E57 file at ``path`` of ``size`` bytes.

    Raises
    ------
    ScanError
        The file does not start with ``ASTM-E57``, is shorter than its header, or is
        shorter (truncated) or longer than the physical length its header states.
    """
    with open(path, "rb") as fh:
        head = fh.read(_HEADER.size)
    if not head.startswith(E57_SIGNATURE):
        shown = head[:16]
        printable = all(32 <= b < 127 or b in (9, 10, 13) for b in shown)
        raise ScanError(f"{path.name}: not an E57 file: it starts with "
                        f"{shown.decode('ascii') if printable else shown.hex(' ')!r}, an "
                        f"E57 file starts with {E57_SIGNATURE.decode()!r}")
    if len(head) < _HEADER.size:
        raise ScanError(f"{path.name}: truncated E57 file: {size} bytes, shorter than the "
                        f"{_HEADER.size}-byte file header")
    _, major, minor, physical, _, _, _ = _HEADER.unpack(head)
    if physical != size:
        what = "truncated E57 file" if size < physical else "E57 file with trailing bytes"
        raise ScanError(f"{path.name}: {what}: the header states {physical:,} bytes, the "
                        f"file has {size:,}")
    return major, minor


def _e57_error(name: str, exc: Exception, doing: str) -> ScanError:
    """A ``ScanError`` for what libE57Format raised, with its first line (its reason)."""
    reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
    return ScanError(f"{name}: corrupt E57 file: {doing}: {reason}")


def _text(node: Any, key: str) -> str | None:
    return node[key].value() if node.isDefined(key) else None


def _node_bounds(prototype: Any, field: str) -> tuple[float, float] | None:
    """``(minimum, maximum)`` a prototype field declares (scaled for a scaled integer)."""
    from pye57.utils import get_node

    node = get_node(prototype, field)
    for low, high in (("scaledMinimum", "scaledMaximum"), ("minimum", "maximum")):
        if hasattr(node, low) and hasattr(node, high):
            return float(getattr(node, low)()), float(getattr(node, high)())
    return None


def colour_limits(header: Any, prototype: Any) -> tuple[float, float]:
    """``(low, high)`` of the red channel: ``colorLimits`` when the scan states them, else
    the prototype's bounds, else 0..255 (the three channels share one range in every
    writer we know; the red one is read)."""
    if header.node.isDefined("colorLimits"):
        limits = header.node["colorLimits"]
        if limits.isDefined("colorRedMinimum") and limits.isDefined("colorRedMaximum"):
            return (float(limits["colorRedMinimum"].value()),
                    float(limits["colorRedMaximum"].value()))
    return _node_bounds(prototype, "colorRed") or (0.0, 255.0)


def apply_pose(local: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
               out: np.ndarray) -> None:
    """``out[k] = R local[k] + t`` for the ``(M, 3)`` rows of ``local``, written into ``out``.

    Three multiply-adds per coordinate in a fixed order rather than ``local @ R.T``: the
    same bits on every machine, and no BLAS call (a 10^6 x 3 by 3 x 3 product took 1 s
    on two busy cores, against 0.15 s here).
    """
    for i in range(3):
        out[:, i] = (rotation[i, 0] * local[:, 0] + rotation[i, 1] * local[:, 1]
                     + rotation[i, 2] * local[:, 2] + translation[i])


def colours_to_uint8(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """``rint(255 (c - low) / (high - low))`` clipped to 0..255, as uint8; ``(M, 3)``."""
    if not high > low:
        return np.clip(np.rint(values), 0, 255).astype(np.uint8)
    return np.clip(np.rint((values - low) * (255.0 / (high - low))), 0, 255).astype(np.uint8)


def read_pose(scan: Any) -> tuple[list[float], list[float]]:
    """``([w, x, y, z], [tx, ty, tz])`` of a scan node's ``pose``, each child read by its
    name (the standard does not fix their order); the identity where a part is absent."""
    rotation, translation = [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
    if scan.isDefined("pose"):
        pose = scan["pose"]
        if pose.isDefined("rotation"):
            node = pose["rotation"]
            rotation = [float(node[k].value()) if node.isDefined(k) else 0.0 for k in "wxyz"]
        if pose.isDefined("translation"):
            node = pose["translation"]
            translation = [float(node[k].value()) if node.isDefined(k) else 0.0 for k in "xyz"]
    return rotation, translation


@dataclass
class ScanReading:
    """How the points of one ``/data3D`` scan are read: picklable, so that a process that
    did not read the headers (a Dask worker) reads the scan the same way.

    Attributes
    ----------
    index : int
        The scan's index in ``/data3D``.
    label : str
        Its name (or ``"scan INDEX"``), for messages.
    claimed : int
        Points its header claims.
    xyz : tuple of str
        The three coordinate fields (cartesian or spherical).
    spherical : bool
    invalid : str or None
        The ``...InvalidState`` field, when the prototype has one.
    rotation, translation : ndarray or None
        ``R (3, 3)`` and ``t (3,)`` of the pose; None for no pose or the identity (the
        points are then kept bit for bit).
    """

    index: int
    label: str
    claimed: int
    xyz: tuple[str, str, str]
    spherical: bool
    invalid: str | None
    rotation: np.ndarray | None
    translation: np.ndarray | None


class _ScanPlan:
    """What one ``/data3D`` scan holds, read from its header before any point."""

    def __init__(self, e57: Any, index: int, name: str) -> None:
        from pye57 import libe57

        self.header = e57.get_header(index)
        self.prototype = libe57.StructureNode(self.header.points.prototype())
        fields = set(self.header.point_fields)
        self.index = index
        self.name = _text(self.header.node, "name") or f"scan {index}"
        self.guid = _text(self.header.node, "guid")
        self.claimed = int(self.header.point_count)
        if set(CARTESIAN) <= fields:
            self.coordinates, xyz, invalid = "cartesian", CARTESIAN, "cartesianInvalidState"
        elif set(SPHERICAL) <= fields:
            self.coordinates, xyz, invalid = "spherical", SPHERICAL, "sphericalInvalidState"
        else:
            raise ScanError(f"{name}: scan {index} ({self.name!r}) has neither cartesianX/Y/Z "
                            f"nor sphericalRange/Azimuth/Elevation; its fields are "
                            f"{sorted(fields)}")
        self.has_colour = set(COLOURS) <= fields
        self.has_intensity = "intensity" in fields
        self.rotation_wxyz, self.translation = read_pose(self.header.node)
        self.posed = bool(self.header.has_pose())
        if not (np.all(np.isfinite(self.rotation_wxyz)) and any(self.rotation_wxyz)
                and np.all(np.isfinite(self.translation))):
            raise ScanError(f"{name}: scan {index} ({self.name!r}) has a pose with a zero or "
                            f"non-finite rotation quaternion or translation: rotation (w, x, "
                            f"y, z) = {self.rotation_wxyz}, translation = {self.translation}")
        rotation = quaternion_matrix([*self.rotation_wxyz[1:], self.rotation_wxyz[0]])
        translation = np.asarray(self.translation, np.float64)
        # the identity pose (pye57 writes one on every scan) is skipped: p is kept bit for bit
        identity = np.array_equal(rotation, np.eye(3)) and not translation.any()
        posed = self.posed and not identity
        self.reading = ScanReading(index, self.name, self.claimed, xyz,
                                   self.coordinates == "spherical",
                                   invalid if invalid in fields else None,
                                   rotation if posed else None, translation if posed else None)

    def record(self, kept: int | None, dropped: int | None,
               intensity: list[float] | None) -> dict:
        """The scan's entry in ``source["scans"]``."""
        return {"name": self.name, "guid": self.guid, "points_claimed": self.claimed,
                "points": kept, "invalid_dropped": dropped, "coordinates": self.coordinates,
                "pose": ({"rotation_wxyz": self.rotation_wxyz, "translation": self.translation}
                         if self.posed else None),
                "colour": self.has_colour, "intensity": intensity}


def _read_fields(e57: Any, reading: ScanReading, fields: dict[str, Any], name: str
                 ) -> Iterator[dict[str, np.ndarray]]:
    """The raw values of ``fields`` (name -> dtype; libE57Format converts and scales into
    it) of every point of a scan, in blocks of up to ``BLOCK_POINTS``: views of buffers
    the next block overwrites.

    Raises
    ------
    ScanError
        The scan holds more or fewer points than its header claims; libE57Format failed.
    """
    from pye57 import libe57

    doing = f"reading the points of scan {reading.index} ({reading.label!r})"
    capacity = min(BLOCK_POINTS, max(reading.claimed, 1))
    arrays = {field: np.empty(capacity, dtype) for field, dtype in fields.items()}
    try:
        buffers = libe57.VectorSourceDestBuffer()
        for field, array in arrays.items():
            buffers.append(libe57.SourceDestBuffer(e57.image_file, field, array, capacity,
                                                   True, True))
        reader = e57.get_header(reading.index).points.reader(buffers)
    except libe57.E57Exception as exc:
        raise _e57_error(name, exc, doing) from None
    read = 0
    try:
        while True:
            try:
                n = reader.read()
            except libe57.E57Exception as exc:
                raise _e57_error(name, exc, doing) from None
            if not n:
                break
            if read + n > reading.claimed:
                raise ScanError(f"{name}: scan {reading.index} ({reading.label!r}) holds more "
                                f"points than the {reading.claimed:,} its header claims")
            read += n
            yield {field: array[:n] for field, array in arrays.items()}
    finally:
        try:
            reader.close()
        except libe57.E57Exception as exc:
            raise _e57_error(name, exc, doing) from None
    if read < reading.claimed:
        raise ScanError(f"{name}: scan {reading.index} ({reading.label!r}): its header claims "
                        f"{reading.claimed:,} points, the file holds {read:,}")


def scan_blocks(e57: Any, reading: ScanReading, name: str,
                colour: tuple[float, float] | None = None, intensity: bool = False
                ) -> Iterator[tuple[np.ndarray, np.ndarray | None, np.ndarray | None, int]]:
    """The valid points of one scan in the file's frame, block by block (the one reading
    :func:`load_e57` and :class:`E57Stream` share, so both give the same bits).

    Yields ``(points (m, 3) float64, colours (m, 3) uint8 or None, intensity (m,) or None,
    points read)``: invalid points dropped, spherical coordinates converted, the pose
    applied; colours only with ``colour = (low, high)``, the file's colour range.
    """
    from pye57.utils import convert_spherical_to_cartesian

    fields = dict.fromkeys(reading.xyz, np.float64)
    if intensity:
        fields["intensity"] = np.float64
    if colour is not None:
        fields.update(dict.fromkeys(COLOURS, np.float64))
    if reading.invalid:
        fields[reading.invalid] = np.int8
    with closing(_read_fields(e57, reading, fields, name)) as blocks:  # closed with us
        for arrays in blocks:
            n = len(arrays[reading.xyz[0]])
            keep = slice(None) if reading.invalid is None else arrays[reading.invalid] == 0
            block = np.column_stack([arrays[f][keep] for f in reading.xyz])
            if reading.spherical:
                block = convert_spherical_to_cartesian(block)
            if reading.rotation is not None:
                local, block = block, np.empty_like(block)
                apply_pose(local, reading.rotation, reading.translation, block)
            rgb = None
            if colour is not None:
                rgb = colours_to_uint8(np.column_stack([arrays[f][keep] for f in COLOURS]),
                                       *colour)
            yield block, rgb, (arrays["intensity"][keep] if intensity else None), n


def count_valid(e57: Any, reading: ScanReading, name: str) -> int:
    """Valid points of a scan: all it claims, or (with an invalid-state field) those whose
    state is 0, counted in a pass that decodes that field only."""
    if reading.invalid is None:
        return reading.claimed
    return sum(int(np.count_nonzero(arrays[reading.invalid] == 0))
               for arrays in _read_fields(e57, reading, {reading.invalid: np.int8}, name))


def _read_scan(e57: Any, plan: _ScanPlan, colour: bool, points: np.ndarray,
               colours: np.ndarray | None, start: int, name: str) -> tuple[int, dict]:
    """Read ``plan``'s points into ``points[start:]`` (and ``colours``), dropping invalid
    points and applying the pose; ``(points kept, the scan's source record)``."""
    limits = colour_limits(plan.header, plan.prototype) if colour else None
    read = kept = 0
    lo_i, hi_i = np.inf, -np.inf
    for block, rgb, values, n in scan_blocks(e57, plan.reading, name, limits,
                                             plan.has_intensity):
        m = len(block)
        points[start + kept:start + kept + m] = block
        if rgb is not None:
            colours[start + kept:start + kept + m] = rgb
        if values is not None and m:
            lo_i, hi_i = min(lo_i, float(values.min())), max(hi_i, float(values.max()))
        kept += m
        read += n
    intensity = [lo_i, hi_i] if plan.has_intensity and kept else None
    return kept, plan.record(kept, read - kept, intensity)


def _open_e57(path: Path, gzipped: bool, budget: InputBudget
              ) -> tuple[Any, list[_ScanPlan], dict]:
    """The open file, its scans' plans and what the source records of the file as a whole
    (version, images, coordinate metadata), the points its headers claim counted against
    ``budget``. The caller closes the file."""
    import pye57
    from pye57 import libe57

    name = path.name
    if gzipped:
        raise ScanError(f"{name}: a gzip-compressed E57 file is not read (libE57Format "
                        "reads the file in place, with random access); decompress it first")
    size = path.stat().st_size
    version = check_e57_header(path, size)
    try:
        e57 = pye57.E57(str(path))
    except libe57.E57Exception as exc:
        raise _e57_error(name, exc, "opening the file") from None
    try:
        try:
            plans = [_ScanPlan(e57, i, name) for i in range(e57.scan_count)]
            images = len(e57.root["images2D"]) if e57.root.isDefined("images2D") else 0
            metadata = _text(e57.root, "coordinateMetadata") or ""
        except libe57.E57Exception as exc:
            raise _e57_error(name, exc, "reading the scan headers") from None
        if not plans:
            raise ScanError(f"{name}: the file contains no points (its data3D lists no scans)")
        claimed = sum(p.claimed for p in plans)
        if claimed == 0:
            raise ScanError(f"{name}: the file contains no points (its {len(plans)} scan(s) "
                            "hold 0 points)")
        budget.take_points(name, claimed)  # refused before a point is read
    except BaseException:
        e57.close()
        raise
    return e57, plans, {"version": version, "images": images, "metadata": metadata}


def _no_valid_points(name: str, plans: list[_ScanPlan]) -> ScanError:
    return ScanError(f"{name}: the file contains no points: all "
                     f"{sum(p.claimed for p in plans):,} points of its {len(plans)} scan(s) "
                     "are marked invalid")


def _e57_source(path: Path, reader: str, scans: list[dict], file_info: dict,
                file: dict) -> dict:
    """The provenance record of an E57 read (``scans`` from :meth:`_ScanPlan.record`)."""
    version, images, metadata = file_info["version"], file_info["images"], file_info["metadata"]
    source = new_source(path.name, str(path), "e57", None, reader)
    source.update(bytes=file["bytes"], sha256=file["sha256"], files=[file], scans=scans,
                  e57_version=f"{version[0]}.{version[1]}",
                  registration="p_file = R(q) p_scan + t, q = (w, x, y, z) (E57 pose)")
    if metadata:
        source["coordinate_metadata"] = metadata[:MAX_METADATA_CHARS]
    if images:
        source["warnings"].append(f"{images} 2D image(s) (images2D) not used")
    return source


def load_e57(path: Path, gzipped: bool, budget: InputBudget | None = None) -> Scan:
    """Read every scan of an ``.e57`` file into one cloud (see the module docstring);
    ``budget`` (default: the default ``InputLimits``) bounds the points the headers claim.

    Raises
    ------
    ScanError
        Not an E57 file, truncated or corrupt, gzip-compressed, no scans or no valid
        points, a scan with no coordinates, more points claimed than ``max_points``.
    """
    name = path.name
    budget = budget if budget is not None else InputBudget()
    e57, plans, file_info = _open_e57(path, gzipped, budget)
    try:
        claimed = sum(p.claimed for p in plans)
        colour = all(p.has_colour for p in plans)
        points = np.empty((claimed, 3), np.float64)
        colours = np.empty((claimed, 3), np.uint8) if colour else None
        kept, scans = 0, []
        for plan in plans:
            count, record = _read_scan(e57, plan, colour, points, colours, kept, name)
            kept += count
            scans.append(record)
    finally:
        e57.close()
    if kept == 0:
        raise _no_valid_points(name, plans)
    if kept < claimed:  # shrink in place (realloc): memory follows the points kept
        points.resize((kept, 3), refcheck=False)
        if colours is not None:
            colours.resize((kept, 3), refcheck=False)
    with HashedInput(path, False, budget) as inp:
        file = inp.finish()
    source = _e57_source(path, "pye57", scans, file_info, file)
    source["hash_method"] = ("sha256 of the stored file, streamed in a separate pass "
                             "(libE57Format reads the file itself)")
    if any(p.has_colour for p in plans) and not colour:
        with_colour = sum(p.has_colour for p in plans)
        source["warnings"].append(f"colour not kept: only {with_colour} of the {len(plans)} "
                                  "scans have colour")
    if any(p.has_intensity for p in plans):
        source["warnings"].append("intensity read but not kept (Scan has no intensity "
                                  "channel); each scan's range is in 'scans'")
    return make_scan(name, points, colors=colours, units="m", source=source)


class E57Stream(ReaderStream):
    """The valid points of every scan of an E57 file, in the file's frame, read block by
    block for the out-of-core fit (``fitter.fitting.io.points.ReaderStream``): one segment
    per scan, each decoded from its first point by libE57Format's compressed-vector reader
    (which cannot seek) through :func:`scan_blocks`, exactly as :func:`load_e57` reads it.
    The file is opened lazily in each process.

    Parameters
    ----------
    path : Path
    readings : list of ScanReading
        Every scan of ``/data3D``, in order.
    valid : list of int
        The valid points of each scan (:func:`count_valid`).
    """

    def __init__(self, path: Path, readings: list[ScanReading], valid: list[int]) -> None:
        super().__init__(Path(path).name, path, valid)
        self.readings = list(readings)

    def open_file(self) -> Any:
        """The file through pye57."""
        import pye57
        from pye57 import libe57

        try:
            return pye57.E57(str(self.path))
        except libe57.E57Exception as exc:
            raise _e57_error(self.name, exc, "opening the file") from None

    def open_segment(self, segment: int, first: int) -> tuple[int, Iterator[np.ndarray]]:
        """Scan ``segment`` from its first point (``first`` is reached by decoding)."""
        return 0, self._points_of(segment)

    def _points_of(self, segment: int) -> Iterator[np.ndarray]:
        with closing(scan_blocks(self.file(), self.readings[segment], self.name)) as blocks:
            for points, _, _, _ in blocks:
                yield points


def open_e57_stream(path: Path, budget: InputBudget | None = None, stream_above: int = 0
                    ) -> tuple[E57Stream, dict, str] | None:
    """An :class:`E57Stream` over an E57 file, its provenance record (without ``sha256``:
    the out-of-core passes hash the file beside their first pass) and its units (``"m"``);
    ``None`` when its headers claim at most ``stream_above`` points (then read it whole with
    :func:`load_e57`).

    Before it returns, the valid points of every scan with an invalid-state field are
    counted (:func:`count_valid`: one pass decoding that field only), so that the stream's
    indices are known; a scan without one counts the points its header claims.

    Raises
    ------
    ScanError
        As :func:`load_e57`, for what the headers and the counting pass show.
    """
    name = path.name
    e57, plans, file_info = _open_e57(path, False, budget or InputBudget())
    try:
        if sum(p.claimed for p in plans) <= stream_above:
            return None
        valid = [count_valid(e57, plan.reading, name) for plan in plans]
    finally:
        e57.close()
    if not any(valid):
        raise _no_valid_points(name, plans)
    scans = [plan.record(kept, plan.claimed - kept if plan.reading.invalid else None, None)
             for plan, kept in zip(plans, valid, strict=True)]
    file = file_record(name, nbytes=path.stat().st_size, sha256=None)
    source = _e57_source(path, "pye57-stream", scans, file_info, file)
    source["hash_method"] = "sha256 of the stored file, read in chunks beside the bounds pass"
    if any(p.has_colour for p in plans):
        source["warnings"].append("colours are not kept by the out-of-core fit (no texture)")
    if any(p.has_intensity for p in plans):
        source["warnings"].append("intensity not read by the out-of-core fit (Scan has no "
                                  "intensity channel)")
    return E57Stream(path, [p.reading for p in plans], valid), source, "m"
