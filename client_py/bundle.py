"""A whole bundle at one level of detail: its base patch with every detail tile up to a level.

The bundle's ``manifest.json`` lists the tiles (``manifest["tiles"]``, see
docs/format.md, "Tiles"); this module picks the files a level needs and
tessellates the whole domain with them, for the PLY export (``tessera
tessellate OUTDIR --level L``) and for anyone who wants "level L everywhere".
No I/O of its own: the caller passes ``read(name) -> bytes`` (a file reader, a
``fetch``, a dict's ``__getitem__``), and decoded texture images.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from .format import read_detail_tile, read_patch
from .layers import TextureImage, tessellate_region, transform_mesh
from .tessellate import Mesh


def detail_levels(manifest: dict) -> int:
    """Number of detail levels the bundle was fitted with (0 for a bundle without tiles)."""
    detail = (manifest.get("tiles") or {}).get("detail") or {}
    return len(detail.get("levels") or [])


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
    detail = (manifest.get("tiles") or {}).get("detail") or {}
    return [n for n in detail.get("nodes") or [] if n["level"] <= level]


def texture_nodes(manifest: dict, level: int | None = None) -> list[dict]:
    """Manifest nodes of the finest texture level at or below ``level`` (default: the
    finest), with the coarser tiles that stand in where that level has none (the fitter
    leaves out tiles without colour samples); ``[]`` when the bundle has no texture.

    A coarser node is kept where its rectangle is not covered by finer kept tiles;
    :func:`client_py.layers.vertex_colours` samples the finest tile holding each vertex.
    """
    texture = (manifest.get("tiles") or {}).get("texture") or {}
    nodes = texture.get("nodes") or []
    if not nodes:
        return []
    top = max(n["level"] for n in nodes)
    if level is not None:
        top = min(top, max(level, 0))
    have = {(n["level"], n["i"], n["j"]) for n in nodes}

    def covered(k: int, i: int, j: int) -> bool:
        """Whether kept tiles finer than level ``k`` cover node (k, i, j)'s rectangle."""
        return all((k + 1, 2 * i + a, 2 * j + b) in have
                   or (k + 1 < top and covered(k + 1, 2 * i + a, 2 * j + b))
                   for a in (0, 1) for b in (0, 1))

    return [n for n in nodes if n["level"] == top
            or (n["level"] < top and not covered(n["level"], n["i"], n["j"]))]


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
        A level the bundle does not have; ``PatchFormatError`` for a bad file.
    """
    surface = read_patch(read(manifest.get("base", {}).get("file", "base.tsp")))
    tiles = [read_detail_tile(read(node["file"])) for node in detail_nodes(manifest, level)]
    mesh = tessellate_region(surface, (0.0, 0.0, 1.0, 1.0), resolution, resolution, tiles,
                             kernel, textures)
    matrix = surface.metadata.get("transform")
    if scan_frame and matrix is not None:
        mesh = transform_mesh(mesh, matrix, kernel)
    return mesh
