"""Scan readers: one entry point, ``load_scan``, over a table of per-format loaders.

``load_scan(path)`` picks the loader by the file name's extension (``.gz``
stripped first and decompressed on the fly), returns a validated ``Scan``
(``fitter.fitting.io.scan``) and raises ``ScanError`` (a ``ValueError``) with the file
name and the problem for every bad input. One module per format, as in
trimesh's ``exchange/``:

==============================  ===========================================================
extension                       loader
==============================  ===========================================================
``.ply``                        ``fitter.fitting.io.ply`` (memory-mapped binary point clouds,
                                ``loadtxt`` for ASCII clouds, trimesh for meshes)
``.obj .stl .off .gltf .glb``   ``fitter.fitting.io.mesh`` (trimesh; OBJ/glTF textures kept)
``.xyz .pts .asc``              ``fitter.fitting.io.text``
``.conf``                       ``fitter.fitting.io.conf`` (Stanford range-scan registration)
``.e57``                        ``fitter.fitting.io.e57`` (pye57: every scan, poses applied)
``.las .laz``                   ``fitter.fitting.io.las`` (laspy, LAZ through lazrs)
==============================  ===========================================================

Every input is read once; its SHA-256 is computed on that read (streamed in
chunks, or over the memory map) and stored with its size in ``scan.source``
for the bundle's provenance. E57 and LAS/LAZ are the exception: their libraries
read the file by path, so it is hashed in a second streamed pass. ``thin=h`` keeps one
point per voxel of edge ``h`` (``fitter.fitting.io.thin``).

``open_point_stream(path, budget, stream_above)`` is the out-of-core entry point
(``fitter.fitting.stream``): for an uncompressed binary PLY point cloud, an E57 or a
LAS/LAZ file of more than ``stream_above`` points, a stream that reads the points block by
block (:data:`STREAMERS`: ``fitter.fitting.io.points``), never the whole cloud at once.

Every read is bounded by one ``InputLimits`` (``fitter.fitting.io.limits``: decompressed
bytes, compression ratio, points, files per registration, paths confined to the
``.conf``'s folder), the same for the command line and the admin uploads. Each loader
takes ``(path, gzipped, budget)``: the ``InputBudget`` of the whole read, which a
``.conf`` shares with every scan it names.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from functools import partial
from pathlib import Path

from .conf import load_conf
from .e57 import load_e57, open_e57_stream
from .las import load_las, open_las_stream
from .limits import InputBudget, InputLimits
from .mesh import load_mesh
from .ply import load_ply, open_ply_stream
from .points import PointStream, ReaderStream
from .scan import Scan, ScanError
from .source import check_path
from .text import load_text
from .thin import check_voxel_size, thin_scan, voxel_thin_indices

__all__ = ["LOADERS", "STREAMERS", "SUPPORTED_EXTENSIONS", "InputBudget", "InputLimits", "Scan",
           "ScanError", "load_scan", "open_point_stream", "thin_scan", "voxel_thin_indices"]


def _load_conf(path: Path, gzipped: bool, budget: InputBudget) -> Scan:
    return load_conf(path, gzipped, budget, lambda p: _load(p, budget, allow_conf=False))


#: extension (lower case, without ``.gz``) -> loader(path, gzipped, budget) -> Scan
LOADERS: dict[str, Callable[[Path, bool, InputBudget], Scan]] = {
    ".ply": load_ply,
    ".obj": partial(load_mesh, file_type="obj"),
    ".stl": partial(load_mesh, file_type="stl"),
    ".off": partial(load_mesh, file_type="off"),
    ".gltf": partial(load_mesh, file_type="gltf"),
    ".glb": partial(load_mesh, file_type="glb"),
    ".xyz": partial(load_text, fmt="xyz"),
    ".pts": partial(load_text, fmt="pts"),
    ".asc": partial(load_text, fmt="asc"),
    ".conf": _load_conf,
    ".e57": load_e57,
    ".las": load_las,
    ".laz": load_las,
}
#: formats read by path by their library (random access), never through gzip
NOT_GZIPPED = (".e57", ".las", ".laz")
SUPPORTED_EXTENSIONS = tuple(LOADERS)
#: extension -> opener(path, budget, stream_above) -> (stream, source, units) or None (the
#: file is then read whole by its loader: a PLY mesh or ASCII PLY, a small file)
STREAMERS: dict[str, Callable[[Path, InputBudget, int],
                              tuple[PointStream | ReaderStream, dict, str] | None]] = {
    ".ply": lambda path, budget, stream_above: open_ply_stream(path, budget),
    ".e57": open_e57_stream,
    ".las": open_las_stream,
    ".laz": open_las_stream,
}


def _split_extension(path: Path) -> tuple[str, bool]:
    suffixes = [s.lower() for s in path.suffixes]
    gzipped = bool(suffixes) and suffixes[-1] == ".gz"
    if gzipped:
        suffixes = suffixes[:-1]
    return (suffixes[-1] if suffixes else ""), gzipped


def _load(path: Path, budget: InputBudget, allow_conf: bool = True) -> Scan:
    ext, gzipped = _split_extension(path)
    loader = LOADERS.get(ext)
    if loader is None or (ext == ".conf" and not allow_conf):
        shown = ext + (".gz" if gzipped else "") or "(none)"
        raise ScanError(f"{path}: unsupported file type {shown!r}; supported: "
                        f"{', '.join(SUPPORTED_EXTENSIONS)} (each but "
                        f"{', '.join(NOT_GZIPPED)} also as .gz)")
    check_path(path)
    before = budget.points
    scan = loader(path, gzipped, budget)
    uncounted = scan.n_points - (budget.points - before)
    if uncounted > 0:  # a reader that cannot count before it allocates (trimesh)
        budget.take_points(path.name, uncounted)
    return scan


def load_scan(path: str | os.PathLike, thin: float | None = None,
              limits: InputLimits | None = None) -> Scan:
    """Load a scan file into a ``Scan``.

    Parameters
    ----------
    path : str or PathLike
        A ``.ply``, ``.obj``, ``.stl``, ``.off``, ``.gltf``, ``.glb``, ``.xyz``,
        ``.pts``, ``.asc`` or ``.conf`` file, each optionally gzip-compressed
        (``NAME.EXT.gz``), or an ``.e57``, ``.las`` or ``.laz`` file. A ``.conf``
        registers all the scans it lists into one cloud (``fitter.fitting.io.conf``), an
        ``.e57`` all its scans by their poses (``fitter.fitting.io.e57``).
    thin : float, optional
        Voxel edge ``h`` in scan units: keep one point per occupied voxel (the one
        nearest the voxel's centroid). None keeps every point.
    limits : InputLimits, optional
        What the read accepts (``fitter.fitting.io.limits``); default ``InputLimits()``.

    Returns
    -------
    Scan
        ``points`` (N, 3) float64, all finite, N >= 1; ``normals``, ``colors``,
        ``faces``, ``uv``/``texture`` when the file has them; ``units``; ``source``
        (file name, size, SHA-256, format, reader, every file read).

    Raises
    ------
    ScanError
        Missing, empty, unreadable, truncated or corrupt file; unsupported
        extension; no points; non-finite coordinates; a bad ``thin``; a limit of
        ``limits`` passed (naming the file, the limit and how to raise it); a ``.conf``
        naming a file outside its folder or the same file twice.
    """
    if thin is not None:
        check_voxel_size(thin)  # reject a bad argument before reading a large file
    scan = _load(Path(path), InputBudget(limits))
    return scan if thin is None else thin_scan(scan, thin)


def open_point_stream(path: str | os.PathLike, budget: InputBudget | None = None,
                      stream_above: int = 0
                      ) -> tuple[PointStream | ReaderStream, dict, str] | None:
    """``(stream, source, units)`` of a scan file read block by block, or ``None`` for a file
    no streamed reader takes (another format, gzip-compressed, a PLY mesh or ASCII PLY, at
    most ``stream_above`` points claimed): its loader (``load_scan``) reads it whole.

    The stream's ``source`` lacks ``sha256`` (the out-of-core passes hash the file beside
    their first pass). The points the file claims are counted against ``budget``.

    Raises
    ------
    ScanError
        What the format's reader finds wrong in the header (and, for an E57 file with
        invalid points, in the counting pass), a limit of ``budget`` passed.
    """
    path = Path(path)
    ext, gzipped = _split_extension(path)
    opener = STREAMERS.get(ext)
    if opener is None or gzipped or not path.is_file():
        return None  # the loaders say what is wrong
    check_path(path)
    return opener(path, budget if budget is not None else InputBudget(), stream_above)
