"""A whole bundle at one level of detail: what level ``L`` needs, its mesh and its PLY.

The bundle's ``manifest.json`` lists the tiles (``manifest["tiles"]``, see
docs/format.md, "Tiles"). :func:`plan_level` is the one rule for "level ``L``
everywhere": the detail tile files (levels ``0..L``), the texture tiles its
vertex colours come from and the grid it is tessellated on;
:func:`plan_levels` lists the levels a viewer offers for download.
:func:`write_level_ply` makes that PLY from the decoded patch, tiles and
texture images, for ``tessera tessellate BUNDLE --level L`` and for the
browser's worker session (:mod:`client_py.session`) alike, so both write the
same bytes. No I/O of its own: the caller passes ``read(name) -> bytes`` (a
file reader, a ``fetch``, a dict's ``__getitem__``), or the decoded objects.
"""

from __future__ import annotations

import math
import reprlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from .errors import PatchFormatError
from .format import read_detail_tile, read_patch
from .layers import (
    MAX_LEVEL,
    MAX_SPANS,
    DetailTile,
    TextureImage,
    tessellate_region,
    transform_mesh,
)
from .ply import write_ply
from .surface import NurbsSurface
from .tessellate import Mesh

PLY_MAX_RESOLUTION = 1025  # a level-L PLY's grid is capped here (about a million vertices)
BASE_RESOLUTION = 256  # the grid of the base alone (level -1), as ``tessera tessellate`` makes it
BASE_FILE = "base.tsp"  # the one name a manifest's ``base.file`` may give
TEXTURE_EXTENSIONS = ("webp", "png")
_NAMING = ("relative POSIX paths inside the bundle, as the fitter writes them: base.tsp, "
           "detail/K/I_J.tsd, texture/K/I_J.webp or .png")


class ManifestError(PatchFormatError):
    """A bundle manifest that ``client_py`` cannot plan from: a part it uses is missing,
    of the wrong type or out of range, or a file name leaves the bundle.

    A :class:`~client_py.errors.PatchFormatError` (the one error of a bad file), so a
    caller that catches that also catches this.

    Attributes
    ----------
    where : str
        The manifest entry, e.g. ``tiles.detail node [3] file``; the message is
        ``invalid bundle manifest: WHERE REASON``.
    """

    def __init__(self, where: str, reason: str) -> None:
        super().__init__(0, f"{where} {reason}", "manifest")
        self.where, self._detail = where, reason
        self.args = (f"invalid bundle manifest: {where} {reason}",)

    def __reduce__(self) -> tuple:
        """Pickle by the constructor's arguments."""
        return type(self), (self.where, self._detail)


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _mapping(value: object, where: str, optional: bool = True) -> dict:
    """``value`` if it is a JSON object; ``{}`` for a missing (``None``) optional one."""
    if value is None and optional:
        return {}
    if not isinstance(value, dict):
        raise ManifestError(where, f"must be a JSON object, got {_shown(value)}")
    return value


_SHORT_REPR = reprlib.Repr()  # bounded depth and length: a hostile value is never walked
_SHORT_REPR.maxlevel, _SHORT_REPR.maxstring, _SHORT_REPR.maxother = 3, 40, 40


def _shown(value: object) -> str:
    """A value for a message: its repr cut to 60 characters (nested lists and dicts cut
    three levels down), and its type."""
    text = _SHORT_REPR.repr(value)
    return f"{text[:57]}... ({type(value).__name__})" if len(text) > 60 else \
        f"{text} ({type(value).__name__})"


def _optional_number(value: object, where: str) -> float | int | None:
    """A finite number or ``None`` (JSON ``null`` or absent)."""
    if value is None or (isinstance(value, int | float) and not isinstance(value, bool)
                         and math.isfinite(value)):
        return value
    raise ManifestError(where, f"must be a finite number or null, got {_shown(value)}")


