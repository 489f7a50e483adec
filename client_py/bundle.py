"""A whole bundle at one level of detail: what level ``L`` needs, its mesh and its PLY.

The bundle's ``manifest.json`` lists the tiles (``manifest["tiles"]``, see
docs/format.md, "Tiles"). :func:`plan_level` is the one rule for "level ``L``
everywhere": the detail tile files (levels ``0..L``), the texture tiles its
vertex colours come from and the grid it is tessellated on;
:func:`plan_levels` lists the levels a viewer offers for download.

Two manifest versions are read by the same functions, dispatched on
``format_version`` (:func:`manifest_version`; another version is a
:class:`ManifestError` naming it): version 1, one patch ``base.tsp`` with its
quadtree of ``.tsd`` tiles; version 2, an *atlas* (``client_py.atlas``) ``base.tsa``
whose detail tiles travel in packs ``detail/K/G.tsdp``, one per level ``K`` and group
``G`` of neighbouring patches (``client_py.atlas_detail``; docs/format.md, "Bundle
manifest, version 2"). Level ``L`` of an atlas is every pack of levels ``0..L`` on
:func:`atlas_resolution` samples per patch side, the one rule of its grid. A version-1
bundle may also carry ``pieces.tsa``: the scan's detached pieces its height field cannot
draw, a small atlas drawn with the patch at every level (:func:`read_pieces`,
:func:`pieces_mesh`, :func:`with_pieces`; docs/format.md, "Pieces").
:func:`write_level_ply` makes that PLY from the decoded patch, tiles and
texture images, for ``tessera tessellate BUNDLE --level L`` and for the
browser's worker session (:mod:`client_py.session`) alike, so both write the
same bytes. No I/O of its own: the caller passes ``read(name) -> bytes`` (a
file reader, a ``fetch``, a dict's ``__getitem__``), or the decoded objects.
"""

from __future__ import annotations

import math
import reprlib
from array import array
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from .atlas import MAX_ATLAS_QUADS, AtlasSurface
from .atlas_detail import pack_is_welded, pack_name, read_pack
from .atlas_format import read_atlas
from .atlas_mesh import tessellate_atlas
from .atlas_texture import (
    BLOCKS_FORMAT,
    MAX_CELL,
    MAX_PACK_SIDE,
    ROWS_FORMAT,
    ColourPack,
    atlas_vertex_colours,
    check_block,
    colour_level,
    colour_pack_name,
    colour_pack_name_parts,
    colours_by_patch,
    pack_shape,
)
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
BASE_FILE = "base.tsp"  # the one name a version-1 manifest's ``base.file`` may give
ATLAS_BASE_FILE = "base.tsa"  # the one name a version-2 (atlas) manifest's ``base.file`` may give
PIECES_FILE = "pieces.tsa"  # the one name a version-1 manifest's ``pieces.file`` may give
#: RGB of the pieces' vertices in a mesh coloured from the patch's texture (no tile maps them)
PIECE_COLOUR = (160, 160, 160)
MANIFEST_VERSIONS = (1, 2)  # 1: one patch; 2: an atlas
#: samples per patch side of an atlas level: ``min(129, 2 m 2^k + 1)`` (atlas_resolution)
ATLAS_MAX_RESOLUTION = 129
#: cells per side across the domain below which no detail level of one patch is drawn
#: (:func:`tile_cells`): about the base alone's grid (:data:`BASE_RESOLUTION`), so a level
#: never draws the base's shape and trim more coarsely than the base alone does. Buddha
#: range scan 0 (quiet, seed of the default fit): the base alone on 256 x 256 vertices has
#: 98.3 % of all scan points within 0.5 % of the diagonal, its level 0 on the 33 x 33 grid
#: of ``2 m 2^L + 1`` only 80.0 % (largest distance to the scan 1.54 against 2.00 %).
#: At most ``client_py.format.MAX_WALLS_SIDE``: level 0's one tile can carry walls found
#: on every cell of its grid.
MIN_LEVEL_CELLS = 256
TEXTURE_EXTENSIONS = ("webp", "png")
_NAMING = ("relative POSIX paths inside the bundle, as the fitter writes them: base.tsp, "
           "pieces.tsa, detail/K/I_J.tsd, texture/K/I_J.webp or .png; in an atlas base.tsa, "
           "detail/K/G.tsdp and texture/K/G.webp")


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

    Accepted: ``base.tsp``, ``pieces.tsa``, ``detail/K/I_J.tsd`` and
    ``texture/K/I_J.webp|png``; of an atlas, ``base.tsa``, ``detail/K/G.tsdp`` and
    ``texture/K/G.webp`` (decimal ``K, I, J, G`` without leading zeros) — so no absolute
    path, no ``..``, no backslash or NUL, and a reader that joins the name to the bundle's
    folder or URL stays inside it.
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
    elif name in (BASE_FILE, ATLAS_BASE_FILE, PIECES_FILE) or _tile_name_parts(name) is not None \
            or pack_name_parts(name) is not None or colour_pack_name_parts(name) is not None:
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


def _decimal(text: str) -> bool:
    return text.isdigit() and text.isascii() and (text == "0" or text[0] != "0")


def pack_name_parts(name: str) -> tuple[int, int] | None:
    """``(K, G)`` of a pack name ``detail/K/G.tsdp`` (``client_py.atlas_detail.pack_name``),
    or ``None``."""
    parts = name.split("/")
    if len(parts) != 3 or parts[0] != "detail" or not parts[2].endswith(".tsdp"):
        return None
    level, group = parts[1], parts[2][: -len(".tsdp")]
    if not (_decimal(level) and _decimal(group)):
        return None
    return int(level), int(group)


def manifest_version(manifest: dict) -> int:
    """``manifest["format_version"]``: 1 (one patch; also when absent) or 2 (an atlas).

    Raises
    ------
    ManifestError
        Not a JSON object, or a version this reader does not know (named in the message).
    """
    if not isinstance(manifest, dict):
        raise ManifestError("manifest", f"must be a JSON object, got {_shown(manifest)}")
    version = manifest.get("format_version", 1)
    if not _is_int(version) or version not in MANIFEST_VERSIONS:
        raise ManifestError("format_version", f"{_shown(version)} is not a version this "
                            f"reader knows: {', '.join(map(str, MANIFEST_VERSIONS))} (1: one "
                            "patch, 2: an atlas)")
    return version


