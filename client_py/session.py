"""The browser worker's session: one loaded patch, the tiles handed over, one method per request.

``web/src/mesh-worker.js`` runs Pyodide in a Web Worker and only moves messages
and buffers: for each request of the page it calls one method of a
:class:`WorkerSession` and sends the result back (docs of the protocol at the
top of that file). The session holds the base patch (in its own frame, which
the detail tiles displace along, and mapped to the scan frame, which the base
meshes are drawn in), the detail tiles the page has handed over, the bundle's
manifest (for :func:`client_py.bundle.plan_level`) and the last base mesh (the
"Download PLY" of the base reuses the mesh on screen). Bytes arrive as any
bytes-like object (Pyodide turns a ``Uint8Array`` into a ``memoryview``);
results are :class:`~client_py.tessellate.Mesh` objects, PLY bytes and plain
dicts and lists. Standard library only, no I/O, CPython and Pyodide alike.

An atlas bundle (manifest version 2) is loaded by :meth:`WorkerSession.load_atlas`
instead; its detail arrives as packs (:meth:`WorkerSession.add_pack`) and the viewer
refines it by group: :meth:`WorkerSession.atlas_mesh` draws the whole atlas as one
welded mesh with each group at its own level (``web/src/atlas-layer.js`` chooses them).
"""

from __future__ import annotations

import json
import zlib
from array import array
from bisect import bisect_right
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from itertools import chain

from . import _kernel
from .atlas import AtlasSurface
from .atlas_detail import pack_name, read_pack
from .atlas_format import read_atlas
from .atlas_mesh import (
    AtlasMesh,
    PatchGrids,
    atlas_parts,
    atlas_ring,
    tessellate_atlas,
    tessellate_atlas_parts,
)
from .atlas_texture import (
    ColourPack,
    atlas_vertex_colours,
    colours_for_groups,
    error_colour_pack,
)
from .bundle import (
    PLY_MAX_RESOLUTION,
    AtlasTiles,
    ManifestError,
    add_pack_tiles,
    atlas_colour,
    atlas_tiles,
    check_atlas_base,
    colour_packs_of,
    detail_spans,
    origin_comments,
    pack_name_parts,
    pieces_entry,
    pieces_mesh,
    plan_level,
    plan_levels,
    read_pieces,
    scan_origin,
    with_pieces,
    write_level_ply,
)
from .errors import PatchFormatError
from .format import read_detail_tile, read_patch
from .layers import (
    DetailTile,
    TextureImage,
    is_rigid_motion,
    mesh_of_region,
    sample_region,
    tile_rect,
    transform_mesh,
)
from .ply import write_ply
from .skirts import hang_skirts
from .surface import NurbsSurface
from .tessellate import Mesh, tessellate_grid


@dataclass(frozen=True)
class PlyFile:
    """A PLY the session wrote.

    Attributes
    ----------
    data : bytes
        The file.
    vertex_count, triangle_count : int
        Of the mesh written.
    resolution : int
        Vertices per side of its grid.
    level : int
        Detail level, ``-1`` for the base.
    """

    data: bytes
    vertex_count: int
    triangle_count: int
    resolution: int
    level: int


class WorkerSession:
    """The state of one viewer's mesh worker, and a method for each of its requests.

    Call :meth:`load_patch` first; :meth:`read_manifest` before the level
    methods (:meth:`level_choices`, :meth:`level_ply`).

    Parameters
    ----------
    kernel : str, optional
        ``'python'`` or ``'numpy'`` for every mesh; default the selected kernel
        (:mod:`client_py._kernel`; ``'python'`` in Pyodide without numpy).
    """

    def __init__(self, kernel: str | None = None) -> None:
        _kernel.backend(kernel)  # a bad name raises here, not at the first request
        self._kernel = kernel
        self._patch: NurbsSurface | None = None  # own frame: detail displaces along *its* normal
        self._scan: NurbsSurface | None = None  # the patch in the scan frame
        self._rigid = False  # the map to the scan frame is a rotation and a shift
        self._source = ""
        self._tiles: dict[str, DetailTile] = {}  # bundle file name -> tile handed over
        self._manifest: dict | None = None
        self._last: tuple[int, Mesh] | None = None  # (resolution, base mesh) last tessellated
        self._pieces: Mesh | None = None  # the patch's detached pieces drawn (load_pieces)
        self._atlas: AtlasSurface | None = None  # an atlas bundle's base (load_atlas), scan frame
        self._atlas_units = "unknown"
        self._packs: dict[str, tuple[int, int, dict[int, list[DetailTile]]]] = {}  # by name
        self._colours: dict[str, ColourPack] = {}  # an atlas's decoded colour packs, by name
        self._error_pack: ColourPack | None = None  # the atlas's error map while it is shown
        self._patch_grids = PatchGrids()  # atlas_part_meshes' patch grids, kept between calls

    @property
    def kernel(self) -> str:
        """The grid kernel in use: ``'numpy'`` or ``'python'`` (Pyodide without numpy)."""
        return self._kernel or _kernel.KERNEL_NAME

    def _loaded(self) -> NurbsSurface:
        if self._patch is None:
            raise RuntimeError("no patch is loaded: call load_patch first")
        return self._patch

    def load_patch(self, data: bytes, source: str) -> dict:
        """Decode a ``.tsp`` patch and start afresh with it (tiles and last mesh forgotten).

        Parameters
        ----------
        data : bytes-like
            The patch file.
        source : str
            Its name, written into the PLY headers (``comment source ...``).

        Returns
        -------
        dict
            ``degree [p, q]``, ``shape [n_u, n_v]``, ``rational``, ``domain
            [u0, u1, v0, v1]``, ``trimmed``, ``units`` and ``bbox [[x, y, z]
            lo, hi]`` (scan frame): what the page shows and frames the view by.

        Raises
        ------
        PatchFormatError
            Not a valid patch.
        """
        patch = read_patch(bytes(data))
        scan = patch.to_scan_frame()
        (u0, u1), (v0, v1) = patch.domain
        lo, hi = scan.bounding_box()
        self._patch, self._scan, self._source = patch, scan, str(source)
        self._rigid = is_rigid_motion(patch.metadata.get("transform"))
        self._atlas = None
        self._packs.clear()
        self._colours.clear()
        self._patch_grids = PatchGrids()
        self._tiles.clear()
        self._last = None
        self._pieces = None
        return {"degree": list(patch.degree), "shape": list(patch.shape),
                "rational": patch.is_rational, "domain": [u0, u1, v0, v1],
                "trimmed": patch.trim is not None,
                "units": patch.metadata.get("units", "unknown"),
                "bbox": [list(lo), list(hi)]}

    def tessellate_base(self, resolution: int) -> Mesh:
        """The base patch on a ``resolution x resolution`` grid, scan frame (kept as the
        last mesh, which :meth:`base_ply` reuses)."""
        self._loaded()
        mesh = tessellate_grid(self._scan, resolution, resolution, kernel=self._kernel)
        self._last = (resolution, mesh)
        return mesh

    def base_ply(self, resolution: int, colors: bytes | None = None) -> PlyFile:
        """PLY of the base on a ``resolution x resolution`` grid (the last mesh when it has
        that grid), with ``colors`` (bytes-like, RGB per vertex) when given."""
        self._loaded()
        if self._last is not None and self._last[0] == resolution:
            mesh = self._last[1]
        else:
            mesh = tessellate_grid(self._scan, resolution, resolution, kernel=self._kernel)
        if colors is not None:
            rgb = array("B", bytes(colors))
            if len(rgb) != 3 * mesh.vertex_count:
                raise ValueError(f"colors has {len(rgb)} bytes; the {resolution}x{resolution} "
                                 f"grid's {mesh.vertex_count} vertices need "
                                 f"{3 * mesh.vertex_count}")
            mesh = replace(mesh, colors=rgb)
        comments = [f"source {self._source}",
                    f"units {self._scan.metadata.get('units', 'unknown')}",
                    f"tessellated by client_py in the browser, {resolution}x{resolution} grid",
                    *origin_comments(None if self._manifest is None
                                     else scan_origin(self._manifest))]
        if self._pieces is not None:
            mesh = with_pieces(mesh, self._pieces)
            comments.append(f"with the scan's detached pieces: {self._pieces.triangle_count} "
                            "triangles")
        data = write_ply(mesh, binary=True, comments=comments)
        return PlyFile(data, mesh.vertex_count, mesh.triangle_count, resolution, -1)

    def add_tile(self, name: str, data: bytes) -> list[int]:
        """Decode and keep the detail tile ``name`` (a bundle file name): ``[level, i, j]``."""
        tile = _decode_tile(name, data)
        self._tiles[str(name)] = tile
        return [tile.level, tile.i, tile.j]

    def drop_tiles(self, names: Iterable[str]) -> None:
        """Forget tiles handed over (names not held are ignored: already dropped)."""
        for name in names:
            self._tiles.pop(name, None)

    def holds(self, name: str) -> bool:
        """Whether the detail tile ``name`` has been handed over and not dropped."""
        return name in self._tiles

    def region_mesh(self, level: int, i: int, j: int, grid: int, names: Iterable[str],
                    skirt_depth: float) -> Mesh:
        """Quadtree node ``(level, i, j)`` on a ``grid x grid`` mesh with the named tiles
        (the viewer passes the level's ``region_resolution`` of :meth:`level_choices`,
        :func:`client_py.bundle.drawn_region_resolution`), skirts on its inner borders
        (:func:`client_py.skirts.hang_skirts`), scan frame:
        ``transform_mesh(hang_skirts(tessellate_region(patch, ...), ...), transform)``, made
        on the scan-frame patch when the transform is a rigid motion
        (:func:`client_py.layers.is_rigid_motion`: equal to rounding, float32).

        Raises
        ------
        ValueError
            A name not handed over, or a tile that does not cover the node.
        """
        patch = self._loaded()
        tiles = []
        for name in names:
            if name not in self._tiles:
                raise ValueError(f"detail tile {name} was not handed over (add_tile)")
            tile = self._tiles[name]
            if tile.level > level or tile.i != i >> (level - tile.level) \
                    or tile.j != j >> (level - tile.level):
                raise ValueError(f"tile {tile.level}/{tile.i}_{tile.j} does not cover region "
                                 f"{level}/{i}_{j}")
            tiles.append(tile)
        rect = tile_rect(level, i, j)
        # A rigid map to the scan frame (the fitter's: a rotation and a shift) commutes with
        # the displacement along the unit normal: the region is made on the scan-frame patch
        # directly (no pass over its vertices to map them; the same mesh to rounding). Any
        # other map is applied to the patch-frame mesh.
        surface = self._scan if self._rigid else patch
        # the base and the level fields sampled once, for the region's grid and its skirts
        samples = sample_region(surface, rect, grid, grid, tiles, self._kernel)
        mesh = mesh_of_region(surface, samples, tiles, self._kernel)
        mesh = hang_skirts(mesh, surface, rect, grid, tiles, skirt_depth, self._kernel, samples)
        matrix = patch.metadata.get("transform")
        if matrix is None or self._rigid:
            return mesh
        return transform_mesh(mesh, matrix, self._kernel)

    def read_manifest(self, text: str) -> None:
        """Keep the bundle's ``manifest.json`` (its text) for the level methods.

        The parts they use are checked here, once (:func:`client_py.bundle.plan_levels`).

        Raises
        ------
        ManifestError
            Not JSON (or nested too deep to parse), not an object, or tiles that
            :func:`client_py.bundle.plan_level` refuses: a ``PatchFormatError``.
        ValueError
            ``text`` is not a string or bytes.
        """
        if not isinstance(text, str | bytes | bytearray):
            raise ValueError(f"text must be the manifest's JSON text, got {type(text).__name__}")
        try:
            manifest = json.loads(text)
        except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError
            reason = "nested too deep" if isinstance(exc, RecursionError) else str(exc)
            raise ManifestError("manifest.json", f"is not valid JSON: {reason}") from None
        if not isinstance(manifest, dict):
            raise ManifestError("manifest.json", "must be a JSON object, got "
                                f"{type(manifest).__name__}")
        plan_levels(manifest)  # a manifest the level methods cannot plan from fails here
        pieces_entry(manifest)  # and one whose pieces load_pieces could not read
        self._manifest = manifest

    def load_pieces(self, data: bytes) -> Mesh:
        """Decode the patch bundle's ``pieces.tsa`` (the manifest's ``pieces``, read by
        :meth:`read_manifest`) and keep its mesh, drawn at every level and appended to the
        PLYs (:func:`client_py.bundle.with_pieces`); returns that mesh (scan frame).

        Raises
        ------
        ValueError
            A manifest without pieces.
        RuntimeError
            No patch loaded (:meth:`load_patch`), or no manifest read.
        PatchFormatError
            A bad file, or one that is not the manifest's pieces.
        """
        self._loaded()
        manifest = self._manifest_read()
        entry = pieces_entry(manifest)
        if entry is None:
            raise ValueError("this bundle's manifest draws no pieces (no pieces.file)")
        self._pieces = pieces_mesh(manifest, read_pieces(manifest, lambda _: bytes(data)),
                                   self._kernel)
        return self._pieces

    def _manifest_read(self) -> dict:
        if self._manifest is None:
            raise RuntimeError("no manifest: call read_manifest first")
        return self._manifest

    def level_choices(self) -> dict:
        """The levels offered as a PLY, for the page's level choice.

        Returns
        -------
        dict
            ``levels``: :func:`client_py.bundle.plan_levels` as dicts
            (:meth:`client_py.bundle.LevelPlan.to_dict`: with each level's grid over the
            whole patch, ``resolution``, and a viewer region's, ``region_resolution``,
            the viewer's only source of them); ``max_resolution``: the
            grid's cap :data:`client_py.bundle.PLY_MAX_RESOLUTION`;
            ``spans_per_tile``: the manifest's (``None`` without detail tiles).
        """
        manifest = self._manifest_read()
        return {"levels": [plan.to_dict() for plan in plan_levels(manifest)],
                "max_resolution": PLY_MAX_RESOLUTION,
                "spans_per_tile": detail_spans(manifest)}

    def level_ply(self, level: int, fresh: Mapping[str, bytes] | None = None,
                  textures: Iterable[Mapping] = (),
                  progress: Callable[[float], object] | None = None) -> PlyFile:
        """The PLY of the bundle at detail level ``level``, as ``tessera tessellate BUNDLE
        --level L`` writes it (:func:`client_py.bundle.write_level_ply` on
        :func:`client_py.bundle.plan_level`'s grid).

        Parameters
        ----------
        level : int
            ``-1`` .. the finest detail level.
        fresh : mapping of str to bytes-like, optional
            Tiles of the plan the session does not hold, by file name: decoded
            for this PLY only (not kept).
        textures : iterable of mapping
            The plan's texture tiles, decoded: ``{"level", "i", "j", "width",
            "height", "rgb"}`` with ``rgb`` the ``3 width height`` bytes, rows
            top to bottom (:class:`client_py.layers.TextureImage`); each of
            the plan's nodes once, in any order.

        Raises
        ------
        ValueError
            A tile of the plan neither held nor fresh, a fresh tile or texture
            the plan does not name, a texture of the plan missing, a bad file.

        Notes
        -----
        With an atlas loaded (:meth:`load_atlas`), ``fresh`` names packs
        (``detail/K/G.tsdp``) and the PLY is one welded mesh of every patch; ``textures``
        are the plan's colour packs decoded, ``{"file", "width", "height", "rgb"}``, and
        ``progress`` (optional) is called with the share of its tessellation done
        (:func:`client_py.atlas_mesh.tessellate_atlas`: seconds for hundreds of patches).
        """
        if self._atlas is not None:
            return self._atlas_level_ply(level, dict(fresh or {}), list(textures), progress)
        patch = self._loaded()
        plan = plan_level(self._manifest_read(), level)
        fresh = dict(fresh or {})
        extra = sorted(set(fresh) - set(plan.detail_files))
        if extra:
            raise ValueError(f"fresh tiles {', '.join(extra)} are not tiles of level {level} "
                             f"(levels 0..{level})")
        tiles = []
        for name in plan.detail_files:
            if name in fresh:
                tiles.append(_decode_tile(name, fresh[name]))
            elif name in self._tiles:
                tiles.append(self._tiles[name])
            else:
                raise ValueError(f"detail tile {name} was neither handed over nor sent")
        images = {}
        for texture in textures:
            key = (texture["level"], texture["i"], texture["j"])
            try:
                images[key] = TextureImage(*key, texture["width"], texture["height"],
                                           bytes(texture["rgb"]))
            except ValueError as exc:
                raise ValueError(f"texture tile {key[0]}/{key[1]}_{key[2]}: {exc}") from None
        wanted = [(n["level"], n["i"], n["j"]) for n in plan.texture_nodes]
        if set(images) != set(wanted):
            missing = ", ".join(f"{k}/{i}_{j}" for k, i, j in sorted(set(wanted) - set(images)))
            extra = ", ".join(f"{k}/{i}_{j}" for k, i, j in sorted(set(images) - set(wanted)))
            raise ValueError(f"the texture tiles sent must be those of level {level}'s plan: "
                             f"missing [{missing}], not in the plan [{extra}]")
        data, mesh = write_level_ply(patch, tiles, plan.level, plan.resolution, self._source,
                                     [images[key] for key in wanted], kernel=self._kernel,
                                     pieces=self._pieces,
                                     origin=scan_origin(self._manifest_read()))
        return PlyFile(data, mesh.vertex_count, mesh.triangle_count, plan.resolution, plan.level)

    # ------------------------------------------------------------------ an atlas bundle
    def load_atlas(self, data: bytes, source: str) -> dict:
        """Decode an atlas ``base.tsa`` (manifest version 2) and start afresh with it (a
        patch, tiles and packs held before are forgotten).

        Returns
        -------
        dict
            ``kind 'atlas'``, ``patches``, ``degree``, ``spans``, ``vertices``, ``rational``,
            ``units`` and ``bbox [[x, y, z] lo, hi]`` of the control points (scan frame;
            the surface lies in their convex hull, The NURBS Book §4.4).

        Raises
        ------
        PatchFormatError
            Not a valid atlas.
        """
        atlas, metadata = read_atlas(bytes(data))
        points = [*atlas.vertices, *atlas.edge_points, *atlas.face_points]
        lo = [min(p[c] for p in points) for c in range(3)]
        hi = [max(p[c] for p in points) for c in range(3)]
        self._patch = self._scan = None
        self._tiles.clear()
        self._last = None
        self._atlas, self._source = atlas, str(source)
        self._atlas_units = str(metadata.get("units", "unknown"))
        self._packs.clear()
        self._colours.clear()
        self._error_pack = None
        self._patch_grids = PatchGrids()
        return {"kind": "atlas", "patches": len(atlas.quads), "degree": atlas.degree,
                "spans": atlas.spans, "vertices": len(atlas.vertices),
                "rational": atlas.weights is not None, "units": self._atlas_units,
                "bbox": [lo, hi]}

    def _atlas_loaded(self) -> tuple[AtlasSurface, AtlasTiles]:
        atlas = self._atlas
        if atlas is None:
            raise RuntimeError("no atlas is loaded: call load_atlas first")
        spec = atlas_tiles(self._manifest_read())
        check_atlas_base(atlas, self._manifest_read())
        return atlas, spec

    def atlas_refinement(self) -> dict:
        """What the viewer refines an atlas by, from the manifest (:meth:`read_manifest`).

        Returns
        -------
        dict
            ``groups``: per group ``first``, ``count``, ``center``, ``radius`` and, per
            detail level ``k``, ``packs[k]`` (the pack's file name or ``None``: the group
            has no tiles there), ``bytes[k]`` and ``errors[k]`` (its ``geometric_error``:
            the largest distance of the group's scan points after levels ``0..k``);
            ``base_error``: ``tiles.detail.base.samples_max`` (the base's error, for every
            group, by the packs' measure: the detail fit's samples), else ``base.max``
            (bundles before issue 14, where ``max`` was that measure);
            ``resolutions``: samples per patch side drawn with levels ``-1, 0, .., L``
            (:meth:`atlas_mesh`'s rule); ``levels``: ``L + 1``; per group also
            ``neighbours``: the other groups whose levels its mesh depends on
            (:meth:`atlas_part_meshes`).
        """
        atlas, spec = self._atlas_loaded()
        detail = self._manifest_read()["tiles"].get("detail") or {}
        groups = []
        for g, group in enumerate(spec.groups):
            keys = [(k, g) if (k, g) in spec.packs else None for k in range(len(spec.levels))]
            groups.append({"first": group.first, "count": group.count,
                           "center": list(group.center), "radius": group.radius,
                           "packs": [key and pack_name(*key) for key in keys],
                           "bytes": [key and spec.packs[key]["bytes"] for key in keys],
                           "errors": [key and spec.packs[key]["geometric_error"]
                                      for key in keys],
                           "neighbours": _neighbour_groups(atlas, spec, g)})
        base = detail.get("base") or {}
        return {"groups": groups, "base_error": base.get("samples_max", base.get("max")),
                "levels": len(spec.levels),
                "resolutions": [_drawn_resolution(spec, k)
                                for k in range(-1, len(spec.levels))]}

    def add_pack(self, name: str, data: bytes) -> dict:
        """Decode and keep the detail pack ``name`` (``detail/K/G.tsdp``, one the manifest
        lists): ``{"level", "group", "tiles"}``.

        Raises
        ------
        ValueError
            A name the manifest does not list.
        PatchFormatError
            A bad pack, or one holding another level or patches outside its group.
        """
        atlas, spec = self._atlas_loaded()
        name = str(name)
        parts = pack_name_parts(name)
        if parts is None or parts not in spec.packs:
            raise ValueError(f"{name!r} is not a pack the manifest lists (detail/K/G.tsdp)")
        level, group = parts
        try:
            found, tiles = read_pack(bytes(data), atlas)
        except PatchFormatError as exc:
            raise PatchFormatError(exc.offset, f"{exc.reason} (detail pack {name})",
                                   exc.section) from None
        held: dict[int, list[DetailTile]] = {}
        add_pack_tiles(held, spec, name, level, group, found, tiles)
        self._packs[name] = (level, group, held)
        return {"level": level, "group": group, "tiles": sum(map(len, held.values()))}

    def drop_packs(self, names: Iterable[str]) -> None:
        """Forget packs handed over (names not held are ignored: already dropped)."""
        for name in names:
            self._packs.pop(name, None)

    def holds_pack(self, name: str) -> bool:
        """Whether the pack ``name`` has been handed over and not dropped."""
        return name in self._packs

    def atlas_mesh(self, levels: Sequence[int]) -> Mesh:
        """The whole atlas as one welded mesh, group ``g`` refined to ``levels[g]``.

        Patches of a group at level ``k`` get the held packs of levels ``0..k`` of that
        group and :func:`_drawn_resolution` ``(k)`` samples per side, the others the base's;
        neighbours of different levels are stitched by ``tessellate_atlas``'s mixed
        resolutions (the manifest's resolutions are checked to be stitchable), so the mesh
        stays watertight whatever the choice.

        Parameters
        ----------
        levels : sequence of int
            One per group, ``-1`` (the base) .. ``L``.

        Raises
        ------
        ValueError
            Not one level per group, a level out of range, or a pack of a wanted level not
            handed over (:meth:`add_pack`).
        """
        atlas, spec = self._atlas_loaded()
        resolution, detail = self._atlas_levels(spec, levels, range(len(spec.groups)))
        mesh = tessellate_atlas(atlas, resolution, detail, self._kernel)
        self._colour_groups(mesh, spec, range(len(spec.groups)), levels)
        self._last = (-2, mesh)  # not a base grid: base_ply never reuses it
        return mesh

    def _atlas_levels(self, spec: AtlasTiles, levels: Sequence[int], groups: Iterable[int]
                      ) -> tuple[list[int], dict[int, list[DetailTile]]]:
        """Samples per side of every patch and the detail of the patches of ``groups``, group
        ``g`` at ``levels[g]`` (the held packs of levels ``0..levels[g]`` of the group and
        :func:`_drawn_resolution` ``(levels[g])``): :meth:`atlas_mesh`'s rule, which
        :meth:`atlas_part_meshes` shares. ``ValueError`` for not one level per group, a level
        out of range, or a pack a group of ``groups`` needs not handed over."""
        levels = list(levels)
        if len(levels) != len(spec.groups):
            raise ValueError(f"levels has {len(levels)} values; the atlas has "
                             f"{len(spec.groups)} groups")
        resolution = [spec.base_resolution] * spec.patches
        for g, (group, level) in enumerate(zip(spec.groups, levels, strict=True)):
            if isinstance(level, bool) or not isinstance(level, int) \
                    or not -1 <= level < len(spec.levels):
                raise ValueError(f"levels[{g}] = {level!r}; an int in -1..{len(spec.levels) - 1}"
                                 " is needed")
            r = _drawn_resolution(spec, level)
            resolution[group.first : group.first + group.count] = [r] * group.count
        detail: dict[int, list[DetailTile]] = {}
        for g in groups:
            for k in range(levels[g] + 1):
                if (k, g) not in spec.packs:
                    continue
                name = pack_name(k, g)
                if name not in self._packs:
                    raise ValueError(f"group {g} at level {levels[g]} needs pack {name}, "
                                     "which was not handed over (add_pack)")
                for patch, tiles in self._packs[name][2].items():
                    detail.setdefault(patch, []).extend(tiles)
        return resolution, detail

    def atlas_part_meshes(self, groups: Sequence[int], levels: Sequence[int]) -> list[Mesh]:
        """Each of ``groups``' share of :meth:`atlas_mesh` ``(levels)``: its triangles of
        that welded mesh, with the vertices they use, the same numbers bit for bit
        (:func:`client_py.atlas_mesh.tessellate_atlas_parts`, one evaluation for all of
        them); the viewer's unit of refinement. Groups made at one level vector, together or
        apart, meet without a crack, and together are the welded mesh.

        A group's mesh depends on the levels of the group and of its ``neighbours``
        (:meth:`atlas_refinement`: the groups of the patches sharing a layout vertex with
        it) alone, and needs their held packs. With colour, a mesh carries RGB per vertex by
        :meth:`atlas_mesh`'s rule (it needs the colour packs of the group and its
        neighbours at their levels; without them its ``colors`` stays ``None``).

        Raises
        ------
        ValueError
            A group out of range or twice, bad ``levels`` (:meth:`atlas_mesh`), or a pack a
            group or a neighbour needs not handed over.
        """
        atlas, spec = self._atlas_loaded()
        groups = list(groups)
        for group in groups:
            if isinstance(group, bool) or not isinstance(group, int) \
                    or not 0 <= group < len(spec.groups):
                raise ValueError(f"group {group!r}; an int in 0..{len(spec.groups) - 1} is "
                                 "needed")
        if len(set(groups)) != len(groups):
            raise ValueError(f"groups {groups} lists a group twice")
        if not groups:
            return []
        around = {g: [g, *_neighbour_groups(atlas, spec, g)] for g in groups}
        resolution, detail = self._atlas_levels(spec, levels, sorted(set(chain(*around.values()))))
        runs = [range(spec.groups[g].first, spec.groups[g].first + spec.groups[g].count)
                for g in groups]
        part = atlas_parts(atlas, runs, _ring_depth(spec))
        meshes = tessellate_atlas_parts(part, resolution, detail, self._kernel,
                                        self._patch_grids)
        for g, mesh in zip(groups, meshes, strict=True):
            self._colour_groups(mesh, spec, around[g], [levels[h] for h in around[g]])
        return meshes

    def _atlas_level_ply(self, level: int, fresh: Mapping[str, bytes],
                         textures: Sequence[Mapping] = (),
                         progress: Callable[[float], object] | None = None) -> PlyFile:
        """:meth:`level_ply` of an atlas: the packs of levels ``0..level``, held or fresh,
        coloured from the decoded colour packs ``textures`` (those of the plan, each once)."""
        atlas, spec = self._atlas_loaded()
        plan = plan_level(self._manifest_read(), level)
        packs = self._plan_colour_packs(plan.texture_nodes, textures)
        extra = sorted(set(fresh) - set(plan.detail_files))
        if extra:
            raise ValueError(f"fresh packs {', '.join(extra)} are not packs of level {level} "
                             f"(levels 0..{level})")
        detail: dict[int, list[DetailTile]] = {}
        for name in plan.detail_files:
            if name in fresh:
                level_k, group = pack_name_parts(name)
                try:
                    found, tiles = read_pack(bytes(fresh[name]), atlas)
                except PatchFormatError as exc:
                    raise PatchFormatError(exc.offset, f"{exc.reason} (detail pack {name})",
                                           exc.section) from None
                add_pack_tiles(detail, spec, name, level_k, group, found, tiles)
            elif name in self._packs:
                for patch, tiles in self._packs[name][2].items():
                    detail.setdefault(patch, []).extend(tiles)
            else:
                raise ValueError(f"detail pack {name} was neither handed over nor sent")
        data, mesh = write_level_ply(atlas, detail, plan.level, plan.resolution, self._source,
                                     packs, kernel=self._kernel,
                                     units=self._manifest_read().get("units")
                                     or self._atlas_units, progress=progress,
                                     origin=scan_origin(self._manifest_read()))
        return PlyFile(data, mesh.vertex_count, mesh.triangle_count, plan.resolution, plan.level)


    # ------------------------------------------------------------------ an atlas's colour
    def atlas_colour_refinement(self) -> dict | None:
        """The atlas's colour for the viewer (``None`` without colour): ``levels`` (colour
        levels), ``texel`` (per detail level ``-1 .. L - 1``, the world size of a texel of the
        colour level drawn with it, median patch), ``packs`` (``file``, ``bytes``, ``level``)
        and ``group_packs`` (per group, per detail level ``-1 .. L - 1``, the file of the
        colour pack its mesh is coloured from: ``client_py.atlas_texture.colour_level``)."""
        _, spec = self._atlas_loaded()
        colour = atlas_colour(self._manifest_read())
        if colour is None:
            return None
        texel, group_packs = [], [[] for _ in spec.groups]
        for k in range(-1, len(spec.levels)):
            packs = colour.level_packs(k)
            texel.append(colour.levels[packs[0]["level"]].get("texel"))
            for pack in packs:
                for g in range(pack["group"], pack["group"] + pack["groups"]):
                    group_packs[g].append(pack["file"])
        return {"levels": len(colour.levels), "texel": texel, "group_packs": group_packs,
                "packs": [{"file": p["file"], "bytes": p["bytes"], "level": p["level"]}
                          for p in colour.packs]}

    def add_colour_pack(self, name: str, width: int, height: int, rgb: bytes) -> dict:
        """Keep the decoded colour pack ``name`` (``texture/C/G.webp``, one the manifest
        lists; ``rgb`` its ``3 width height`` bytes, rows top to bottom): ``{"level",
        "first", "count"}``.

        Raises
        ------
        ValueError
            A name the manifest does not list, or an image of another size.
        """
        self._atlas_loaded()
        colour = atlas_colour(self._manifest_read())
        nodes = [] if colour is None else [p for p in colour.packs if p["file"] == str(name)]
        if not nodes:
            raise ValueError(f"{name!r} is not a colour pack the manifest lists "
                             "(texture/C/G.webp)")
        (pack,) = colour_packs_of(nodes, {nodes[0]["file"]: (width, height, rgb)})
        self._colours[nodes[0]["file"]] = pack
        return {"level": pack.level, "first": pack.first, "count": pack.count}

    def drop_colour_packs(self, names: Iterable[str]) -> None:
        """Forget colour packs handed over (names not held are ignored)."""
        for name in names:
            self._colours.pop(name, None)

    def holds_colour_pack(self, name: str) -> bool:
        """Whether the colour pack ``name`` has been handed over and not dropped."""
        return name in self._colours

    def set_error_map(self, data: bytes | None, palette: bytes | None = None) -> dict:
        """Show the atlas's error map (``data``: the bundle's ``error_raster.bin``, the
        manifest's ``error_raster``; ``palette``: RGB of each of its 256 codes) on the meshes
        made from now on, in place of the colour packs, or ``data`` ``None``: no more.
        Returns ``{"patches", "rows"}``.

        Raises
        ------
        ValueError
            No error raster in the manifest, or a file or palette that does not fit it.
        """
        _, spec = self._atlas_loaded()
        if data is None:
            self._error_pack = None
            return {"patches": spec.patches, "rows": 0}
        raster = self._manifest_read().get("error_raster")
        if not isinstance(raster, dict) or "file" not in raster:
            raise ValueError("the manifest has no atlas error_raster (an older bundle)")
        try:
            codes = zlib.decompress(bytes(data))
        except zlib.error as exc:
            raise ValueError(f"{raster['file']} is not zlib data: {exc}") from None
        if raster.get("patches") != spec.patches or raster.get("rows") != raster.get("cols"):
            raise ValueError(f"error_raster has {raster.get('patches')} patches of "
                             f"{raster.get('rows')}x{raster.get('cols')} cells; the atlas has "
                             f"{spec.patches} patches and square cells are needed")
        self._error_pack = error_colour_pack(codes, spec.patches, raster["rows"],
                                             bytes(palette or b""))
        return {"patches": spec.patches, "rows": raster["rows"]}

    def _colour_groups(self, mesh: AtlasMesh, spec: AtlasTiles, groups: Sequence[int],
                       levels: Sequence[int]) -> None:
        """Colour ``mesh`` (of the patches of detail groups ``groups``) per vertex from the
        held colour packs, group ``groups[i]`` at the colour level of detail level
        ``levels[i]`` (:func:`client_py.atlas_texture.colours_for_groups`), when the bundle
        has colour and a pack is held for every patch of those groups (else it stays
        uncoloured: the packs are still on their way); while the error map is shown
        (:meth:`set_error_map`), from its one pack instead. The one colour rule of
        :meth:`atlas_mesh` (every group) and :meth:`atlas_part_meshes` (some groups)."""
        if self._error_pack is not None:
            everywhere = dict.fromkeys(range(spec.patches), self._error_pack)
            mesh.colors = atlas_vertex_colours(mesh.patches, mesh.uvs, everywhere)
            return
        colour = atlas_colour(self._manifest_read())
        if colour is None or not self._colours:
            return
        runs = [(spec.groups[g].first, spec.groups[g].count) for g in groups]
        of_patch = colours_for_groups(list(self._colours.values()), runs, levels,
                                      len(colour.levels))
        if len(of_patch) == sum(count for _, count in runs):
            mesh.colors = atlas_vertex_colours(mesh.patches, mesh.uvs, of_patch)

    def _plan_colour_packs(self, nodes: Sequence[Mapping],
                           textures: Sequence[Mapping]) -> list[ColourPack]:
        """The decoded colour packs of a level's plan ``nodes`` from ``textures`` sent
        (``{"file", "width", "height", "rgb"}``), held ones standing in for those not sent;
        ``ValueError`` for one the plan does not name, or one missing."""
        sent = {}
        for texture in textures:
            try:
                sent[str(texture["file"])] = (texture["width"], texture["height"],
                                              texture["rgb"])
            except (KeyError, TypeError):
                raise ValueError("a colour pack sent must be {'file', 'width', 'height', "
                                 f"'rgb'}}, got {texture!r:.80}") from None
        wanted = {n["file"] for n in nodes}
        extra = sorted(set(sent) - wanted)
        if extra:
            raise ValueError(f"colour packs {', '.join(extra)} are not in this level's plan "
                             f"({', '.join(sorted(wanted)) or 'no colour'})")
        out = []
        for node in nodes:
            if node["file"] in sent:
                out.extend(colour_packs_of([node], sent))
            elif node["file"] in self._colours:
                out.append(self._colours[node["file"]])
            else:
                raise ValueError(f"colour pack {node['file']} was neither handed over nor sent")
        return out


def _decode_tile(name: str, data: bytes) -> DetailTile:
    """``read_detail_tile`` with the file's name in the message of a bad file."""
    try:
        return read_detail_tile(bytes(data))
    except PatchFormatError as exc:
        raise PatchFormatError(exc.offset, f"{exc.reason} (detail tile {name})",
                               exc.section) from None


def _ring_depth(spec: AtlasTiles) -> int:
    """Rings of patches a group's mesh depends on (:func:`client_py.atlas_mesh.atlas_parts`):
    one, or two where the base has 2 samples per side."""
    return 1 if spec.base_resolution >= 3 else 2


def _neighbour_groups(atlas: AtlasSurface, spec: AtlasTiles, group: int) -> list[int]:
    """The other groups with a patch in group ``group``'s rings (:func:`_ring_depth`)."""
    first, count = spec.groups[group].first, spec.groups[group].count
    firsts = [g.first for g in spec.groups]
    ring = atlas_ring(atlas, range(first, first + count), _ring_depth(spec))
    return sorted({bisect_right(firsts, f) - 1 for f in ring} - {group})


def _drawn_resolution(spec: AtlasTiles, level: int) -> int:
    """Samples per patch side the viewer draws a group at ``level`` with: the level's
    (:func:`client_py.bundle.atlas_resolution`), never fewer than the base's, so refining a
    group never coarsens it."""
    return max(spec.base_resolution, spec.resolution(level))