def check_file_name(name: object, where: str) -> str:
    """``name`` if it names a file inside the bundle; else :class:`ManifestError`.

    Accepted: ``base.tsp``, ``detail/K/I_J.tsd`` and ``texture/K/I_J.webp|png``
    (decimal ``K, I, J`` without leading zeros) — so no absolute path, no ``..``,
    no backslash or NUL, and a reader that joins the name to the bundle's folder or
    URL stays inside it.
    """
    if not isinstance(name, str):
        raise ManifestError(where, f"must be a file name (a string), got {_shown(name)}")
    parts = name.split("/")
    if name.startswith("/") or name[1:3] == ":\\" or name[1:3] == ":/":
        problem = "is an absolute path"
    elif ".." in parts:
        problem = "climbs out of the bundle ('..')"
    elif "\\" in name or "\0" in name:
        problem = "holds a backslash or NUL"
    elif name == BASE_FILE or _tile_name_parts(name) is not None:
        return name
    else:
        problem = "is not a bundle file name"
    raise ManifestError(where, f"{name[:80]!r} {problem}; file names are {_NAMING}")


def _tile_name_parts(name: str) -> tuple[str, int, int, int, str] | None:
    """``(kind, K, I, J, extension)`` of ``kind/K/I_J.ext``, or ``None``."""
    parts = name.split("/")
    if len(parts) != 3 or parts[0] not in ("detail", "texture"):
        return None
    stem, dot, ext = parts[2].partition(".")
    i, underscore, j = stem.partition("_")
    numbers = (parts[1], i, j)
    if not dot or not underscore or not all(
            x.isdigit() and x.isascii() and (x == "0" or x[0] != "0") for x in numbers):
        return None
    if ext not in (("tsd",) if parts[0] == "detail" else TEXTURE_EXTENSIONS):
        return None
    return parts[0], int(parts[1]), int(i), int(j), ext


def _tiles(manifest: dict) -> dict:
    if not isinstance(manifest, dict):
        raise ManifestError("manifest", f"must be a JSON object, got {_shown(manifest)}")
    return _mapping(manifest.get("tiles"), "tiles")


def _detail(manifest: dict) -> dict:
    return _mapping(_tiles(manifest).get("detail"), "tiles.detail")


def base_file(manifest: dict) -> str:
    """The base patch's file name: ``manifest["base"]["file"]``, default ``base.tsp``;
    any other name is refused (:class:`ManifestError`)."""
    if not isinstance(manifest, dict):
        raise ManifestError("manifest", f"must be a JSON object, got {_shown(manifest)}")
    name = _mapping(manifest.get("base"), "base").get("file", BASE_FILE)
    if check_file_name(name, "base.file") != BASE_FILE:
        raise ManifestError("base.file", f"{name!r} is not {BASE_FILE!r}, the base's one name")
    return name


def _nodes(manifest: dict, kind: str) -> list[dict]:
    """``manifest["tiles"][kind]["nodes"]``, each checked to name a quadtree node of levels
    ``0..MAX_LEVEL``, its own file (``kind/K/I_J.ext``) and a byte size (optional)."""
    section = _mapping(_tiles(manifest).get(kind), f"tiles.{kind}")
    nodes = section.get("nodes")
    if nodes is None:
        return []
    if not isinstance(nodes, list):
        raise ManifestError(f"tiles.{kind}.nodes", f"must be a list, got {_shown(nodes)}")
    seen: set[str] = set()  # the file names, one per node
    for k, node in enumerate(nodes):
        where = f"tiles.{kind} node [{k}]"
        fields = [node.get(key) if isinstance(node, dict) else None for key in ("level", "i", "j")]
        if not all(_is_int(x) for x in fields) or not 0 <= fields[0] <= MAX_LEVEL \
                or not all(0 <= x < 1 << fields[0] for x in fields[1:]):
            raise ManifestError(where, f"{_shown(node)} is not a node: it needs integer level "
                                f"in 0..{MAX_LEVEL}, i and j in 0..2^level - 1, and a file name")
        name = check_file_name(node.get("file"), f"{where} file")
        parsed = _tile_name_parts(name)
        if parsed is None or parsed[:4] != (kind, *fields):
            raise ManifestError(f"{where} file", f"{name!r} is not node {fields[0]}/{fields[1]}_"
                                f"{fields[2]}'s file; file names are {_NAMING}")
        size = node.get("bytes")
        if size is not None and not (_is_int(size) and size >= 0):
            raise ManifestError(f"{where} bytes", f"must be a byte count >= 0, got {_shown(size)}")
        seen.add(name)
        if len(seen) != k + 1:
            raise ManifestError(where, f"repeats node {fields[0]}/{fields[1]}_{fields[2]}: "
                                "each node is listed once")
    return nodes