def _tiles(manifest: dict) -> dict:
    if not isinstance(manifest, dict):
        raise ManifestError("manifest", f"must be a JSON object, got {_shown(manifest)}")
    return _mapping(manifest.get("tiles"), "tiles")


def _detail(manifest: dict) -> dict:
    return _mapping(_tiles(manifest).get("detail"), "tiles.detail")


def base_file(manifest: dict) -> str:
    """The base's file name: ``manifest["base"]["file"]``, default ``base.tsp`` (version 1)
    or ``base.tsa`` (version 2, an atlas); any other name is refused (:class:`ManifestError`)."""
    expected = ATLAS_BASE_FILE if manifest_version(manifest) == 2 else BASE_FILE
    name = _mapping(manifest.get("base"), "base").get("file", expected)
    if check_file_name(name, "base.file") != expected:
        raise ManifestError("base.file", f"{name!r} is not {expected!r}, the base's one name "
                            f"in a version-{manifest_version(manifest)} manifest")
    return name


def pieces_entry(manifest: dict) -> dict | None:
    """A version-1 manifest's ``pieces``, checked: the scan's detached pieces that the height
    field cannot draw, fitted as a small atlas of their own (docs/format.md, "Pieces");
    ``None`` when none is drawn (no entry, or ``file`` null: every piece left uncovered).

    Raises
    ------
    ManifestError
        ``pieces`` in an atlas manifest (an atlas draws every piece itself), a ``file`` that
        is not ``pieces.tsa``, or ``patches`` / ``resolution`` out of range.
    """
    if "pieces" not in manifest:
        return None
    if manifest_version(manifest) != 1:
        raise ManifestError("pieces", "is only read in a version-1 manifest (one patch); an "
                            "atlas draws every piece of the scan itself")
    entry = _mapping(manifest["pieces"], "pieces", optional=False)
    if entry.get("file") is None:
        return None
    if check_file_name(entry["file"], "pieces.file") != PIECES_FILE:
        raise ManifestError("pieces.file", f"{entry['file']!r} is not {PIECES_FILE!r}, the "
                            "pieces' one name")
    for key, low, top in (("patches", 1, MAX_ATLAS_QUADS), ("resolution", 2,
                                                            ATLAS_MAX_RESOLUTION)):
        value = entry.get(key)
        if not (_is_int(value) and low <= value <= top):
            raise ManifestError(f"pieces.{key}", f"must be an integer in {low}..{top}, got "
                                f"{_shown(value)}")
    return entry


def read_pieces(manifest: dict, read: Callable[[str], bytes]) -> AtlasSurface | None:
    """The bundle's pieces (``pieces.tsa``, an atlas in the scan frame), checked to hold the
    manifest's ``pieces.patches``; ``None`` when it has none drawn (:func:`pieces_entry`).

    Raises
    ------
    PatchFormatError
        A bad file, or a bad entry (:class:`ManifestError`).
    """
    entry = pieces_entry(manifest)
    if entry is None:
        return None
    try:
        pieces, _ = read_atlas(read(entry["file"]))
    except PatchFormatError as exc:  # named: the base may be fine
        raise PatchFormatError(exc.offset, f"{exc.reason} ({PIECES_FILE})", exc.section) \
            from None
    if len(pieces.quads) != entry["patches"]:
        raise ManifestError("pieces.patches", f"is {entry['patches']} but {PIECES_FILE} holds "
                            f"{len(pieces.quads)} patches")
    return pieces


def pieces_mesh(manifest: dict, pieces: AtlasSurface | None, kernel: str | None = None
                ) -> Mesh | None:
    """The pieces as drawn at every level: ``pieces`` (:func:`read_pieces`) tessellated on
    the manifest's ``pieces.resolution`` samples per patch side, without detail; ``None``
    without pieces."""
    if pieces is None:
        return None
    return tessellate_atlas(pieces, pieces_entry(manifest)["resolution"], None, kernel)


def with_pieces(mesh: Mesh, pieces: Mesh | None) -> Mesh:
    """``mesh`` (the patch's, scan frame) with the pieces' mesh appended: its vertices after
    the patch's, its triangles renumbered. The pieces' ``uvs`` are their own patches' (no
    texture tile maps them); in a coloured mesh their vertices are :data:`PIECE_COLOUR`."""
    if pieces is None:
        return mesh
    offset = mesh.vertex_count
    colors = None
    if mesh.colors is not None:
        colors = array("B", mesh.colors)
        colors.extend(PIECE_COLOUR * pieces.vertex_count)
    return Mesh(array("f", mesh.positions) + pieces.positions,
                array("f", mesh.normals) + pieces.normals, array("f", mesh.uvs) + pieces.uvs,
                array("I", mesh.indices) + array("I", (k + offset for k in pieces.indices)),
                colors)


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


def scan_origin(manifest: dict) -> list[float] | None:
    """``provenance.origin``: what a scan fitted far from the origin was moved by (a bundle
    coordinate plus it is the scan file's; docs/format.md), ``None`` when it was not moved.

    Raises
    ------
    ManifestError
        An ``origin`` that is not three finite numbers.
    """
    provenance = manifest.get("provenance")
    origin = provenance.get("origin") if isinstance(provenance, dict) else None
    if origin is None:
        return None
    if not (isinstance(origin, list) and len(origin) == 3 and all(
            isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
            for x in origin)):
        raise ManifestError("provenance.origin", f"must be three finite numbers, got "
                            f"{_shown(origin)}")
    return [float(x) for x in origin]


def fit_notes(manifest: dict) -> list[tuple[str, str]]:
    """What the fit says its admin should know, as ``(label, sentence)`` pairs (``tessera
    fit``'s summary, the admin's object page): each reader warning
    (``provenance.warnings``), why no atlas was made (``atlas_refused``), the options an
    atlas did not use (``options_unused``) and a capped depth (``fit.detail_levels_capped``).
    Entries of a shape this reader does not know are left out (a note is never an error)."""
    notes: list[tuple[str, str]] = []
    provenance = manifest.get("provenance")
    warnings = provenance.get("warnings") if isinstance(provenance, dict) else None
    notes += [("warning", text) for text in (warnings if isinstance(warnings, list) else [])
              if isinstance(text, str)]
    if isinstance(manifest.get("atlas_refused"), str):
        notes.append(("no atlas", manifest["atlas_refused"]))
    unused = manifest.get("options_unused")
    if isinstance(unused, list) and unused and all(isinstance(n, str) for n in unused):
        notes.append(("not used", ", ".join(unused) + ": a single patch's options"))
    fit = manifest.get("fit")
    capped = fit.get("detail_levels_capped") if isinstance(fit, dict) else None
    if isinstance(capped, dict) and {"asked", "held", "why"} <= set(capped):
        notes.append(("capped", f"detail_levels {capped['asked']}: the atlas holds "
                                f"{capped['held']} ({capped['why']})"))
    return notes


