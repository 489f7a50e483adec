"""The atlas's colour: per patch texel cells, packed by groups into WebP images.

Layout (``client_py.atlas_texture``, docs/format.md "Atlas colour"). Colour level ``c``
gives every patch a cell of ``T_c = T_0 2^c`` texels per side over its own ``[0, 1]^2``,
with ``T_0 = 2 m`` (``m`` the detail's spans per tile), so that ``T_c = R_c - 1``: as many
texels per side as the level-``c`` mesh has cells per patch side (the client colours the
welded mesh per vertex). The cells of a run of whole detail groups (in k-d tree order, so a
compact piece of the object) share one image, cut where an image would pass
:data:`TEXELS_PER_PACK` texels: a handful of requests per level instead of one per patch,
and one pack per group and level for the viewer's per-group refinement. In the image, the
cells sit in blocks of ``b x b`` cells in Morton order (``client_py.atlas_texture.
cell_origin``), ``b`` the most that fit one WebP macroblock of :data:`MACROBLOCK` texels
(:func:`cell_block`; 1 for cells of 16 texels or more): a macroblock then holds
consecutive patches, neighbours on the object, where rows of 4-texel cells put patches
``ceil(sqrt(count))`` apart in one. On the Bali mask's smooth base (cells of 4 texels,
WebP quality 90) the blocks took 100.1 KB for a mean texel error of 3.55 where rows took
112.6 KB for 4.39 (session 32). Cells are even-sized and start on even texels (WebP's 2x2
chroma subsampling), so a chroma sample never mixes two patches' colours.

Colour. A texel centred at ``(f, u, v)`` takes the scan's colour at the foot point, on the
scan's surface, of the point the visitor is drawn there: ``X = C_f(u, v) + D_f(u, v) n_f``
(base and finest detail level, ``client_py.layers.displacement_grid``), projected to the
closest point of the scan's triangles (``.measure.closest_points_on_mesh``); there the
per-vertex colours are interpolated with the point's barycentric coordinates, or the
texture coordinates are and the scan's texture is sampled bilinearly
(``fitter.fitting.texture.sample_image``). A point cloud gives the colour of the nearest
point. Coarser levels are 2x2 means of the finest.

Depth. ``fitter.fitting.texture.texel_levels``, the single patch's rule, over one patch:
the scan's colour samples per patch (vertices, or texture texels through the mesh's UV
area, over the patch count) give the side a cell need not pass; at most the detail levels.
"""

from __future__ import annotations

from array import array
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from client_py.atlas_texture import cell_origin, colour_pack_name, pack_shape, texture_format
from client_py.layers import displacement_grid

from ..texture import (
    colour_samples,
    encode_image,
    has_colour,
    sample_image,
    texel_levels,
    uv_picture,
)
from .measure import DrawnMesh, barycentric, closest_points_on_mesh
from .patches import control_points, evaluate_patches, index_table

TEXELS_PER_PACK = 512 * 512  # an image grows by whole groups until it passes this
MACROBLOCK = 16  # texels per side of a WebP macroblock (its luma block)
CHUNK_TEXELS = 200_000  # texels projected at once (memory ~ 1 KB each)
FILLER = 128  # grey of the unused cells past a pack's last patch
#: WebP quality of the colour images: cells of neighbouring images' patches sit side by side,
#: and at the single patch's 82 the decoder's chroma upsampling and the coarser quantisation
#: carried one cell's colour into the next (bench atlas_colour: the measured trade-off)
COLOUR_QUALITY = 90


@dataclass
class AtlasTexture:
    """The atlas's colour, ready for the bundle.

    Attributes
    ----------
    tree : dict
        The manifest's ``tiles.texture``.
    files : dict of str to bytes
        ``texture/C/G.webp`` -> the image's bytes.
    cells : list of ndarray
        ``cells[c]``: shape ``(F, T_c, T_c, 3)``, uint8, axis 1 ``u`` and axis 2 ``v``: the
        texels before encoding.
    groups : list of dict
        The detail groups the packs hold (``tiles.detail.groups``).
    """

    tree: dict
    files: dict
    cells: list
    groups: list


def scan_colour_at(scan, points: np.ndarray) -> np.ndarray:
    """RGB ``(N, 3)`` float of ``scan`` at the foot points of ``points (N, 3)`` on its
    surface (module docstring): a mesh's per-vertex colours or texture, interpolated at
    the closest point of its triangles; a cloud's nearest point's colour."""
    vertices = np.asarray(scan.points, dtype=float)
    if scan.faces is None or not len(scan.faces):
        _, nearest = cKDTree(vertices).query(points)
        return scan.colors[nearest, :3].astype(float)
    faces = np.asarray(scan.faces, dtype=np.int64)
    _, tri, q = closest_points_on_mesh(points, vertices, faces)
    corners = faces[tri]
    w = barycentric(q, *(vertices[corners[:, k]] for k in range(3)))
    if scan.uv is not None and scan.texture is not None:
        tex_uv = np.einsum("nk,nkc->nc", w, scan.uv[corners])
        return sample_image(np.asarray(scan.texture.convert("RGB")), tex_uv)
    return np.einsum("nk,nkc->nc", w, scan.colors[corners, :3].astype(float))


def drawn_texel_points(atlas, tiles_of_patch: dict, patches: np.ndarray, side: int
                       ) -> np.ndarray:
    """The drawn surface ``C_f + D_f n_f`` at the texel centres ``((x + 1/2) / T, (y + 1/2)
    / T)`` of each of ``patches``' cells of ``T = side`` texels: shape ``(len(patches), T,
    T, 3)``, axis 1 ``u``, axis 2 ``v``."""
    t = (np.arange(side) + 0.5) / side
    uu, vv = np.meshgrid(t, t, indexing="ij")
    count = len(patches)
    f = np.repeat(patches, side * side)
    u, v = np.tile(uu.ravel(), count), np.tile(vv.ravel(), count)
    c, cu, cv = evaluate_patches(index_table(atlas), control_points(atlas), atlas.degree,
                                 atlas.spans, f, u, v, derivatives=True)
    n = np.cross(cu, cv)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    d = np.zeros(len(f))
    ts = t.tolist()
    for k, patch in enumerate(patches):
        tiles = tiles_of_patch.get(int(patch))
        if tiles:
            d[k * side * side:(k + 1) * side * side] = np.frombuffer(
                displacement_grid(tiles, ts, ts, "numpy"), dtype=float)
    return (c + d[:, None] * n).reshape(count, side, side, 3)


def pack_runs(groups: list[dict], cell: int, limit: int = TEXELS_PER_PACK
              ) -> list[tuple[int, int]]:
    """``(first group, group count)`` of each image of a level with ``cell`` texels per
    patch side: consecutive whole groups, a new image once the next group would take it
    past ``limit`` texels (a group alone may pass it)."""
    runs: list[tuple[int, int]] = []
    start, texels = 0, 0
    for g, group in enumerate(groups):
        size = group["count"] * cell * cell
        if g > start and texels + size > limit:
            runs.append((start, g - start))
            start, texels = g, 0
        texels += size
    runs.append((start, len(groups) - start))
    return runs


def cell_block(cell: int) -> int:
    """Cells per side of a pack's blocks for cells of ``cell`` texels: the largest power of
    two ``b`` with ``b cell <= MACROBLOCK``, at least 1."""
    block = 1
    while 2 * block * cell <= MACROBLOCK:
        block *= 2
    return block


def pack_image(cells: np.ndarray, cell: int, block: int) -> np.ndarray:
    """The image ``(H, W, 3)`` of consecutive patches' ``cells (count, T, T, 3)`` in the
    pack layout of ``block x block`` cell blocks (``client_py.atlas_texture.cell_origin``;
    the fitter's :func:`cell_block`), filler grey past the last."""
    count = len(cells)
    width, height = pack_shape(count, cell, block)
    image = np.full((height, width, 3), FILLER, np.uint8)
    for s in range(count):
        x, y = cell_origin(s, count, cell, block)
        image[y:y + cell, x:x + cell] = uv_picture(cells[s])
    return image