def _levels(manifest: dict) -> list:
    levels = _detail(manifest).get("levels")
    if levels is None:
        return []
    if not isinstance(levels, list) or len(levels) > MAX_LEVEL + 1:
        raise ManifestError("tiles.detail.levels", f"must be a list of at most {MAX_LEVEL + 1} "
                            f"levels, got {_shown(levels)}")
    return levels


def detail_levels(manifest: dict) -> int:
    """Number of detail levels the bundle was fitted with (0 for a bundle without tiles)."""
    return len(_levels(manifest))


def detail_spans(manifest: dict) -> int | None:
    """``tiles.detail.spans_per_tile``, the knot spans per tile side ``m`` in
    ``1..MAX_SPANS`` (``None`` when absent from a bundle without detail levels)."""
    spans = _detail(manifest).get("spans_per_tile")
    if spans is None and not detail_levels(manifest):
        return None
    if not (_is_int(spans) and 1 <= spans <= MAX_SPANS):
        raise ManifestError("tiles.detail.spans_per_tile", "must be a positive integer, "
                            f"got {_shown(spans)}; at most {MAX_SPANS}")
    return spans


def _check_level(manifest: dict, level: int | None) -> int:
    count = detail_levels(manifest)
    if level is None:
        return count - 1
    if isinstance(level, bool) or not isinstance(level, int) or not -1 <= level < count:
        raise ValueError(f"level must be an integer in -1..{count - 1} (-1: the base alone; "
                         f"this bundle has {count} detail level(s)), got {level!r}")
    return level


def detail_nodes(manifest: dict, level: int | None = None) -> list[dict]:
    """Manifest nodes of the detail tiles of levels ``0..level`` (default: all)."""
    level = _check_level(manifest, level)
    return [n for n in _nodes(manifest, "detail") if n["level"] <= level]


def texture_nodes(manifest: dict, level: int | None = None) -> list[dict]:
    """Manifest nodes of the finest texture level at or below ``level`` (default: the
    finest), with the coarser tiles that stand in where that level has none (the fitter
    leaves out tiles without colour samples); ``[]`` when the bundle has no texture.

    A coarser node is kept where its rectangle is not covered by finer kept tiles;
    :func:`client_py.layers.vertex_colours` samples the finest tile holding each vertex.
    """
    if level is not None and not (_is_int(level) and level >= -1):
        raise ValueError(f"level must be an integer >= -1 or None, got {level!r}")
    nodes = _nodes(manifest, "texture")
    if not nodes:
        return []
    top = max(n["level"] for n in nodes)
    if level is not None:
        top = min(top, max(level, 0))
    have = {(n["level"], n["i"], n["j"]) for n in nodes}
    known: dict[tuple[int, int, int], bool] = {}  # each node's answer once: no repeated subtrees

    def covered(k: int, i: int, j: int) -> bool:
        """Whether kept tiles finer than level ``k`` cover node (k, i, j)'s rectangle
        (recursion at most ``MAX_LEVEL`` deep: node levels are checked)."""
        if (k, i, j) not in known:
            known[k, i, j] = all((k + 1, 2 * i + a, 2 * j + b) in have
                                 or (k + 1 < top and covered(k + 1, 2 * i + a, 2 * j + b))
                                 for a in (0, 1) for b in (0, 1))
        return known[k, i, j]

    return [n for n in nodes if n["level"] == top
            or (n["level"] < top and not covered(n["level"], n["i"], n["j"]))]


def level_resolution(spans_per_tile: int, level: int) -> int:
    """Grid of a level-``L`` PLY: ``R = min(1025, 2 m 2^L + 1)`` vertices per side.

    ``m 2^L`` is the number of knot spans of level ``L``'s field across the
    domain (``m`` = spans per tile), so ``R`` puts two vertices per span of the
    finest tiles applied, up to :data:`PLY_MAX_RESOLUTION`.
    """
    if isinstance(spans_per_tile, bool) or not isinstance(spans_per_tile, int) \
            or spans_per_tile < 1:
        raise ValueError(f"spans_per_tile must be a positive integer, got {spans_per_tile!r}")
    if isinstance(level, bool) or not isinstance(level, int) or level < 0:
        raise ValueError(f"level must be an integer >= 0, got {level!r}")
    return min(PLY_MAX_RESOLUTION, 2 * spans_per_tile * 2**level + 1)