def origin_comments(origin: Sequence[float] | None) -> list[str]:
    """A PLY's header comments giving :func:`scan_origin` (none when not moved): ``origin X
    Y Z`` (three numbers a reader splits off), then what to do with it."""
    if origin is None:
        return []
    return ["origin " + " ".join(repr(float(x)) for x in origin),
            "the scan file's coordinates are each vertex plus the origin"]


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


def tile_cells(spans_per_tile: int, level: int, min_cells: int = MIN_LEVEL_CELLS) -> int:
    """Grid cells per tile side that level ``L`` of one patch is drawn with, the one rule of
    its grid: ``c_L = 2 m 2^j``, ``j >= 0`` the least with ``c_L 2^L >= min_cells``.

    ``m 2^L`` is the number of knot spans of level ``L``'s field across the domain (``m`` =
    spans per tile), so ``j = 0`` puts two vertices per span of the finest tiles applied;
    a coarse level's grid is refined by halving its cells until the whole domain has at
    least ``min_cells`` (:data:`MIN_LEVEL_CELLS`; ``0`` for a bundle written before it:
    :func:`drawn_level_resolution`). Halving keeps every vertex of the coarser grid and
    makes ``c_L`` divide into the level's ``2^L`` tiles, so a viewer's quadtree regions
    (:func:`region_resolution`) and the whole level (:func:`level_resolution`) are the same
    grid. The fitter finds each level's walls masks on it (``fitter.fitting.detail``,
    ``level_walls``).
    """
    if isinstance(spans_per_tile, bool) or not isinstance(spans_per_tile, int) \
            or spans_per_tile < 1:
        raise ValueError(f"spans_per_tile must be a positive integer, got {spans_per_tile!r}")
    if isinstance(level, bool) or not isinstance(level, int) or level < 0:
        raise ValueError(f"level must be an integer >= 0, got {level!r}")
    if isinstance(min_cells, bool) or not isinstance(min_cells, int) or min_cells < 0:
        raise ValueError(f"min_cells must be an integer >= 0, got {min_cells!r}")
    cells = 2 * spans_per_tile
    while cells << level < min_cells:
        cells *= 2
    return cells


def level_resolution(spans_per_tile: int, level: int, min_cells: int = MIN_LEVEL_CELLS) -> int:
    """Grid of a level-``L`` PLY: ``R = min(1025, c_L 2^L + 1)`` vertices per side.

    ``c_L`` cells per tile side (:func:`tile_cells`: ``2 m 2^j``, at least ``min_cells``
    across the domain), capped at :data:`PLY_MAX_RESOLUTION`. With the default
    ``min_cells``, 256: ``R = 257, 257, 257, 257, 513, 1025`` at levels ``0..5`` for
    ``m = 16``; with ``min_cells = 0`` (bundles written before session 13)
    ``R = min(1025, 2 m 2^L + 1)``: ``33, 65, 129, 257, ...``.
    """
    return min(PLY_MAX_RESOLUTION, (tile_cells(spans_per_tile, level, min_cells) << level) + 1)


def region_resolution(spans_per_tile: int, level: int, min_cells: int = MIN_LEVEL_CELLS) -> int:
    """Vertices per side of a viewer's region at quadtree node ``(L, i, j)``: ``c_L + 1``
    (:func:`tile_cells`; not capped: a region is a ``2^-L`` part of the domain). The
    regions of level ``L`` side by side are the level's grid, as long as that is not
    capped at :data:`PLY_MAX_RESOLUTION`."""
    return tile_cells(spans_per_tile, level, min_cells) + 1


def _level_min_cells(manifest: dict, level: int) -> int:
    """The ``min_cells`` of :func:`tile_cells` that level ``level`` (``>= 0``) of a
    version-1 manifest is drawn with: :data:`MIN_LEVEL_CELLS` when its
    ``tiles.detail.levels[L]`` states ``resolution`` (which must then be
    :func:`level_resolution`'s), ``0`` when it does not (a bundle written before session
    13, whose walls masks were found on that grid)."""
    entry = _levels(manifest)[level]
    if not isinstance(entry, dict) or entry.get("level") != level:
        raise ManifestError(f"tiles.detail.levels[{level}]",
                            f"must describe level {level}, got {_shown(entry)}")
    stated = entry.get("resolution")
    if stated is None:
        return 0
    spans = detail_spans(manifest)
    expected = level_resolution(spans, level)
    if not _is_int(stated) or stated != expected:
        raise ManifestError(f"tiles.detail.levels[{level}].resolution",
                            f"is {_shown(stated)}; level {level} is drawn on {expected} "
                            f"vertices per side (m = {spans}, at least {MIN_LEVEL_CELLS} "
                            "cells: client_py.bundle.level_resolution)")
    return MIN_LEVEL_CELLS


def drawn_level_resolution(manifest: dict, level: int) -> int:
    """Vertices per side of the grid level ``level`` (``>= 0``) of a version-1 bundle is
    drawn on as a whole (``tessera tessellate --level L``, the PLY, the benchmark):
    :func:`level_resolution` with the bundle's ``min_cells`` (:func:`_level_min_cells`:
    a level entry without ``resolution`` is drawn as before session 13)."""
    level = _check_level(manifest, level)
    if level < 0:
        raise ValueError("level must be a detail level >= 0; the base alone is drawn on "
                         f"BASE_RESOLUTION = {BASE_RESOLUTION}")
    return level_resolution(detail_spans(manifest), level, _level_min_cells(manifest, level))


def drawn_region_resolution(manifest: dict, level: int) -> int:
    """Vertices per side of a viewer's region at a level-``level`` quadtree node of a
    version-1 bundle: :func:`region_resolution` with the bundle's ``min_cells`` (as
    :func:`drawn_level_resolution`)."""
    level = _check_level(manifest, level)
    if level < 0:
        raise ValueError("level must be a detail level >= 0: the base alone has no regions")
    return region_resolution(detail_spans(manifest), level, _level_min_cells(manifest, level))


