"""The ``Scan`` container every reader returns, the one error type, and their checks.

A reader turns a file into plain arrays; ``make_scan`` validates them once
(shapes, dtypes, finite coordinates, face indices in range) so that every
format gives the fitter the same guarantees: ``points`` is ``(N, 3)`` float64,
finite, with ``N >= 1``. ``Scan`` itself only holds data.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from client_py.errors import TesseraError


class ScanError(TesseraError, ValueError):
    """A scan file that cannot be read: missing, empty, corrupt, unsupported or non-finite.

    The message names the file and says what is wrong (and, where it helps,
    what would be accepted).
    """


@dataclass(eq=False, repr=False)
class Scan:
    """A loaded scan: points and whatever per-point data the file carried.

    Attributes
    ----------
    points : ndarray, shape (N, 3), float64
        Point (vertex) coordinates in the file's own frame and units; all finite.
    normals : ndarray, shape (N, 3), float32, or None
        Per-point normals as stored in the file (not renormalised); None when absent.
    colors : ndarray, shape (N, 3), uint8, or None
        Per-point RGB; None when absent.
    faces : ndarray, shape (M, 3), int64, or None
        Triangles indexing ``points`` when the file is a mesh; None for point clouds
        (and after voxel thinning, which does not keep connectivity).
    uv : ndarray, shape (N, 2), float64, or None
        Per-point texture coordinates into ``texture`` (OBJ, glTF/GLB, textured PLY).
    texture : PIL.Image.Image or None
        The texture image ``uv`` refers to (decoded lazily by PIL).
    units : str
        Length unit the file states (``"mm"``, ``"m"``, ...), ``"unknown"`` otherwise.
        glTF/GLB are metres by specification.
    source : dict
        Provenance: ``name``, ``path``, ``bytes``, ``sha256`` of the input file as
        stored (compressed bytes for ``.gz``), ``format``, ``compression``,
        ``reader``, ``hash_method``, ``files`` (every file read, each with
        ``name``, ``bytes``, ``sha256``, ``role``), ``warnings`` (things read but
        not used, e.g. skipped ``.conf`` lines or a missing texture), and format
        specific entries (PLY ``properties``, text ``columns``, ``.conf`` ``scans``,
        ``thinning``).
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    faces: np.ndarray | None = None
    uv: np.ndarray | None = None
    texture: Any = None
    units: str = "unknown"
    source: dict = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        """Number of points ``N``."""
        return int(self.points.shape[0])

    def __len__(self) -> int:
        return self.n_points

    def __repr__(self) -> str:
        parts = [f"{self.n_points} points"]
        if self.faces is not None:
            parts.append(f"{len(self.faces)} faces")
        for name in ("normals", "colors", "uv"):
            if getattr(self, name) is not None:
                parts.append(name)
        if self.texture is not None:
            parts.append("texture {}x{}".format(*self.texture.size))
        name = self.source.get("name", "?")
        return f"Scan({name!r}: {', '.join(parts)}, units={self.units!r})"

    @classmethod
    def from_array(cls, points: Any, normals: Any = None, colors: Any = None,
                   name: str = "array", units: str = "unknown") -> Scan:
        """A scan from in-memory arrays, validated like a file.

        ``source`` records ``name``, ``bytes`` and ``sha256`` of the float64
        C-order point buffer (so the same array always gives the same digest)
        and ``format = "array"``.
        """
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64))
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ScanError(f"{name}: points must have shape (N, 3), got {pts.shape}")
        digest = hashlib.sha256(memoryview(pts).cast("B") if pts.size else b"").hexdigest()
        source = new_source(name, None, "array", compression=None, reader="array")
        source.update(bytes=pts.nbytes, sha256=digest,
                      hash_method="sha256 of the float64 C-order points")
        return make_scan(name, pts, normals=normals, colors=colors, units=units, source=source)


def new_source(name: str, path: str | None, fmt: str, compression: str | None,
               reader: str) -> dict:
    """An empty provenance record, filled in by the reader."""
    return {"name": name, "path": path, "bytes": None, "sha256": None, "format": fmt,
            "compression": compression, "reader": reader, "hash_method": None,
            "files": [], "warnings": []}