@dataclass(frozen=True)
class LevelPlan:
    """What the bundle at detail level ``level`` needs (see :func:`plan_level`).

    Attributes
    ----------
    level : int
        ``-1`` (the base alone) .. the finest detail level.
    rms : float or None
        RMS deviation of the scan at that level (``tiles.detail.levels[L].rms``;
        the base's ``tiles.detail.base.rms`` at ``-1``), in the bundle's units.
    detail_files : tuple of str
        The detail tiles of levels ``0..level``, in manifest order.
    detail_bytes : int
        Their total size.
    texture_nodes : tuple of dict
        Manifest nodes of the texture tiles the vertex colours are sampled from
        (:func:`texture_nodes`); empty without texture.
    texture_bytes : int
        Their total size.
    resolution : int
        Vertices per side of the grid over the whole domain
        (:func:`level_resolution`; :data:`BASE_RESOLUTION` at ``-1``).
    """

    level: int
    rms: float | None
    detail_files: tuple[str, ...]
    detail_bytes: int
    texture_nodes: tuple[dict, ...]
    texture_bytes: int
    resolution: int

    def to_dict(self) -> dict:
        """The plan as JSON-ready plain values (lists for the tuples), for the browser."""
        return {"level": self.level, "rms": self.rms, "detail_files": list(self.detail_files),
                "detail_bytes": self.detail_bytes,
                "texture_nodes": [dict(n) for n in self.texture_nodes],
                "texture_bytes": self.texture_bytes, "resolution": self.resolution}


def plan_level(manifest: dict, level: int | None = None) -> LevelPlan:
    """The files and grid of the bundle at detail level ``level`` (default: the finest).

    Parameters
    ----------
    manifest : dict
        The parsed ``manifest.json``.
    level : int, optional
        ``-1`` the base alone, else ``0..detail_levels(manifest) - 1``.

    Returns
    -------
    LevelPlan
        Detail tiles of levels ``0..L`` (:func:`detail_nodes`), texture nodes
        (:func:`texture_nodes`) and the grid ``R = min(1025, 2 m 2^L + 1)``,
        ``m = tiles.detail.spans_per_tile``.

    Raises
    ------
    ValueError
        A level the bundle does not have.
    ManifestError
        A malformed ``tiles`` entry or a file name outside the bundle (a
        ``PatchFormatError``).
    """
    level = _check_level(manifest, level)
    detail = _detail(manifest)
    nodes = detail_nodes(manifest, level)
    textures = texture_nodes(manifest, level)
    if level < 0:
        resolution = BASE_RESOLUTION
        rms = _optional_number(_mapping(detail.get("base"), "tiles.detail.base").get("rms"),
                               "tiles.detail.base.rms")
    else:
        resolution = level_resolution(detail_spans(manifest), level)
        entry = _levels(manifest)[level]
        if not isinstance(entry, dict) or entry.get("level") != level:
            raise ManifestError(f"tiles.detail.levels[{level}]",
                                f"must describe level {level}, got {_shown(entry)}")
        rms = _optional_number(entry.get("rms"), f"tiles.detail.levels[{level}].rms")
    return LevelPlan(level, rms, tuple(n["file"] for n in nodes),
                     sum(n.get("bytes") or 0 for n in nodes), tuple(textures),
                     sum(n.get("bytes") or 0 for n in textures), resolution)


def plan_levels(manifest: dict) -> list[LevelPlan]:
    """The levels a bundle offers as a PLY: :func:`plan_level` of each detail level
    ``0..L`` (``[]`` for a bundle without detail tiles; the base is the viewer's own mesh)."""
    return [plan_level(manifest, level) for level in range(detail_levels(manifest))]


def _level_mesh(surface: NurbsSurface, tiles: Sequence[DetailTile], resolution: int,
                textures: Iterable[TextureImage], kernel: str | None,
                scan_frame: bool = True) -> Mesh:
    """The whole domain on a resolution^2 grid with ``tiles`` applied, coloured from
    ``textures``, mapped to the scan frame by the patch's ``transform``."""
    mesh = tessellate_region(surface, (0.0, 0.0, 1.0, 1.0), resolution, resolution, tiles,
                             kernel, textures)
    matrix = surface.metadata.get("transform")
    if scan_frame and matrix is not None:
        mesh = transform_mesh(mesh, matrix, kernel)
    return mesh