# ------------------------------------------------------------------ version 2: an atlas
@dataclass(frozen=True)
class AtlasGroup:
    """A group of neighbouring atlas patches: ``first .. first + count - 1``, the unit of
    the viewer's refinement (one pack per level), with its bounding sphere (scan frame)."""

    first: int
    count: int
    center: tuple[float, float, float]
    radius: float


@dataclass(frozen=True)
class AtlasTiles:
    """The checked ``base`` and ``tiles`` of a version-2 manifest (:func:`atlas_tiles`).

    Attributes
    ----------
    patches : int
        ``F``, the atlas's patch count (``base.patches``).
    base_resolution : int
        Samples per patch side of the base alone (``base.resolution``).
    spans_per_tile : int or None
        ``m``; ``None`` without detail.
    levels : tuple of dict
        ``tiles.detail.levels``, entry ``k`` of level ``k``.
    groups : tuple of AtlasGroup
        Contiguous, in patch order, covering ``0..F - 1`` exactly.
    packs : dict
        ``(level, group) -> {"bytes": n, "geometric_error": e}`` of every pack.
    """

    patches: int
    base_resolution: int
    spans_per_tile: int | None
    levels: tuple[dict, ...]
    groups: tuple[AtlasGroup, ...]
    packs: dict[tuple[int, int], dict]

    def resolution(self, level: int) -> int:
        """Samples per patch side at ``level``: ``base.resolution`` at ``-1``, else
        ``R_k = min(129, 2 m 2^k + 1)`` (two vertices per span of the finest tiles)."""
        if level < 0:
            return self.base_resolution
        return atlas_level_resolution(self.spans_per_tile, level)


def atlas_level_resolution(spans_per_tile: int, level: int) -> int:
    """``R_k = min(129, 2 m 2^k + 1)`` samples per patch side of an atlas at detail level
    ``k`` (``m`` spans per tile): two vertices per span of the finest tiles applied, capped
    at :data:`ATLAS_MAX_RESOLUTION`. The fitter writes it into ``levels[k].resolution``."""
    return min(ATLAS_MAX_RESOLUTION, 2 * spans_per_tile * 2**level + 1)


def _stitchable(a: int, b: int) -> bool:
    """Whether neighbours of ``a`` and ``b`` samples per side can be welded
    (``client_py.atlas_mesh``: ``(r_hi - 1) / (r_lo - 1)`` a power of 2)."""
    ratio, rest = divmod(max(a, b) - 1, min(a, b) - 1)
    return not rest and not ratio & (ratio - 1)


def _finite(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def atlas_tiles(manifest: dict) -> AtlasTiles:
    """Check a version-2 manifest's ``base`` and ``tiles`` and return them (docs/format.md,
    "Bundle manifest, version 2 (atlas)", for the rules).

    The lists are bounded before they are walked (groups: at most ``base.patches``; packs:
    at most ``levels x groups``), so a hostile manifest costs at most a pass over its own
    entries.

    Raises
    ------
    ManifestError
        Not a version-2 manifest, or any entry missing, of the wrong type or out of range.
    """
    if manifest_version(manifest) != 2:
        raise ManifestError("format_version", "must be 2 for an atlas, got "
                            f"{_shown(manifest.get('format_version', 1))}")
    base = _mapping(manifest.get("base"), "base", optional=False)
    base_file(manifest)
    if base.get("kind") != "atlas":
        raise ManifestError("base.kind", f"must be 'atlas' in a version-2 manifest, got "
                            f"{_shown(base.get('kind'))}")
    patches = base.get("patches")
    if not (_is_int(patches) and 1 <= patches <= MAX_ATLAS_QUADS):
        raise ManifestError("base.patches", f"must be an integer in 1..{MAX_ATLAS_QUADS}, "
                            f"got {_shown(patches)}")
    base_res = base.get("resolution")
    if not (_is_int(base_res) and 2 <= base_res <= ATLAS_MAX_RESOLUTION):
        raise ManifestError("base.resolution", f"must be an integer in 2.."
                            f"{ATLAS_MAX_RESOLUTION} (samples per patch side), got "
                            f"{_shown(base_res)}")
    detail = _detail(manifest)
    if not detail:
        return AtlasTiles(patches, base_res, None, (), (), {})
    spans = detail_spans(manifest)
    levels = tuple(_levels(manifest))
    spec = AtlasTiles(patches, base_res, spans, levels, (), {})
    for k, entry in enumerate(levels):
        where = f"tiles.detail.levels[{k}]"
        if not isinstance(entry, dict) or entry.get("level") != k:
            raise ManifestError(where, f"must describe level {k}, got {_shown(entry)}")
        for key in ("rms", "max"):
            _optional_number(entry.get(key), f"{where}.{key}")
        stated = entry.get("resolution")
        if stated is not None and stated != spec.resolution(k):
            raise ManifestError(f"{where}.resolution", f"is {_shown(stated)}; level {k} is "
                                f"tessellated at min({ATLAS_MAX_RESOLUTION}, 2 m 2^k + 1) = "
                                f"{spec.resolution(k)} samples per patch side (m = {spans})")
        if not _stitchable(base_res, spec.resolution(k)):
            raise ManifestError(f"{where}", f"has {spec.resolution(k)} samples per patch side "
                                f"and base.resolution {base_res}: neighbours of the two "
                                "cannot be welded ((r - 1) of one must be a power-of-2 "
                                "multiple of the other's)")
    for key in ("rms", "max"):
        _optional_number(_mapping(detail.get("base"), "tiles.detail.base").get(key),
                         f"tiles.detail.base.{key}")
    raw_groups = detail.get("groups")
    if not isinstance(raw_groups, list) or not 1 <= len(raw_groups) <= patches:
        raise ManifestError("tiles.detail.groups", f"must be a list of 1..{patches} groups "
                            f"(base.patches), got {_shown(raw_groups)}")
    groups, first = [], 0
    for g, entry in enumerate(raw_groups):
        where = f"tiles.detail.groups[{g}]"
        entry = _mapping(entry, where, optional=False)
        count, center, radius = entry.get("count"), entry.get("center"), entry.get("radius")
        if entry.get("first") != first or not (_is_int(count) and 1 <= count <= patches - first):
            raise ManifestError(where, f"must hold patches first = {first} (where the previous "
                                f"group ended) .. at most {patches - 1}, got first "
                                f"{_shown(entry.get('first'))}, count {_shown(count)}")
        if not (isinstance(center, list) and len(center) == 3 and all(map(_finite, center))):
            raise ManifestError(f"{where}.center", f"must be 3 finite numbers, got "
                                f"{_shown(center)}")
        if not (_finite(radius) and radius >= 0):
            raise ManifestError(f"{where}.radius", f"must be a finite number >= 0, got "
                                f"{_shown(radius)}")
        groups.append(AtlasGroup(first, count, tuple(float(c) for c in center), float(radius)))
        first += count
    if first != patches:
        raise ManifestError("tiles.detail.groups", f"cover patches 0..{first - 1}; every "
                            f"patch 0..{patches - 1} must be in one group")
    raw_packs = detail.get("packs")
    if not isinstance(raw_packs, list) or len(raw_packs) > len(levels) * len(groups):
        raise ManifestError("tiles.detail.packs", f"must be a list of at most "
                            f"{len(levels) * len(groups)} packs (one per level and group), "
                            f"got {_shown(raw_packs)}")
    packs: dict[tuple[int, int], dict] = {}
    for p, entry in enumerate(raw_packs):
        where = f"tiles.detail.packs[{p}]"
        entry = _mapping(entry, where, optional=False)
        level, group = entry.get("level"), entry.get("group")
        if not (_is_int(level) and 0 <= level < len(levels)
                and _is_int(group) and 0 <= group < len(groups)):
            raise ManifestError(where, f"needs an integer level in 0..{len(levels) - 1} and "
                                f"group in 0..{len(groups) - 1}, got {_shown(entry)}")
        if (level, group) in packs:
            raise ManifestError(where, f"repeats the pack of level {level}, group {group}")
        size, error = entry.get("bytes"), entry.get("geometric_error")
        if not (_is_int(size) and size >= 0):
            raise ManifestError(f"{where}.bytes", f"must be a byte count >= 0, got "
                                f"{_shown(size)}")
        if error is not None and not (_finite(error) and error >= 0):
            raise ManifestError(f"{where}.geometric_error", "must be a finite number >= 0 or "
                                f"null, got {_shown(error)}")
        packs[level, group] = {"bytes": size, "geometric_error": error}
    return AtlasTiles(patches, base_res, spans, levels, tuple(groups), packs)


@dataclass(frozen=True)
class AtlasColour:
    """The checked ``tiles.texture`` of a version-2 manifest (:func:`atlas_colour`).

    Attributes
    ----------
    levels : tuple of dict
        ``tiles.texture.levels``, entry ``c`` of colour level ``c`` (``cell``: texels per
        patch side; ``block``: cells per side of the pack layout's blocks).
    packs : tuple of dict
        Every colour pack, by level then group: ``level``, ``group`` (its first detail
        group), ``groups``, ``first`` and ``count`` (its patches), ``cell``, ``block``,
        ``width``, ``height``, ``file`` and ``bytes``.
    """

    levels: tuple[dict, ...]
    packs: tuple[dict, ...]

    def level_packs(self, detail_level: int) -> list[dict]:
        """The packs of the colour level drawn with detail level ``detail_level``
        (:func:`client_py.atlas_texture.colour_level`): every patch's cell once."""
        c = colour_level(detail_level, len(self.levels))
        return [p for p in self.packs if p["level"] == c]


def atlas_colour(manifest: dict) -> AtlasColour | None:
    """Check a version-2 manifest's ``tiles.texture`` (docs/format.md, "Atlas colour") and
    return it; ``None`` when it is absent or null (a bundle without colour).

    Colour level ``c`` (``0 <= c <`` the detail levels) has ``cell = cell_0 2^c`` texels per
    patch side; its packs hold runs of whole detail groups (``group``, ``groups``) that
    cover every group once, in order.

    Raises
    ------
    ManifestError
        Any entry missing, of the wrong type or out of range.
    """
    spec = atlas_tiles(manifest)
    section = _tiles(manifest).get("texture")
    if section is None:
        return None
    section = _mapping(section, "tiles.texture", optional=False)
    layout = section.get("format")
    if layout not in (ROWS_FORMAT, BLOCKS_FORMAT):
        raise ManifestError("tiles.texture.format", f"must be '{ROWS_FORMAT}' or "
                            f"'{BLOCKS_FORMAT}' (the atlas's colour images, their cells in "
                            f"rows or in blocks), got {_shown(layout)}")
    if not spec.levels:
        raise ManifestError("tiles.texture", "needs tiles.detail with at least one level: "
                            "the colour packs follow its groups and levels")
    levels = section.get("levels")
    if not isinstance(levels, list) or not 1 <= len(levels) <= len(spec.levels):
        raise ManifestError("tiles.texture.levels", f"must be a list of 1..{len(spec.levels)} "
                            f"levels (at most the detail levels), got {_shown(levels)}")
    cells, blocks = [], []
    for c, entry in enumerate(levels):
        where = f"tiles.texture.levels[{c}]"
        entry = _mapping(entry, where, optional=False)
        cell = entry.get("cell")
        wanted = cells[0] << c if cells else None
        if entry.get("level") != c or not (_is_int(cell) and 1 <= cell <= MAX_CELL) \
                or (wanted is not None and cell != wanted):
            raise ManifestError(where, f"must describe colour level {c} with an integer cell "
                                f"in 1..{MAX_CELL} texels per patch side"
                                + (f", {wanted} (twice the previous level's)" if wanted else "")
                                + f", got {_shown(entry)}")
        block = entry.get("block", 1 if layout == ROWS_FORMAT else None)
        try:  # rows: absent (bundles written before blocks) or 1
            blocks.append(check_block(block))
        except ValueError as error:
            raise ManifestError(f"{where}.block", f"cells per side of the pack layout's "
                                f"blocks: {error}") from None
        if layout == ROWS_FORMAT and block != 1:
            raise ManifestError(f"{where}.block", f"is {block}; cells in blocks need "
                                f"tiles.texture.format '{BLOCKS_FORMAT}'")
        texel = entry.get("texel")
        if texel is not None and not (_finite(texel) and texel >= 0):
            raise ManifestError(f"{where}.texel", f"must be a finite number >= 0 or null, "
                                f"got {_shown(texel)}")
        cells.append(cell)
    raw = section.get("packs")
    if not isinstance(raw, list) or len(raw) > len(levels) * len(spec.groups):
        raise ManifestError("tiles.texture.packs", f"must be a list of at most "
                            f"{len(levels) * len(spec.groups)} packs, got {_shown(raw)}")
    packs = []
    reached = [0] * len(levels)  # the next group each level's packs must start at
    for p, entry in enumerate(raw):
        where = f"tiles.texture.packs[{p}]"
        entry = _mapping(entry, where, optional=False)
        c, group, groups = entry.get("level"), entry.get("group"), entry.get("groups")
        if not (_is_int(c) and 0 <= c < len(levels) and _is_int(group)
                and group == reached[c] and _is_int(groups)
                and 1 <= groups <= len(spec.groups) - group):
            raise ManifestError(where, f"needs a colour level in 0..{len(levels) - 1}, its "
                                "first group where that level's previous pack ended and a "
                                f"group count within the {len(spec.groups)} groups, got "
                                f"{_shown(entry)}")
        size = entry.get("bytes")
        if not (_is_int(size) and size >= 0):
            raise ManifestError(f"{where}.bytes", f"must be a byte count >= 0, got "
                                f"{_shown(size)}")
        reached[c] = group + groups
        first = spec.groups[group].first
        last = spec.groups[group + groups - 1]
        count = last.first + last.count - first
        width, height = pack_shape(count, cells[c], blocks[c])
        if max(width, height) > MAX_PACK_SIDE:
            raise ManifestError(where, f"makes a {width}x{height} image; at most "
                                f"{MAX_PACK_SIDE} texels per side")
        packs.append({"level": c, "group": group, "groups": groups, "first": first,
                      "count": count, "cell": cells[c], "block": blocks[c],
                      "width": width, "height": height,
                      "file": colour_pack_name(c, group), "bytes": size})
    for c, end in enumerate(reached):
        if end != len(spec.groups):
            raise ManifestError("tiles.texture.packs", f"of colour level {c} cover groups "
                                f"0..{end - 1}; every group 0..{len(spec.groups) - 1} must be "
                                "in one pack")
    return AtlasColour(tuple(levels), tuple(packs))


def colour_packs_of(nodes: Sequence[Mapping], images: Mapping[str, tuple[int, int, bytes]]
                    ) -> list[ColourPack]:
    """The decoded :class:`~client_py.atlas_texture.ColourPack` of each plan node
    (:attr:`LevelPlan.texture_nodes` of an atlas) from ``images[file] = (width, height,
    rgb)``, checked against the node's shape (``ValueError`` naming the file)."""
    out = []
    for node in nodes:
        width, height, rgb = images[node["file"]]
        if (width, height) != (node["width"], node["height"]):
            raise ValueError(f"{node['file']} is {width}x{height}; the manifest's pack is "
                             f"{node['width']}x{node['height']}")
        out.append(ColourPack(node["level"], node["first"], node["count"], node["cell"],
                              width, height, bytes(rgb), node["block"]))
    return out


def atlas_resolution(manifest: dict, level: int) -> int:
    """Samples per patch side of an atlas bundle at ``level`` (the one rule).

    ``-1`` (the base alone): ``base.resolution``; detail level ``k``:
    ``R_k = min(129, 2 m 2^k + 1)``, ``m = tiles.detail.spans_per_tile``: two vertices per
    knot span of the finest tiles applied (as :func:`level_resolution` for one patch, capped
    at :data:`ATLAS_MAX_RESOLUTION` per patch since an atlas has many).

    Raises
    ------
    ManifestError
        Not a valid version-2 manifest (:func:`atlas_tiles`).
    ValueError
        A level the bundle does not have.
    """
    spec = atlas_tiles(manifest)
    return spec.resolution(_check_level(manifest, level))


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
        (:func:`drawn_level_resolution`; :data:`BASE_RESOLUTION` at ``-1``).
    region_resolution : int or None
        Vertices per side of a viewer's region at a level-``level`` quadtree node
        (:func:`drawn_region_resolution`); ``None`` for the base alone and an atlas.
    """

    level: int
    rms: float | None
    detail_files: tuple[str, ...]
    detail_bytes: int
    texture_nodes: tuple[dict, ...]
    texture_bytes: int
    resolution: int
    region_resolution: int | None = None

    def to_dict(self) -> dict:
        """The plan as JSON-ready plain values (lists for the tuples), for the browser."""
        return {"level": self.level, "rms": self.rms, "detail_files": list(self.detail_files),
                "detail_bytes": self.detail_bytes,
                "texture_nodes": [dict(n) for n in self.texture_nodes],
                "texture_bytes": self.texture_bytes, "resolution": self.resolution,
                "region_resolution": self.region_resolution}


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
        (:func:`texture_nodes`) and the grid ``R = min(1025, c_L 2^L + 1)``,
        ``c_L = 2 m 2^j`` cells per tile side with at least 256 across the domain
        (:func:`drawn_level_resolution`; ``2 m 2^L + 1`` for a bundle written before
        session 13), ``m = tiles.detail.spans_per_tile``.

    Raises
    ------
    ValueError
        A level the bundle does not have.
    ManifestError
        A malformed ``tiles`` entry or a file name outside the bundle (a
        ``PatchFormatError``), or an unknown ``format_version``.

    Notes
    -----
    Of an atlas (version 2): ``detail_files`` are the packs of levels ``0..L``
    (``detail/K/G.tsdp``, by level then group), ``texture_nodes`` the colour packs drawn
    with level ``L`` (:meth:`AtlasColour.level_packs`; none without colour), and
    ``resolution`` the samples per patch side (:func:`atlas_resolution`).
    """
    if manifest_version(manifest) == 2:
        return _plan_atlas_level(manifest, level)
    level = _check_level(manifest, level)
    detail = _detail(manifest)
    nodes = detail_nodes(manifest, level)
    textures = texture_nodes(manifest, level)
    if level < 0:
        resolution = BASE_RESOLUTION
        rms = _optional_number(_mapping(detail.get("base"), "tiles.detail.base").get("rms"),
                               "tiles.detail.base.rms")
    else:
        resolution = drawn_level_resolution(manifest, level)  # checks the level's entry
        region = drawn_region_resolution(manifest, level)
        rms = _optional_number(_levels(manifest)[level].get("rms"),
                               f"tiles.detail.levels[{level}].rms")
    return LevelPlan(level, rms, tuple(n["file"] for n in nodes),
                     sum(n.get("bytes") or 0 for n in nodes), tuple(textures),
                     sum(n.get("bytes") or 0 for n in textures), resolution,
                     None if level < 0 else region)


def _plan_atlas_level(manifest: dict, level: int | None) -> LevelPlan:
    spec = atlas_tiles(manifest)
    level = _check_level(manifest, level)
    if level < 0:
        rms = _optional_number(_mapping(_detail(manifest).get("base"), "tiles.detail.base")
                               .get("rms"), "tiles.detail.base.rms")
    else:
        rms = _optional_number(spec.levels[level].get("rms"), f"tiles.detail.levels[{level}].rms")
    keys = sorted(key for key in spec.packs if key[0] <= level)
    colour = atlas_colour(manifest)
    textures = () if colour is None else tuple(colour.level_packs(level))
    return LevelPlan(level, rms, tuple(pack_name(k, g) for k, g in keys),
                     sum(spec.packs[key]["bytes"] for key in keys), textures,
                     sum(n["bytes"] for n in textures), spec.resolution(level))


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


def atlas_level_detail(manifest: dict, read: Callable[[str], bytes],
                       level: int | None = None, atlas: AtlasSurface | None = None
                       ) -> dict[int, list[DetailTile]]:
    """The detail tiles of an atlas bundle at ``level``: every pack of levels ``0..level``
    read and decoded, as ``{patch: [tiles]}`` for ``client_py.atlas_mesh.tessellate_atlas``.
    ``atlas``: the bundle's base, which a welded pack needs (``client_py.atlas_detail``);
    ``None``: read from ``base.tsa`` when a pack needs it.

    Raises
    ------
    PatchFormatError
        A bad pack, one of another level than its name's, one holding a patch outside its
        group, or a bad manifest (:class:`ManifestError`).
    """
    spec = atlas_tiles(manifest)
    detail: dict[int, list[DetailTile]] = {}
    for name in plan_level(manifest, level).detail_files:
        level_k, group = pack_name_parts(name)
        data = read(name)
        if atlas is None and pack_is_welded(data):
            atlas, _ = read_atlas(read(base_file(manifest)))
            check_atlas_base(atlas, manifest)
        try:
            found, tiles = read_pack(data, atlas)
        except PatchFormatError as exc:
            raise PatchFormatError(exc.offset, f"{exc.reason} (detail pack {name})",
                                   exc.section) from None
        add_pack_tiles(detail, spec, name, level_k, group, found, tiles)
    return detail


def add_pack_tiles(detail: dict[int, list[DetailTile]], spec: AtlasTiles, name: str,
                   level: int, group: int, found: int,
                   tiles: Mapping[int, Sequence[DetailTile]]) -> None:
    """Add a decoded pack's ``tiles`` to ``detail`` after checking it is pack ``name``:
    of ``level`` (``found`` is its header's) and holding only patches of ``group``."""
    if found != level:
        raise PatchFormatError(5, f"{name} holds level {found}, not the manifest's {level}")
    first = spec.groups[group].first
    last = first + spec.groups[group].count - 1
    for patch, patch_tiles in tiles.items():
        if not first <= patch <= last:
            raise PatchFormatError(8, f"{name} holds patch {patch}, outside group {group}'s "
                                   f"patches {first}..{last}")
        detail.setdefault(patch, []).extend(patch_tiles)


def tessellate_bundle(manifest: dict, read: Callable[[str], bytes], level: int | None = None,
                      resolution: int | None = None, kernel: str | None = None,
                      textures: Sequence[TextureImage] = (), scan_frame: bool = True) -> Mesh:
    """The bundle's surface with every detail tile of levels ``0..level`` applied.

    Parameters
    ----------
    manifest : dict
        The parsed ``manifest.json``.
    read : callable
        ``read(name)`` returns the bytes of the bundle file ``name``
        (``"base.tsp"``, ``"detail/2/1_3.tsd"``; of an atlas ``"base.tsa"``,
        ``"detail/2/5.tsdp"``).
    level : int, optional
        Finest detail level applied; ``-1`` the base alone; default the finest.
    resolution : int, optional
        Vertices per side of the grid over the whole domain (of each patch, for an
        atlas); default the level's, :attr:`LevelPlan.resolution`.
    textures : sequence of TextureImage, or of ColourPack for an atlas
        Decoded texture tiles (e.g. those of :func:`texture_nodes`); vertex
        colours are sampled from them. Of an atlas, the decoded colour packs of the
        plan's ``texture_nodes`` (:func:`colour_packs_of`).
    scan_frame : bool
        Map the mesh into the scan's coordinates by the patch's ``transform`` (an atlas is
        in the scan frame already); only then are a patch's pieces drawn
        (:func:`pieces_mesh`, appended by :func:`with_pieces`).

    Returns
    -------
    Mesh
        Of an atlas, one welded watertight
        :class:`~client_py.atlas_mesh.AtlasMesh` (``tessellate_atlas``).

    Raises
    ------
    ValueError
        A level the bundle does not have.
    PatchFormatError
        A bad file, or a bad manifest (:class:`ManifestError`).
    """
    if resolution is None:
        resolution = plan_level(manifest, level).resolution
    if manifest_version(manifest) == 2:
        atlas_tiles(manifest)  # the manifest is checked before any file is read
        atlas, _ = read_atlas(read(base_file(manifest)))
        check_atlas_base(atlas, manifest)
        detail = atlas_level_detail(manifest, read, level, atlas)
        mesh = tessellate_atlas(atlas, resolution, detail, kernel)
        if textures:
            if atlas_colour(manifest) is None:
                raise ValueError("this atlas bundle has no colour (tiles.texture is null); "
                                 "no colour packs may be given")
            of_patch = colours_by_patch(textures, len(atlas.quads))
            mesh.colors = atlas_vertex_colours(mesh.patches, mesh.uvs, of_patch)
        return mesh
    surface = read_patch(read(base_file(manifest)))
    tiles = []
    for node in detail_nodes(manifest, level):
        tile = read_detail_tile(read(node["file"]))
        if (tile.level, tile.i, tile.j) != (node["level"], node["i"], node["j"]):
            raise PatchFormatError(6, f"{node['file']} holds tile {tile.level}/{tile.i}_"
                                   f"{tile.j}, not the manifest node's")
        tiles.append(tile)
    mesh = _level_mesh(surface, tiles, resolution, textures, kernel, scan_frame)
    if not scan_frame:  # the pieces are drawn in the scan frame only
        return mesh
    return with_pieces(mesh, pieces_mesh(manifest, read_pieces(manifest, read), kernel))


def check_atlas_base(atlas: AtlasSurface, manifest: dict) -> None:
    """Refuse a ``base.tsa`` whose patch count is not the manifest's ``base.patches`` (the
    groups and packs index its patches): :class:`ManifestError`."""
    patches = manifest["base"]["patches"]
    if len(atlas.quads) != patches:
        raise ManifestError("base.patches", f"is {patches} but {ATLAS_BASE_FILE} holds "
                            f"{len(atlas.quads)} patches")


def write_level_ply(surface: NurbsSurface | AtlasSurface,
                    tiles: Iterable[DetailTile] | Mapping[int, Sequence[DetailTile]],
                    level: int, resolution: int | Sequence[int], source: str,
                    textures: Iterable[TextureImage] = (), binary: bool = True,
                    texture_file: str | None = None, kernel: str | None = None,
                    units: str | None = None,
                    progress: Callable[[float], object] | None = None,
                    pieces: Mesh | None = None,
                    origin: Sequence[float] | None = None) -> tuple[bytes, Mesh]:
    """The PLY of the bundle at detail level ``level``: ``X = S + sum_{k <= L} D_k n``
    over the whole domain on a ``resolution x resolution`` grid, in the scan frame.

    Parameters
    ----------
    surface : NurbsSurface or AtlasSurface
        The base patch in its own frame (as ``read_patch`` gives it; its
        ``transform`` maps the mesh to the scan); or an atlas (``read_atlas``, in the
        scan frame): then one welded mesh (``client_py.atlas_mesh.tessellate_atlas``).
    tiles : iterable of DetailTile, or mapping of int to sequence of DetailTile
        The detail tiles of levels ``0..level`` (:attr:`LevelPlan.detail_files`); of an
        atlas, ``{patch: tiles}`` (:func:`atlas_level_detail`).
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
    units : str, optional
        Named in the header; default the patch's ``units`` metadata (an atlas: the
        metadata ``read_atlas`` returns, which the caller passes here).

    progress : callable, optional
        An atlas's: called with the share of the tessellation done
        (:func:`client_py.atlas_mesh.tessellate_atlas`).
    pieces : Mesh, optional
        A patch's pieces as drawn (:func:`pieces_mesh`), appended (:func:`with_pieces`).
    origin : sequence of 3 floats, optional
        The manifest's :func:`scan_origin`, named in a header comment: the mesh is in the
        bundle's frame, and a vertex plus ``origin`` is in the scan file's.

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
    if isinstance(level, bool) or not isinstance(level, int) or level < -1:
        raise ValueError(f"level must be an integer >= -1, got {level!r}")
    if isinstance(surface, AtlasSurface):
        if pieces is not None:
            raise ValueError("pieces are a patch bundle's; an atlas draws every piece itself")
        return _write_atlas_ply(surface, tiles, level, resolution, source, binary, kernel,
                                units, list(textures), progress, origin)
    tiles = list(tiles)
    textures = list(textures)
    for tile in tiles:
        if tile.level > level:
            raise ValueError(f"detail tile {tile.level}/{tile.i}_{tile.j} is of level "
                             f"{tile.level}, finer than level {level}")
    mesh = with_pieces(_level_mesh(surface, tiles, resolution, textures, kernel), pieces)
    units = surface.metadata.get("units", "unknown") if units is None else units
    comments = [f"source {source}", f"units {units}",
                f"detail level {level}: " + (
                    f"base patch + {len(tiles)} detail tiles of levels 0..{level}" if level >= 0
                    else "the base patch alone"),
                f"tessellated by client_py on a {resolution}x{resolution} grid",
                *origin_comments(origin)]
    if pieces is not None:
        comments.append(f"with the scan's detached pieces ({PIECES_FILE}): "
                        f"{pieces.triangle_count} triangles")
    if textures:
        levels = sorted({t.level for t in textures})
        comments.append(f"vertex colours sampled from {len(textures)} texture tiles of levels "
                        + ", ".join(str(k) for k in levels))
    data = write_ply(mesh, binary=binary, texture_file=texture_file, comments=comments)
    return data, mesh


def _write_atlas_ply(atlas: AtlasSurface, detail: Mapping[int, Sequence[DetailTile]],
                     level: int, resolution: int | Sequence[int], source: str, binary: bool,
                     kernel: str | None, units: str | None,
                     packs: Sequence[ColourPack] = (),
                     progress: Callable[[float], object] | None = None,
                     origin: Sequence[float] | None = None) -> tuple[bytes, Mesh]:
    """:func:`write_level_ply` of an atlas: one welded mesh, ``detail`` = ``{patch: tiles}``,
    coloured per vertex from ``packs`` (the decoded colour packs of the level's plan, which
    hold every patch's cell once) when given."""
    if not isinstance(detail, Mapping):
        raise ValueError("tiles of an atlas must be a mapping of patch index to DetailTile "
                         f"lists, got {type(detail).__name__}")
    count = 0
    for patch, patch_tiles in detail.items():
        for tile in patch_tiles:
            count += 1
            if tile.level > level:
                raise ValueError(f"patch {patch}: detail tile {tile.level}/{tile.i}_{tile.j} "
                                 f"is of level {tile.level}, finer than level {level}")
    mesh = tessellate_atlas(atlas, resolution, detail, kernel, progress)
    grid = (f"{resolution}x{resolution} grid per patch" if isinstance(resolution, int)
            else f"{min(resolution)}..{max(resolution)} samples per patch side")
    comments = [f"source {source}", f"units {units or 'unknown'}",
                f"detail level {level}: " + (
                    f"atlas of {len(atlas.quads)} patches + {count} detail tiles of levels "
                    f"0..{level}" if level >= 0 else
                    f"the atlas of {len(atlas.quads)} patches alone"),
                f"tessellated by client_py, one welded mesh, {grid}",
                *origin_comments(origin)]
    if packs:
        of_patch = colours_by_patch(packs, len(atlas.quads))
        mesh.colors = atlas_vertex_colours(mesh.patches, mesh.uvs, of_patch)
        comments.append(f"vertex colours sampled from {len(packs)} colour packs of level "
                        + ", ".join(str(c) for c in sorted({p.level for p in packs})))
    return write_ply(mesh, binary=binary, comments=comments), mesh
