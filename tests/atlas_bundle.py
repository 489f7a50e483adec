"""Version-2 (atlas) bundles for tests, made without the fitter.

:func:`write_atlas_bundle` writes a bundle folder per docs/format.md, "Bundle manifest,
version 2 (atlas)": ``base.tsa`` of a sphere atlas on a subdivided cube
(``tests/atlas_cases.sphere_atlas``: closed, ``6 k^2`` patches), one pack per level and
group of random detail tiles (every tile of every patch at every level, small
displacements so the mesh stays a closed surface), and the manifest. Groups are the six
cube faces (``k^2`` contiguous patches each), their bounding spheres measured on the
atlas's own tessellation; a pack's ``geometric_error`` shrinks with the level.

:func:`add_colour_packs` gives such a bundle colour (docs/format.md, "Atlas colour"): WebP
colour packs of two levels whose cells the caller paints.
"""

from __future__ import annotations

import io
import json
import math
import random
import zlib
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from atlas_cases import sphere_atlas

from client_py.atlas import ring_positions
from client_py.atlas_detail import PACK_VERSION, WALLS_FREE_VERSION, pack_name, write_pack
from client_py.atlas_format import write_atlas
from client_py.atlas_mesh import tessellate_atlas
from client_py.atlas_texture import cell_origin, colour_pack_name, pack_shape
from client_py.layers import DetailTile
from client_py.trim import TrimMask

DEGREE, SPANS_PER_TILE = 2, 2


def random_tile(level: int, i: int, j: int, rnd: random.Random, amplitude: float) -> DetailTile:
    """A tile of ``(SPANS_PER_TILE + DEGREE)^2`` random coefficients of at most
    ``amplitude`` (scan units)."""
    size = SPANS_PER_TILE + DEGREE
    step = amplitude / 8
    return DetailTile(level, i, j, DEGREE, SPANS_PER_TILE, step,
                      tuple(rnd.randint(-8, 8) for _ in range(size * size)))


def welded_tiles(atlas, level: int, rnd: random.Random, amplitude: float
                 ) -> dict[int, list[DetailTile]]:
    """Every tile of every patch at ``level`` as the fitter makes them: a level grid of ``n
    = SPANS_PER_TILE 2^level + DEGREE`` random coefficients a side per patch whose border
    ring takes one value per shared slot (``AtlasSurface.border_slots``), cut into tiles."""
    n, size = (SPANS_PER_TILE << level) + DEGREE, SPANS_PER_TILE + DEGREE
    slots: dict[int, int] = {}
    out = {}
    for f in range(len(atlas.quads)):
        grid = [[rnd.randint(-8, 8) for _ in range(n)] for _ in range(n)]
        for (a, b), slot in zip(ring_positions(n), atlas.border_slots(f, n), strict=True):
            grid[a][b] = slots.setdefault(slot, rnd.randint(-8, 8))
        out[f] = [DetailTile(level, i, j, DEGREE, SPANS_PER_TILE, amplitude / 8,
                             tuple(grid[i * SPANS_PER_TILE + a][j * SPANS_PER_TILE + b]
                                   for a in range(size) for b in range(size)))
                  for i in range(1 << level) for j in range(1 << level)]
    return out