def tessellate_bundle(manifest: dict, read: Callable[[str], bytes], level: int | None = None,
                      resolution: int = 256, kernel: str | None = None,
                      textures: Sequence[TextureImage] = (), scan_frame: bool = True) -> Mesh:
    """The bundle's surface with every detail tile of levels ``0..level`` applied.

    Parameters
    ----------
    manifest : dict
        The parsed ``manifest.json``.
    read : callable
        ``read(name)`` returns the bytes of the bundle file ``name``
        (``"base.tsp"``, ``"detail/2/1_3.tsd"``).
    level : int, optional
        Finest detail level applied; ``-1`` the base alone; default the finest.
    resolution : int
        Vertices per side of the grid over the whole domain.
    textures : sequence of TextureImage
        Decoded texture tiles (e.g. those of :func:`texture_nodes`); vertex
        colours are sampled from them.
    scan_frame : bool
        Map the mesh into the scan's coordinates by the patch's ``transform``.

    Raises
    ------
    ValueError
        A level the bundle does not have.
    PatchFormatError
        A bad file, or a bad manifest (:class:`ManifestError`).
    """
    surface = read_patch(read(base_file(manifest)))
    tiles = []
    for node in detail_nodes(manifest, level):
        tile = read_detail_tile(read(node["file"]))
        if (tile.level, tile.i, tile.j) != (node["level"], node["i"], node["j"]):
            raise PatchFormatError(6, f"{node['file']} holds tile {tile.level}/{tile.i}_"
                                   f"{tile.j}, not the manifest node's")
        tiles.append(tile)
    return _level_mesh(surface, tiles, resolution, textures, kernel, scan_frame)


def write_level_ply(surface: NurbsSurface, tiles: Iterable[DetailTile], level: int,
                    resolution: int, source: str, textures: Iterable[TextureImage] = (),
                    binary: bool = True, texture_file: str | None = None,
                    kernel: str | None = None) -> tuple[bytes, Mesh]:
    """The PLY of the bundle at detail level ``level``: ``X = S + sum_{k <= L} D_k n``
    over the whole domain on a ``resolution x resolution`` grid, in the scan frame.

    Parameters
    ----------
    surface : NurbsSurface
        The base patch in its own frame (as ``read_patch`` gives it; its
        ``transform`` maps the mesh to the scan).
    tiles : iterable of DetailTile
        The detail tiles of levels ``0..level`` (:attr:`LevelPlan.detail_files`).
    level : int
        The level, ``-1`` for the base alone; a finer tile is refused.
    resolution : int
        Vertices per side (:attr:`LevelPlan.resolution`).
    source : str
        Named in the header (``comment source SOURCE``).
    textures : iterable of TextureImage
        Vertex colours are sampled from them (:attr:`LevelPlan.texture_nodes`,
        decoded, in plan order); none: no colours.
    binary : bool
        Binary little-endian (default) or ASCII PLY.
    texture_file : str, optional
        Write ``texture_u/v`` and ``comment TextureFile`` naming this image.
    kernel : str, optional
        ``'python'`` or ``'numpy'``; default the selected kernel.

    Returns
    -------
    data : bytes
        The PLY: header comments name the source, the units (the patch's
        ``units`` metadata), the level and its tile count, the grid and the
        texture levels sampled.
    mesh : Mesh
        The mesh written.

    Raises
    ------
    ValueError
        A tile finer than ``level``, or a bad grid.
    """
    tiles = list(tiles)
    textures = list(textures)
    if isinstance(level, bool) or not isinstance(level, int) or level < -1:
        raise ValueError(f"level must be an integer >= -1, got {level!r}")
    for tile in tiles:
        if tile.level > level:
            raise ValueError(f"detail tile {tile.level}/{tile.i}_{tile.j} is of level "
                             f"{tile.level}, finer than level {level}")
    mesh = _level_mesh(surface, tiles, resolution, textures, kernel)
    comments = [f"source {source}", f"units {surface.metadata.get('units', 'unknown')}",
                f"detail level {level}: " + (
                    f"base patch + {len(tiles)} detail tiles of levels 0..{level}" if level >= 0
                    else "the base patch alone"),
                f"tessellated by client_py on a {resolution}x{resolution} grid"]
    if textures:
        levels = sorted({t.level for t in textures})
        comments.append(f"vertex colours sampled from {len(textures)} texture tiles of levels "
                        + ", ".join(str(k) for k in levels))
    data = write_ply(mesh, binary=binary, texture_file=texture_file, comments=comments)
    return data, mesh