def sample_cells(scan, atlas, tiles_of_patch: dict, side: int) -> np.ndarray:
    """Every patch's cell of ``side`` texels from ``scan``'s colour at the foot points of
    the drawn texel centres (:func:`drawn_texel_points`, :func:`scan_colour_at`), in chunks
    of about :data:`CHUNK_TEXELS`: shape ``(F, side, side, 3)`` uint8, axis 1 ``u``."""
    patches = len(atlas.quads)
    step = max(1, CHUNK_TEXELS // (side * side))
    cells = np.empty((patches, side, side, 3), np.uint8)
    for start in range(0, patches, step):
        chunk = np.arange(start, min(patches, start + step))
        points = drawn_texel_points(atlas, tiles_of_patch, chunk, side)
        rgb = scan_colour_at(scan, points.reshape(-1, 3))
        cells[chunk] = np.clip(np.rint(rgb), 0, 255).astype(np.uint8).reshape(
            len(chunk), side, side, 3)
    return cells


def coarser_cells(finest: np.ndarray, levels: int) -> list[np.ndarray]:
    """The cells of colour levels ``0..levels-1`` from the finest ``(F, T, T, 3)``: each
    coarser level the 2x2 means of the next, rounded."""
    cells = [finest]
    for _ in range(levels - 1):
        count, r = len(cells[0]), cells[0].shape[1] // 2
        coarse = cells[0].astype(float).reshape(count, r, 2, r, 2, 3).mean(axis=(2, 4))
        cells.insert(0, np.clip(np.rint(coarse), 0, 255).astype(np.uint8))
    return cells


def encode_levels(cells: list[np.ndarray], groups: list[dict], texel_zero: float,
                  quality: int = COLOUR_QUALITY) -> tuple[dict, list, list]:
    """The colour images of every level's ``cells`` packed by runs of ``groups``
    (:func:`pack_runs`, :func:`pack_image`) as WebP of ``quality``: ``(files, packs,
    levels)``, the bundle's files and the manifest's ``packs`` and ``levels`` rows
    (``texel``: ``texel_zero`` over the level's texels per side)."""
    files: dict[str, bytes] = {}
    packs, rows = [], []
    for c, level_cells in enumerate(cells):
        cell = level_cells.shape[1]
        block = cell_block(cell)
        total = 0
        runs = pack_runs(groups, cell)
        for g, count in runs:
            first = groups[g]["first"]
            last = groups[g + count - 1]
            end = last["first"] + last["count"]
            data = encode_image(pack_image(level_cells[first:end], cell, block),
                                quality=quality)
            files[colour_pack_name(c, g)] = data
            total += len(data)
            packs.append({"level": c, "group": g, "groups": count, "bytes": len(data)})
        rows.append({"level": c, "cell": cell, "block": block,
                     "texel": float(f"{texel_zero / cell:.6g}"),
                     "bytes_total": total, "packs": len(runs)})
    return files, packs, rows


def fit_atlas_texture(scan, detail, enabled: bool = True) -> AtlasTexture | None:
    """The colour of ``detail``'s atlas (an ``.detail.AtlasDetail``: its renumbered atlas,
    tiles and groups) from ``scan``: ``None`` without colour, without detail levels (the
    packs follow the detail groups) or when not ``enabled``."""
    if not enabled or not has_colour(scan) or not detail.levels:
        return None
    atlas = detail.atlas
    patches = len(atlas.quads)
    first_cell = 2 * detail.tree["spans_per_tile"]
    covered = np.ones(len(scan.points), dtype=bool)
    per_patch = colour_samples(scan, covered) / patches
    levels = texel_levels(np.sqrt(max(per_patch, 1.0)), first_cell, len(detail.levels))
    top = sample_cells(scan, atlas, detail.detail_up_to(len(detail.levels) - 1),
                       first_cell << (levels - 1))
    cells = coarser_cells(top, levels)
    groups = detail.tree["groups"]
    files, packs, rows = encode_levels(cells, groups, float(detail.patch_side))
    tree = {"format": texture_format([row["block"] for row in rows]), "levels": rows,
            "packs": packs,
            "source": "texture" if scan.uv is not None and scan.texture is not None
            and scan.faces is not None else "vertex colours"}
    return AtlasTexture(tree, files, cells, groups)


def scan_vertex_colours(scan) -> np.ndarray:
    """The scan's own colour at each of its points ``(N, 3)`` float: its per-vertex colour,
    or its texture sampled at its texture coordinates."""
    if scan.uv is not None and scan.texture is not None:
        return sample_image(np.asarray(scan.texture.convert("RGB")), scan.uv)
    return scan.colors[:, :3].astype(float)


def colour_error(scan, vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray,
                 foot: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """How far the drawn colours are from the scan's: for EVERY scan point, its colour
    (:func:`scan_vertex_colours`) against the drawn mesh's ``(vertices, faces)`` vertex
    ``colours (V, 3)`` interpolated at its foot point (the closest point of the drawn
    triangles, as the GPU interpolates vertex colours; ``foot``: each point's nearest
    triangle ``(N,)`` and closest point ``(N, 3)`` when already found,
    ``atlas.measure.closest_points_on_mesh``). ``mean_abs``: mean ``|ΔRGB|`` per
    channel; ``rms``, ``p95``: of the Euclidean ``ΔRGB`` (0..255 units)."""
    points = np.asarray(scan.points, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    vertices = np.asarray(vertices, dtype=float)
    tri, q = closest_points_on_mesh(points, vertices, faces)[1:] if foot is None else foot
    corners = faces[tri]
    w = barycentric(q, *(vertices[corners[:, k]] for k in range(3)))
    drawn = np.einsum("nk,nkc->nc", w, np.asarray(colours, float)[corners])
    delta = drawn - scan_vertex_colours(scan)
    norm = np.linalg.norm(delta, axis=1)
    return {"points": int(len(points)), "mean_abs": float(np.abs(delta).mean()),
            "rms": float(np.sqrt(np.mean(norm ** 2))), "p95": float(np.percentile(norm, 95))}


def decoded_packs(texture: AtlasTexture, level: int) -> list:
    """Colour level ``level``'s images decoded from their bytes (Pillow) as the client's
    ``client_py.atlas_texture.ColourPack``, patches from the manifest's groups."""
    import io

    from PIL import Image

    from client_py.atlas_texture import ColourPack

    out = []
    groups = texture.groups
    for pack in texture.tree["packs"]:
        if pack["level"] != level:
            continue
        first = groups[pack["group"]]["first"]
        last = groups[pack["group"] + pack["groups"] - 1]
        count = last["first"] + last["count"] - first
        with Image.open(io.BytesIO(texture.files[colour_pack_name(level, pack["group"])])) as im:
            rgb = im.convert("RGB")
            entry = texture.tree["levels"][level]
            out.append(ColourPack(level, first, count, entry["cell"], rgb.width, rgb.height,
                                  rgb.tobytes(), entry["block"]))
    return out


def drawn_colour_error(scan, drawn: DrawnMesh, foot: tuple[np.ndarray, np.ndarray],
                       texture: AtlasTexture, level: int, patches: int) -> dict:
    """:func:`colour_error` of ``drawn``, the mesh a visitor is drawn with every group at
    detail level ``level`` (``atlas.measure.drawn_mesh`` of an atlas of ``patches``
    patches), coloured from the DECODED colour images of the level's colour level
    (``client_py.atlas_texture.atlas_vertex_colours``); ``foot``: the scan points' nearest
    triangles of ``drawn`` and closest points on them (the error stage's, not searched
    again)."""
    from client_py.atlas_texture import atlas_vertex_colours, colour_level, colours_by_patch

    c = colour_level(level, len(texture.tree["levels"]))
    of_patch = colours_by_patch(decoded_packs(texture, c), patches)
    rgb = np.frombuffer(atlas_vertex_colours(
        array("I", drawn.patches.astype(np.uint32).tobytes()),
        array("f", drawn.uvs.astype(np.float32).tobytes()), of_patch), np.uint8)
    return {"level": level, "colour_level": c,
            **colour_error(scan, drawn.vertices, drawn.faces, rgb.reshape(-1, 3), foot)}