def colors_to_uint8(values: np.ndarray) -> np.ndarray:
    """RGB(A) of any numeric dtype to ``(N, 3)`` uint8.

    uint8 is kept; other integer types are taken as 0..max of their type
    (uint16 ``v // 257``), floats as 0..1 (the PLY and glTF convention), clipped.
    """
    rgb = np.asarray(values)[:, :3]
    if rgb.dtype == np.uint8:
        return np.ascontiguousarray(rgb)
    if np.issubdtype(rgb.dtype, np.integer):
        top = np.iinfo(rgb.dtype).max
        if top <= 255:
            return np.clip(rgb, 0, 255).astype(np.uint8)
        return np.clip(np.rint(rgb.astype(np.float64) * (255.0 / top)), 0, 255).astype(np.uint8)
    return np.clip(np.rint(rgb.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)


def count_nonfinite(points: np.ndarray) -> tuple[int, int]:
    """``(count, first_index)`` of rows with a NaN or inf coordinate; ``(0, -1)`` if none."""
    bad = ~np.isfinite(points).all(axis=1)
    count = int(np.count_nonzero(bad))
    return count, (int(np.argmax(bad)) if count else -1)


def make_scan(name: str, points: np.ndarray, *, normals: Any = None, colors: Any = None,
              faces: Any = None, uv: Any = None, texture: Any = None, units: str = "unknown",
              source: dict) -> Scan:
    """Validate reader output and build the ``Scan``.

    Raises
    ------
    ScanError
        No points, wrong shapes, non-finite coordinates (with their count), face
        indices out of range, or per-point arrays of the wrong length.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ScanError(f"{name}: points must have shape (N, 3), got {pts.shape}")
    n = pts.shape[0]
    if n == 0:
        raise ScanError(f"{name}: the file contains no points")
    bad, first = count_nonfinite(pts)
    if bad:
        raise ScanError(f"{name}: {bad} of {n} points have non-finite coordinates (NaN or inf); "
                        f"the first is point {first}: {pts[first].tolist()}")

    def per_point(value: Any, what: str, width: int, dtype: Any) -> np.ndarray | None:
        if value is None:
            return None
        arr = np.ascontiguousarray(value, dtype=dtype)
        if arr.shape != (n, width):
            raise ScanError(f"{name}: {what} must have shape ({n}, {width}) to match the "
                            f"points, got {arr.shape}")
        return arr

    normals = per_point(normals, "normals", 3, np.float32)
    colors = per_point(colors, "colors", 3, np.uint8)
    uv = per_point(uv, "uv", 2, np.float64)
    if faces is not None:
        faces = np.ascontiguousarray(faces, dtype=np.int64)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ScanError(f"{name}: faces must be triangles, shape (M, 3), got {faces.shape}")
        if faces.size and (faces.min() < 0 or faces.max() >= n):
            raise ScanError(f"{name}: face vertex indices must lie in [0, {n}), found "
                            f"{int(faces.min())}..{int(faces.max())}")
        if faces.shape[0] == 0:
            faces = None
    return Scan(points=pts, normals=normals, colors=colors, faces=faces, uv=uv,
                texture=texture, units=units, source=source)


_UNIT_ALIASES = {
    "mm": "mm", "millimeter": "mm", "millimeters": "mm", "millimetre": "mm", "millimetres": "mm",
    "cm": "cm", "centimeter": "cm", "centimeters": "cm", "centimetre": "cm", "centimetres": "cm",
    "m": "m", "meter": "m", "meters": "m", "metre": "m", "metres": "m",
    "um": "um", "µm": "um", "micron": "um", "microns": "um", "micrometer": "um",
    "micrometers": "um", "micrometre": "um", "micrometres": "um",
    "km": "km", "in": "in", "inch": "in", "inches": "in", "ft": "ft", "foot": "ft", "feet": "ft",
}


def units_from_comments(comments: list[str]) -> str:
    """The unit a header comment states, e.g. ``units mm``, ``Units: millimeters``, ``unit=m``.

    Known spellings are normalised (``millimetres`` -> ``"mm"``); an unknown word
    after ``unit(s)`` is returned lower-cased; ``"unknown"`` when no comment says.
    """
    for text in comments:
        words = text.replace(":", " ").replace("=", " ").split()
        for i, word in enumerate(words[:-1]):
            if word.lower() in ("unit", "units", "length_unit", "length_units"):
                value = words[i + 1].lower().strip(".,;")
                return _UNIT_ALIASES.get(value, value)
    return "unknown"