def write_atlas_bundle(folder: Path, k: int = 1, levels: int = 2, base_resolution: int = 5,
                       seed: int = 0, title: str = "Atlas sphere", welded: bool = False,
                       walls: float = 0.0) -> dict:
    """Write an atlas bundle of ``6 k^2`` patches and ``levels`` detail levels into
    ``folder``; returns its manifest. ``welded``: tiles whose neighbours share their border
    coefficients (:func:`welded_tiles`), in welded packs (``write_pack(..., atlas)``), as the
    fitter writes them; else independent random tiles in packs without an atlas. ``walls``:
    the share of random cells each tile's walls mask leaves out (docs/format.md, version 5
    packs; its side the level's cells a tile side), 0 for none."""
    folder.mkdir(parents=True, exist_ok=True)
    rnd = random.Random(seed)
    atlas = sphere_atlas(k, noise=0.02, seed=seed)
    base = write_atlas(atlas, bits=12, metadata={"units": "mm"})
    (folder / "base.tsa").write_bytes(base)
    files = {"base.tsa": len(base)}
    per_face = k * k
    mesh = tessellate_atlas(atlas, 5)
    groups = []
    for g in range(6):
        first = g * per_face
        points = [tuple(mesh.positions[3 * v : 3 * v + 3]) for v in range(mesh.vertex_count)
                  if first <= mesh.patches[v] < first + per_face]
        centre = [sum(p[c] for p in points) / len(points) for c in range(3)]
        radius = max(math.dist(centre, p) for p in points)
        groups.append({"first": first, "count": per_face, "center": centre, "radius": radius})
    packs, level_entries = [], []
    for level in range(levels):
        amplitude = 0.02 / 2**level
        total = 0
        every = welded_tiles(atlas, level, rnd, amplitude) if welded else None
        for g in range(6):
            patches = range(g * per_face, (g + 1) * per_face)
            if welded:
                tiles = {f: every[f] for f in patches}
            else:
                tiles = {f: [random_tile(level, i, j, rnd, amplitude) for i in range(1 << level)
                             for j in range(1 << level)] for f in patches}
            if walls:
                side = 2 * SPANS_PER_TILE  # the level's drawn cells a tile side
                tiles = {f: [replace(t, walls=TrimMask.from_flat(
                    side, side, bytes(rnd.random() < walls for _ in range(side * side))))
                    for t in ts] for f, ts in tiles.items()}
            data = write_pack(level, tiles, atlas if welded else None)
            name = pack_name(level, g)
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_bytes(data)
            files[name] = len(data)
            total += len(data)
            packs.append({"level": level, "group": g, "bytes": len(data),
                          "geometric_error": 0.01 / 2**level})
        level_entries.append({"level": level, "rms": 0.004 / 2**level, "max": 0.01 / 2**level,
                              "bytes_total": total, "packs": 6,
                              "resolution": min(129, 2 * SPANS_PER_TILE * 2**level + 1)})
    raster = write_error_raster(folder, len(atlas.quads), rnd, 0.02)
    files[raster["file"]] = raster["bytes"]
    manifest = {
        "format": "tessera-bundle", "format_version": 2, "title": title,
        "description": "a test atlas", "units": "mm",
        "provenance": {"source": "tests/atlas_bundle.py", "points": 0, "bytes": 0},
        "options": {}, "view": {"up": [0.0, 0.0, 1.0], "front": [0.0, -1.0, 0.0]},
        "files": files,
        "base": {"file": "base.tsa", "kind": "atlas", "degree": atlas.degree,
                 "spans": atlas.spans, "patches": len(atlas.quads),
                 "vertices": len(atlas.vertices), "edges": len(atlas.edges.edges),
                 "border_edges": len(atlas.edges.border_edges), "bits": 12,
                 "rational": False, "resolution": base_resolution},
        "transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
        "stats": {"rms": 0.004, "max": 0.02, "units": "mm"},
        "error_raster": raster,
        "tiles": {"version": 2, "texture": None, "detail": {
            "format": "tsdp", "format_version": PACK_VERSION if walls else WALLS_FREE_VERSION,
            "tile_format_version": 2,
            "degree": DEGREE, "spans_per_tile": SPANS_PER_TILE,
            "base": {"rms": 0.008, "max": 0.03}, "levels": level_entries,
            "groups": groups, "packs": packs}},
    }
    (folder / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest


#: cells per patch side of :func:`write_error_raster`
ERROR_RASTER_SIDE = 4


def write_error_raster(folder: Path, patches: int, rnd: random.Random, largest: float) -> dict:
    """An atlas's ``error_raster.bin`` (docs/format.md) of random codes, patch 0 uncovered
    (every cell 255) and one cell of patch 1 at the largest code (254 = ``largest``);
    returns its manifest entry."""
    side = ERROR_RASTER_SIDE
    codes = bytearray(rnd.randrange(0, 200) for _ in range(patches * side * side))
    codes[: side * side] = bytes([255]) * (side * side)
    codes[side * side + 5] = 254
    data = zlib.compress(bytes(codes))
    (folder / "error_raster.bin").write_bytes(data)
    return {"file": "error_raster.bin", "patches": patches, "rows": side, "cols": side,
            "statistic": "max |d|", "max": largest, "bytes": len(data),
            "encoding": "zlib of uint8 codes"}


#: colour levels of :func:`add_colour_packs`: per level, its packs' runs of detail groups
#: ``(first group, groups)`` (level 0: one pack of all six; level 1: two packs of three)
COLOUR_PACK_RUNS = ((0, ((0, 6),)), (1, ((0, 3), (3, 3))))


def add_colour_packs(folder: Path, manifest: dict, paint_cell: Callable, cell: int = 8) -> dict:
    """Colour packs of two levels (:data:`COLOUR_PACK_RUNS`) for the bundle of
    :func:`write_atlas_bundle` in ``folder``: level ``c``'s cells are ``cell 2^c`` texels per
    side, patch ``f``'s painted ``paint_cell(c, f, side)`` (a ``(side, side, 3)`` uint8
    array, row 0 the top), filler cells grey; the manifest is updated, rewritten and
    returned. Lossless WebP, so the texels read back are those painted."""
    import numpy as np  # test helpers only: the bundle itself needs neither
    from PIL import Image

    groups = manifest["tiles"]["detail"]["groups"]
    levels, packs = [], []
    for level, runs in COLOUR_PACK_RUNS:
        side = cell << level
        total = 0
        for g, count in runs:
            first = groups[g]["first"]
            patches = sum(groups[h]["count"] for h in range(g, g + count))
            width, height = pack_shape(patches, side)
            image = np.full((height, width, 3), 128, np.uint8)
            for s in range(patches):  # no "block": rows of cells, as before blocks
                x, y = cell_origin(s, patches, side)
                image[y:y + side, x:x + side] = paint_cell(level, first + s, side)
            buffer = io.BytesIO()
            Image.fromarray(image).save(buffer, "WEBP", lossless=True)
            name = colour_pack_name(level, g)
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_bytes(buffer.getvalue())
            manifest["files"][name] = len(buffer.getvalue())
            total += len(buffer.getvalue())
            packs.append({"level": level, "group": g, "groups": count,
                          "bytes": len(buffer.getvalue())})
        levels.append({"level": level, "cell": side, "texel": 1.0 / side,
                       "bytes_total": total, "packs": len(runs)})
    manifest["tiles"]["texture"] = {"format": "webp", "source": "vertex colours",
                                    "levels": levels, "packs": packs}
    (folder / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest
