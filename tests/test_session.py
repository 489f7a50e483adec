"""client_py.session (the browser worker's Python) and the one rule for a level-L PLY
(client_py.bundle.plan_level, write_level_ply), in CPython: the plan against the manifest and
the files on disk, the skirts against a per-vertex numpy reference, the region mesh against
tessellate_region + hang_skirts, and the session's level PLY against ``tessera tessellate
BUNDLE --level L``, byte for byte."""

from __future__ import annotations

import json
import random
import re
from fractions import Fraction

import numpy as np
import pytest
from conftest import PROJECT_ROOT
from nurbs_cases import random_surface
from PIL import Image

from client_py import (
    DetailTile,
    NurbsSurface,
    PatchFormatError,
    TrimMask,
    hang_skirts,
    plan_level,
    plan_levels,
    read_patch,
    tessellate_bundle,
    tessellate_region,
    write_detail_tile,
    write_patch,
)
from client_py.bundle import (
    MIN_LEVEL_CELLS,
    PLY_MAX_RESOLUTION,
    ManifestError,
    level_resolution,
    region_resolution,
    texture_nodes,
)
from client_py.layers import tile_rect, transform_mesh
from client_py.session import WorkerSession
from fitter.cli import main

DEGREE, SPANS, LEVELS = 2, 4, 3
ABSENT_DETAIL = {(2, 0, 3), (2, 3, 0), (2, 3, 3)}  # level-2 tiles the bundle leaves out
ABSENT_TEXTURE = (1, 1, 1)  # the level-1 texture tile left out (level 0 stands in)
TEXTURE_SIZE = 8
# patch frame -> scan frame: a rotation about z, a scale and a shift
TRANSFORM = [[0.0, -2.0, 0.0, 250.0], [2.0, 0.0, 0.0, -40.0], [0.0, 0.0, 2.0, 1200.0],
             [0.0, 0.0, 0.0, 1.0]]


def _base_patch() -> NurbsSurface:
    """A gently curved rational patch over (0, 2) x (-1, 1), a corner trimmed away (mask
    rows 3..7 x columns 5..7 of 8 x 8)."""
    rough = random_surface(np.random.default_rng(3), 2, 2, 6, 5,
                           domain=((0.0, 2.0), (-1.0, 1.0)))
    a, b = np.meshgrid(np.linspace(0, 2, 6), np.linspace(-1, 1, 5), indexing="ij")
    points = np.stack([a, b, 0.1 * np.sin(3 * a) * np.cos(2 * b)], axis=-1)
    trim = TrimMask([[not (r >= 3 and c >= 5) for c in range(8)] for r in range(8)])
    return NurbsSurface((2, 2), rough.knots, points.tolist(), rough.weights, trim=trim,
                        metadata={"units": "mm", "transform": TRANSFORM})


def _detail_tile(rng: np.random.Generator, level: int, i: int, j: int) -> DetailTile:
    values = rng.integers(-40, 41, (SPANS + DEGREE) ** 2)
    return DetailTile(level, i, j, DEGREE, SPANS, 2.0**-9, tuple(int(x) for x in values))


def _texture_rgb(level: int, i: int, j: int) -> np.ndarray:
    """A gradient per tile (red along x, green along y), blue naming the tile."""
    ramp = np.linspace(0, 255, TEXTURE_SIZE).round().astype(np.uint8)
    rgb = np.empty((TEXTURE_SIZE, TEXTURE_SIZE, 3), np.uint8)
    rgb[..., 0], rgb[..., 1] = ramp[None, :], ramp[:, None]
    rgb[..., 2] = 30 + 50 * level + 20 * (i + 2 * j)
    return rgb


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A bundle written here (no fit): base, detail levels 0..2 with three level-2 tiles
    absent, texture levels 0 and 1 with tile 1/1_1 absent; lossless PNG textures."""
    root = tmp_path_factory.mktemp("session") / "relief-session"
    root.mkdir()
    (root / "base.tsp").write_bytes(write_patch(_base_patch()))
    rng = np.random.default_rng(7)
    nodes = []
    for level in range(LEVELS):
        for i in range(1 << level):
            for j in range(1 << level):
                if (level, i, j) in ABSENT_DETAIL:
                    continue
                name = f"detail/{level}/{i}_{j}.tsd"
                (root / name).parent.mkdir(parents=True, exist_ok=True)
                data = write_detail_tile(_detail_tile(rng, level, i, j))
                (root / name).write_bytes(data)
                nodes.append({"level": level, "i": i, "j": j, "uv": list(tile_rect(level, i, j)),
                              "file": name, "bytes": len(data)})
    textures = []
    for level, i, j in [(0, 0, 0), (1, 0, 0), (1, 1, 0), (1, 0, 1)]:
        name = f"texture/{level}/{i}_{j}.png"
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(_texture_rgb(level, i, j)).save(root / name)
        textures.append({"level": level, "i": i, "j": j, "file": name,
                         "bytes": (root / name).stat().st_size})
    manifest = {
        "units": "mm", "base": {"file": "base.tsp"},
        "tiles": {"version": 1,
                  "detail": {"format": "tsd", "format_version": 2, "degree": DEGREE,
                             "spans_per_tile": SPANS, "base": {"rms": 0.5, "max": 2.0},
                             "levels": [{"level": k, "rms": 0.4 / (k + 1)}
                                        for k in range(LEVELS)],
                             "nodes": nodes},
                  "texture": {"format": "png", "size": TEXTURE_SIZE,
                              "levels": [{"level": 0}, {"level": 1}], "nodes": textures}},
    }
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root


def _manifest(bundle) -> dict:
    return json.loads((bundle / "manifest.json").read_text())


def _session(bundle, source=None) -> WorkerSession:
    session = WorkerSession()
    session.load_patch((bundle / "base.tsp").read_bytes(), source or bundle.name)
    session.read_manifest((bundle / "manifest.json").read_text())
    return session


def _texture_dicts(bundle, nodes) -> list[dict]:
    """The plan's texture tiles decoded by Pillow, as the page sends them (rows top first)."""
    out = []
    for node in nodes:
        with Image.open(bundle / node["file"]) as im:
            rgb = im.convert("RGB")
            out.append({"level": node["level"], "i": node["i"], "j": node["j"],
                        "width": rgb.width, "height": rgb.height,
                        "rgb": memoryview(rgb.tobytes())})  # Pyodide hands memoryviews
    return out


# --- the plan: one rule for what level L needs ------------------------------------------------

def test_the_plan_names_the_manifest_tiles_and_the_files_on_disk(bundle):
    manifest = _manifest(bundle)
    on_disk = sorted(p.relative_to(bundle).as_posix() for p in bundle.glob("detail/*/*.tsd"))
    for level in range(LEVELS):
        plan = plan_level(manifest, level)
        wanted = [f for f in on_disk if int(f.split("/")[1]) <= level]
        assert sorted(plan.detail_files) == wanted
        assert plan.detail_bytes == sum((bundle / f).stat().st_size for f in wanted)
        assert plan.resolution == min(1025, 2 * SPANS * 2**level + 1)
        assert plan.rms == manifest["tiles"]["detail"]["levels"][level]["rms"]
    # texture: level 0 alone at level 0; from level 1 on, the three level-1 tiles and, for
    # the absent one's quadrant, level 0's
    assert [(n["level"], n["i"], n["j"]) for n in plan_level(manifest, 0).texture_nodes] == \
        [(0, 0, 0)]
    fine = plan_level(manifest, 2)
    assert {(n["level"], n["i"], n["j"]) for n in fine.texture_nodes} == \
        {(0, 0, 0), (1, 0, 0), (1, 1, 0), (1, 0, 1)}
    assert fine.texture_bytes == sum((bundle / n["file"]).stat().st_size
                                     for n in fine.texture_nodes)
    base = plan_level(manifest, -1)
    assert base.detail_files == () and base.rms == 0.5
    assert plan_level(manifest) == fine  # default: the finest
    assert plan_levels(manifest) == [plan_level(manifest, k) for k in range(LEVELS)]
    assert plan_levels({"tiles": {"detail": None}}) == []


def test_the_grid_is_capped_and_the_session_offers_every_level(bundle):
    assert level_resolution(16, 4) == 513
    assert level_resolution(16, 5) == PLY_MAX_RESOLUTION == 1025  # 1025 = 2 16 2^5 + 1
    assert level_resolution(64, 4) == 1025  # not 2049
    assert [level_resolution(16, k) for k in range(4)] == [257] * 4  # Buddha scan 0's levels
    assert [level_resolution(16, k, min_cells=0) for k in range(4)] == [33, 65, 129, 257]
    session = _session(bundle)
    offered = session.level_choices()
    assert json.loads(json.dumps(offered)) == offered  # plain values for the page
    assert offered["max_resolution"] == 1025 and offered["spans_per_tile"] == SPANS
    choices = offered["levels"]
    assert choices == [p.to_dict() for p in plan_levels(_manifest(bundle))]
    assert [c["level"] for c in choices] == list(range(LEVELS))
    assert choices[1]["texture_nodes"] == [dict(n) for n in texture_nodes(_manifest(bundle), 1)]


# --- the grid a level is drawn on (client_py.bundle.tile_cells, session 13) ----------------

def _grid(resolution: int) -> set:
    """The parameter values ``a / (R - 1)`` of an ``R``-vertex grid, exactly."""
    return {Fraction(a, resolution - 1) for a in range(resolution)}


@pytest.mark.parametrize("spans", [1, 3, 4, 16, 64, 255])
def test_a_level_is_drawn_on_its_own_grid_halved_until_it_has_256_cells(spans):
    """Against the grids a level could be drawn on that keep every vertex of its own grid
    (two per knot span, ``2 m 2^L`` cells: each cell halved ``j`` times): the coarsest of
    them with at least ``MIN_LEVEL_CELLS`` cells across, capped at 1025 vertices. The
    regions of a level side by side are that grid, each a multiple of the tile's spans."""
    from client_py.format import MAX_WALLS_SIDE

    assert MIN_LEVEL_CELLS == 256 <= MAX_WALLS_SIDE  # level 0's one tile holds its walls
    for level in range(7):
        own = min(1025, 2 * spans * 2**level + 1)
        assert level_resolution(spans, level, min_cells=0) == own  # bundles before it
        halved = [2 * spans * 2**level * 2**j for j in range(12)]
        expected = min(1025, min(c for c in halved if c >= 256) + 1)
        drawn = level_resolution(spans, level)
        assert drawn == expected, (spans, level)
        assert _grid(own) <= _grid(drawn)  # every vertex of the level's own grid is kept
        region = region_resolution(spans, level)
        assert (region - 1) % (2 * spans) == 0 and region >= 2 * spans + 1
        assert region_resolution(spans, level, min_cells=0) == 2 * spans + 1
        if drawn < 1025:
            assert (region - 1) * 2**level + 1 == drawn
            assert (region - 1) * 2**level >= 256


@pytest.mark.parametrize(("args", "match"), [
    ((0, 0), r"spans_per_tile must be a positive integer, got 0"),
    ((16, -1), r"level must be an integer >= 0, got -1"),
    ((16, True), r"level must be an integer >= 0, got True"),
    ((16, 0, -4), r"min_cells must be an integer >= 0, got -4"),
])
def test_a_bad_grid_argument_is_refused(args, match):
    with pytest.raises(ValueError, match=match):
        level_resolution(*args)


def _stating(manifest: dict, levels=range(LEVELS)) -> dict:
    """``manifest`` with ``resolution`` stated on the level entries ``levels``, as the
    fitter writes it from session 13."""
    for k in levels:
        manifest["tiles"]["detail"]["levels"][k]["resolution"] = level_resolution(SPANS, k)
    return manifest


def test_a_bundle_stating_its_grids_is_drawn_on_them_an_older_one_as_before(bundle):
    """The fixture's manifest (m = 4) states no ``resolution``: its levels are drawn on
    ``2 m 2^L + 1`` = 9, 17, 33 vertices, as every bundle before session 13; stated, on
    257 (every level, 256 cells across), in regions of 257, 129, 65 vertices. A level
    entry tells its own level's rule."""
    old = _manifest(bundle)
    assert [(p.resolution, p.region_resolution) for p in plan_levels(old)] == \
        [(9, 9), (17, 9), (33, 9)]
    new = _stating(_manifest(bundle))
    assert [(p.resolution, p.region_resolution) for p in plan_levels(new)] == \
        [(257, 257), (257, 129), (257, 65)]
    assert plan_level(new, -1).region_resolution is None
    mixed = _stating(_manifest(bundle), levels=[1])
    assert [p.resolution for p in plan_levels(mixed)] == [9, 257, 33]
    session = WorkerSession()
    session.read_manifest(json.dumps(new))
    assert [c["region_resolution"] for c in session.level_choices()["levels"]] == [257, 129, 65]


@pytest.mark.parametrize("stated", [33, 129, 258, "257", 257.0, True, None])
def test_a_stated_grid_that_is_not_the_rules_is_refused(bundle, stated):
    manifest = _stating(_manifest(bundle))
    manifest["tiles"]["detail"]["levels"][1]["resolution"] = stated
    if stated is None:  # null: no statement, the older rule
        assert plan_level(manifest, 1).resolution == 17
        return
    with pytest.raises(ManifestError, match=r"tiles\.detail\.levels\[1\]\.resolution is "
                       r".*level 1 is drawn on 257 vertices per side \(m = 4"):
        plan_level(manifest, 1)
    with pytest.raises(ManifestError, match=r"levels\[1\]\.resolution"):
        WorkerSession().read_manifest(json.dumps(manifest))


def test_a_levels_regions_side_by_side_are_its_whole_mesh(bundle):
    """The viewer's regions at a level-1 node, on the plan's region grid (129), hold the
    vertices of the level-1 PLY's grid (257) over their rectangles: the same points, as
    ``tessellate_bundle`` draws the whole level (float32 positions, scan frame). But for
    the lines ``u = 1/2`` and ``v = 1/2`` two regions share: this fixture's tiles are
    random per tile, so they disagree there (a fitted pyramid's tiles hold one field)."""
    manifest = _stating(_manifest(bundle))
    session = WorkerSession()
    session.load_patch((bundle / "base.tsp").read_bytes(), bundle.name)
    session.read_manifest(json.dumps(manifest))
    plan = plan_level(manifest, 1)
    whole = tessellate_bundle(manifest, lambda n: (bundle / n).read_bytes(), level=1,
                              resolution=plan.resolution, kernel="numpy")
    r = plan.resolution
    xyz = np.frombuffer(whole.positions, np.float32).reshape(r, r, 3)
    nodes = {(n["level"], n["i"], n["j"]): n["file"] for n in manifest["tiles"]["detail"]["nodes"]}
    differ = []
    for (i, j) in [(0, 0), (1, 0), (0, 1), (1, 1)]:
        names = [nodes[0, 0, 0], nodes[1, i, j]]
        for name in names:
            session.add_tile(name, (bundle / name).read_bytes())
        g = plan.region_resolution
        mesh = session.region_mesh(1, i, j, g, names, 0.05)
        region = np.frombuffer(mesh.positions, np.float32)[: 3 * g * g].reshape(g, g, 3)
        block = xyz[i * (g - 1): i * (g - 1) + g, j * (g - 1): j * (g - 1) + g]
        rows = slice(1, None) if i else slice(None, -1)  # leave out u = 1/2
        cols = slice(1, None) if j else slice(None, -1)  # and v = 1/2
        np.testing.assert_allclose(region[rows, cols], block[rows, cols], rtol=0, atol=2e-4)
        differ.append(np.abs(region - block).max() > 1e-3)
    assert any(differ)  # the shared lines do differ here: the reference can tell


@pytest.mark.parametrize(("change", "match"), [
    (lambda m: m, r"level must be an integer in -1\.\.2 .* got 3"),
    (lambda m: m["tiles"]["detail"].update(spans_per_tile=0),
     r"spans_per_tile must be a positive integer, got 0"),
    (lambda m: m["tiles"]["detail"]["nodes"][0].pop("file"), r"tiles\.detail node .* file"),
    (lambda m: m["tiles"]["texture"]["nodes"][0].update(level=-1),
     r"tiles\.texture node .* integer level"),
])
def test_a_bad_level_or_manifest_is_refused(bundle, change, match):
    manifest = _manifest(bundle)
    change(manifest)
    with pytest.raises(ValueError, match=match):
        plan_level(manifest, 3 if match.startswith("level") else 1)


# --- skirts ----------------------------------------------------------------------------------

def _skirt_reference(surface, tiles, us, vs, depth):
    """Per border vertex, without the kernels: base point S and unit normal n (scipy-free
    NurbsSurface.evaluate/normal), and the partial sums P_l from DetailTile.evaluate."""
    (a0, a1), (b0, b1) = surface.domain
    out = []
    for u, v in zip(us, vs, strict=True):
        s = np.array(surface.evaluate(a0 + (a1 - a0) * u, b0 + (b1 - b0) * v))
        n = np.array(surface.normal(a0 + (a1 - a0) * u, b0 + (b1 - b0) * v))
        partial = np.cumsum([t.evaluate(u, v) for t in sorted(tiles, key=lambda t: t.level)])
        top = partial[-1] if len(partial) else 0.0
        bottom = min(0.0, partial.min() if len(partial) else 0.0) - depth
        out.append((s, n, top, bottom))
    return out


def _region_tiles(level, i, j, seed=1):
    rng = np.random.default_rng(seed)
    return [_detail_tile(rng, k, i >> (level - k), j >> (level - k)) for k in range(level + 1)]


@pytest.mark.parametrize(("node", "sides"), [((2, 1, 2), "u0 u1 v0 v1"), ((1, 0, 0), "u1 v1"),
                                             ((2, 3, 1), "u0 v0 v1"), ((0, 0, 0), "")])
def test_skirts_hang_from_inner_borders_and_never_rise_above_them(node, sides):
    surface, n, depth = _base_patch(), 9, 0.05
    surface = NurbsSurface(surface.degree, surface.knots, surface.control_points,
                           surface.weights)  # no trim here: every segment has its wall
    tiles = _region_tiles(*node)
    rect = tile_rect(*node)
    plain = tessellate_region(surface, rect, n, n, tiles)
    count, triangles = plain.vertex_count, plain.triangle_count
    mesh = hang_skirts(tessellate_region(surface, rect, n, n, tiles), surface, rect, n, tiles,
                       depth)
    sides = sides.split()
    assert mesh.vertex_count == count + 2 * n * len(sides)
    assert mesh.triangle_count == triangles + 2 * (n - 1) * len(sides)
    assert mesh.positions[: 3 * count] == plain.positions  # the grid unchanged
    walls = np.array(mesh.positions[3 * count :]).reshape(-1, 2, 3)  # (bottom, top) pairs
    uvs = np.array(mesh.uvs[2 * count :]).reshape(-1, 2, 2)[:, 0]
    # one run of n border vertices per side, each on its border line, none on the domain's edge
    u0, v0, u1, v1 = rect
    lines = {"u0": (0, u0), "u1": (0, u1), "v0": (1, v0), "v1": (1, v1)}
    found = []
    for run in uvs.reshape(-1, n, 2):
        on = [name for name, (axis, at) in lines.items() if np.all(run[:, axis] == at)]
        assert len(on) == 1, run
        found += on
    assert sorted(found) == sorted(sides)
    assert all(lines[name][1] not in (0.0, 1.0) for name in found)
    grid = np.array(plain.positions).reshape(-1, 3)
    reference = _skirt_reference(surface, tiles, uvs[:, 0], uvs[:, 1], depth)
    for (bottom, top), (s, nrm, p_top, p_bottom) in zip(walls, reference, strict=True):
        # the top is the region's own edge S + P_k n, the bottom S + (min_l P_l - depth) n
        scale = 4 * np.finfo(np.float32).eps * max(1.0, np.abs(s).max())
        assert np.abs(top - (s + p_top * nrm)).max() <= scale
        assert np.abs(bottom - (s + p_bottom * nrm)).max() <= scale
        # never above the edge: along n the wall runs down from its top by at least depth
        assert np.dot(top - bottom, nrm) >= depth - scale
        assert np.min(np.abs(grid - top).max(axis=1)) <= scale  # the top is a grid vertex


def test_no_skirt_on_the_domain_edge_and_none_over_trimmed_cells():
    surface, n, depth = _base_patch(), 9, 0.05  # trim: rows 3..7 x columns 5..7 cut away
    trim = np.array([[surface.trim.covers((r + 0.5) / 8, (c + 0.5) / 8) for c in range(8)]
                     for r in range(8)])
    node = (1, 1, 1)  # borders u0 = 0.5 and v0 = 0.5 are inner; u1 = v1 = 1 the domain's
    tiles = _region_tiles(*node)
    rect = tile_rect(*node)
    plain = tessellate_region(surface, rect, n, n, tiles)
    mesh = hang_skirts(tessellate_region(surface, rect, n, n, tiles), surface, rect, n, tiles,
                       depth)
    count = plain.vertex_count
    uvs = np.array(mesh.uvs[2 * count :]).reshape(-1, 2)
    assert len(uvs) == 2 * 2 * n  # two sides, bottom and top per border vertex
    assert np.all((uvs[:, 0] == 0.5) | (uvs[:, 1] == 0.5))
    # walls only where the inward cell is drawn: cell centres beside u0 = 0.5 and v0 = 0.5
    h = 0.5 * 0.5 / (n - 1)
    steps = 0.5 + 0.5 * np.arange(n - 1) / (n - 1)
    kept = sum(bool(trim[int((0.5 + h) * 8), int((t + h) * 8)]) for t in steps) + \
        sum(bool(trim[int((t + h) * 8), int((0.5 + h) * 8)]) for t in steps)
    assert kept < 2 * (n - 1)  # the trim does take some away
    assert mesh.triangle_count - plain.triangle_count == 2 * kept
    new = np.array(mesh.indices[3 * plain.triangle_count :])
    assert new.min() >= count  # the walls' triangles use the walls' vertices


def test_no_skirt_over_cells_a_walls_mask_leaves_out():
    """A walls mask on the region's finest tile leaving out the cells of its u0 border's
    first half: those segments hang no skirt; the other sides' segments keep theirs."""
    import dataclasses

    surface, n, depth = _base_patch(), 9, 0.05
    surface = NurbsSurface(surface.degree, surface.knots, surface.control_points,
                           surface.weights)  # no trim: only the walls take segments away
    node = (2, 1, 2)  # all four borders inner
    tiles = _region_tiles(*node)
    rect = tile_rect(*node)
    walls = np.zeros((8, 8), bool)
    walls[0, :4] = True  # mask row 0 (along u0), columns 0..3: v in the first half
    tiles[-1] = dataclasses.replace(tiles[-1], walls=TrimMask(walls.tolist()))
    plain = tessellate_region(surface, rect, n, n, tiles)
    mesh = hang_skirts(tessellate_region(surface, rect, n, n, tiles), surface, rect, n, tiles,
                       depth)
    # the grid's 8 x 8 cells are the mask's: cells (0, 0..3) left out, so u0's segments 0..3
    # and v0's segment 0 (its inward cell is (0, 0)) hang nothing
    assert plain.triangle_count == 2 * (64 - 4)
    assert mesh.triangle_count - plain.triangle_count == 2 * (4 * (n - 1) - 5)


def test_skirt_arguments_are_checked():
    surface = _base_patch()
    mesh = tessellate_region(surface, (0, 0, 0.5, 0.5), 5, 5)
    with pytest.raises(ValueError, match=r"depth must be a finite length >= 0, got -1\.0"):
        hang_skirts(mesh, surface, (0, 0, 0.5, 0.5), 5, [], -1.0)
    with pytest.raises(ValueError, match=r"mesh has 25 vertices; an 6x6 grid has 36"):
        hang_skirts(mesh, surface, (0, 0, 0.5, 0.5), 6, [], 0.1)


# --- the session -----------------------------------------------------------------------------

def test_load_patch_gives_the_page_its_facts(bundle):
    session = WorkerSession()
    info = session.load_patch(memoryview((bundle / "base.tsp").read_bytes()), "base.tsp")
    patch = read_patch((bundle / "base.tsp").read_bytes())
    assert info["degree"] == [2, 2] and info["shape"] == [6, 5] and info["rational"] is True
    assert info["domain"] == [0.0, 2.0, -1.0, 1.0] and info["trimmed"] is True
    assert info["units"] == "mm"
    lo, hi = patch.to_scan_frame().bounding_box()
    assert info["bbox"] == [list(lo), list(hi)]
    with pytest.raises(PatchFormatError, match="magic"):
        session.load_patch(b"not a patch at all, not at all", "x.tsp")
    with pytest.raises(RuntimeError, match="no patch is loaded"):
        WorkerSession().tessellate_base(8)
    with pytest.raises(ValueError, match="kernel must be 'python' or 'numpy'"):
        WorkerSession("fortran")


def test_region_mesh_is_tessellate_region_plus_skirts_in_the_scan_frame(bundle):
    session = _session(bundle)
    manifest = _manifest(bundle)
    names = [n["file"] for n in manifest["tiles"]["detail"]["nodes"]
             if (n["level"], n["i"], n["j"]) in {(0, 0, 0), (1, 0, 1), (2, 1, 2)}]
    for name in names:
        node = next(n for n in manifest["tiles"]["detail"]["nodes"] if n["file"] == name)
        assert session.add_tile(name, (bundle / name).read_bytes()) == \
            [node["level"], node["i"], node["j"]]
    mesh = session.region_mesh(2, 1, 2, 9, names, 0.05)
    patch = read_patch((bundle / "base.tsp").read_bytes())
    tiles = [session._tiles[name] for name in names]
    rect = tile_rect(2, 1, 2)
    expected = transform_mesh(hang_skirts(tessellate_region(patch, rect, 9, 9, tiles), patch,
                                          rect, 9, tiles, 0.05), TRANSFORM)
    for field in ("positions", "normals", "uvs", "indices"):
        assert getattr(mesh, field) == getattr(expected, field), field
    grid = transform_mesh(tessellate_region(patch, rect, 9, 9, tiles), TRANSFORM)
    assert mesh.positions[: 3 * 81] == grid.positions
    # a tile that does not cover the region, a name never handed over
    with pytest.raises(ValueError, match=r"tile 1/0_1 does not cover region 2/3_0"):
        session.region_mesh(2, 3, 0, 9, names[:2], 0.05)
    session.drop_tiles([names[0], "never/held.tsd"])
    assert not session.holds(names[0]) and session.holds(names[1])
    with pytest.raises(ValueError, match=rf"detail tile {names[0]} was not handed over"):
        session.region_mesh(2, 1, 2, 9, names, 0.05)


def test_base_ply_reuses_the_mesh_on_screen_and_checks_colours(bundle):
    session = _session(bundle, "base.tsp")
    mesh = session.tessellate_base(12)
    rgb = bytes(range(256)) * 2
    ply = session.base_ply(12, memoryview(rgb[: 3 * 144]))
    assert (ply.vertex_count, ply.triangle_count, ply.level) == (144, mesh.triangle_count, -1)
    assert b"comment source base.tsp\ncomment units mm\n" in ply.data
    assert b"property uchar red" in ply.data
    assert session.base_ply(12).data != ply.data
    with pytest.raises(ValueError, match=r"colors has 6 bytes; the 12x12 grid's 144 vertices"):
        session.base_ply(12, b"\x00" * 6)


@pytest.mark.parametrize("level", [0, 1, 2])
def test_level_ply_is_byte_identical_to_tessera_tessellate(bundle, tmp_path, level, capsys):
    """The session (some tiles held, the rest fresh, textures in a shuffled order) writes the
    very bytes `tessera tessellate BUNDLE --level L` writes."""
    out = tmp_path / "cli.ply"
    assert main(["tessellate", str(bundle), "--level", str(level), "-o", str(out)]) == 0
    plan = plan_level(_manifest(bundle), level)
    assert f"level {level}, {plan.resolution**2} vertices" in capsys.readouterr().out

    session = _session(bundle)
    held = plan.detail_files[::2]
    for name in held:
        session.add_tile(name, (bundle / name).read_bytes())
    fresh = {name: memoryview((bundle / name).read_bytes())
             for name in plan.detail_files if name not in held}
    textures = _texture_dicts(bundle, plan.texture_nodes)
    random.Random(level).shuffle(textures)
    ply = session.level_ply(level, fresh, textures)
    assert ply.data == out.read_bytes()
    assert (ply.level, ply.resolution, ply.vertex_count) == (level, plan.resolution,
                                                              plan.resolution**2)
    for name in fresh:
        assert not session.holds(name)  # decoded for this PLY only

    header = ply.data[: ply.data.index(b"end_header")].decode()
    count = len(plan.detail_files)
    assert f"comment source {bundle.name}\ncomment units mm\n" in header
    assert f"comment detail level {level}: base patch + {count} detail tiles of levels " \
           f"0..{level}\n" in header
    assert f"on a {plan.resolution}x{plan.resolution} grid" in header
    levels = ", ".join(str(k) for k in sorted({n["level"] for n in plan.texture_nodes}))
    assert f"comment vertex colours sampled from {len(plan.texture_nodes)} texture tiles of " \
           f"levels {levels}\n" in header
    # the vertices are the bundle at that level (tessellate_bundle), the colours its sampling
    body = np.frombuffer(ply.data[len(header) + len("end_header\n"):][: 27 * ply.vertex_count],
                         np.dtype([("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 3)]))
    reference = tessellate_bundle(_manifest(bundle), lambda name: (bundle / name).read_bytes(),
                                  level, plan.resolution)
    assert np.array_equal(body["p"].ravel(), np.frombuffer(reference.positions, np.float32))
    # a vertex inside tile 1/0_0 (level >= 1) or the level-0 tile carries its tile's blue
    assert body["c"][0, 2] == (80 if level >= 1 else 30)


def test_level_ply_needs_every_tile_and_texture_of_its_plan(bundle):
    session = _session(bundle)
    plan = plan_level(_manifest(bundle), 1)
    textures = _texture_dicts(bundle, plan.texture_nodes)
    fresh = {name: (bundle / name).read_bytes() for name in plan.detail_files}
    lost = plan.detail_files[-1]
    with pytest.raises(ValueError, match=rf"detail tile {lost} was neither handed over nor sent"):
        session.level_ply(1, {k: v for k, v in fresh.items() if k != lost}, textures)
    extra = plan_level(_manifest(bundle), 2).detail_files[-1]
    with pytest.raises(ValueError, match=rf"fresh tiles {extra} are not tiles of level 1"):
        session.level_ply(1, {**fresh, extra: (bundle / extra).read_bytes()}, textures)
    with pytest.raises(ValueError, match=r"missing \[1/0_1\], not in the plan \[\]"):
        session.level_ply(1, fresh, [t for t in textures if (t["i"], t["j"]) != (0, 1)
                                     or t["level"] != 1])
    with pytest.raises(PatchFormatError, match=rf"CRC32 mismatch.* \(detail tile {lost}\)"):
        broken = bytearray(fresh[lost])
        broken[20] ^= 0xFF
        session.level_ply(1, {**fresh, lost: bytes(broken)}, textures)
    with pytest.raises(ValueError, match=r"level must be an integer in -1\.\.2"):
        session.level_ply(5, fresh, textures)
    with pytest.raises(RuntimeError, match="no manifest"):
        fresh_session = WorkerSession()
        fresh_session.load_patch((bundle / "base.tsp").read_bytes(), "base.tsp")
        fresh_session.level_choices()


def test_the_worker_javascript_holds_no_python():
    """The browser's Python is client_py.session: no Python source in web/src/*.js strings."""
    python = re.compile(r"^\s*(def |from client_py|import client_py)")
    found = [f"{path.name}:{k}: {line.strip()}"
             for path in sorted((PROJECT_ROOT / "web" / "src").glob("*.js"))
             for k, line in enumerate(path.read_text().splitlines(), 1) if python.match(line)]
    assert found == []
    worker = (PROJECT_ROOT / "web" / "src" / "mesh-worker.js").read_text()
    assert 'pyodide.pyimport("client_py.session")' in worker
    assert "runPython" not in worker


# --- the fast region path (issue 14) ---------------------------------------------------------

#: a rigid map to the scan frame, as the fitter writes: a rotation (about an oblique axis) and
#: a shift far from the origin
RIGID = [[0.818328576, 0.537805074, -0.202741324, 249.841619],
         [-0.574725941, 0.762419829, -0.297331628, -40.6558272],
         [-0.00533245283, 0.359835666, 0.933000460, 1201.01985],
         [0.0, 0.0, 0.0, 1.0]]


def _orthonormal(matrix):
    """``matrix`` with its 3x3 part made orthonormal to float64 precision (its polar part)."""
    a = np.array(matrix, dtype=float)
    u, _, vt = np.linalg.svd(a[:3, :3])
    a[:3, :3] = u @ vt
    return a.tolist()


def _random_tiles(rng, node, spans=SPANS):
    """Random tiles for every level of the chain of ``node`` (the region's own included)."""
    level, i, j = node
    return [DetailTile(k, i >> (level - k), j >> (level - k), DEGREE, spans, 2.0**-7,
                       tuple(int(x) for x in rng.integers(-60, 61, (spans + DEGREE) ** 2)))
            for k in range(level + 1)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_region_mesh_on_the_scan_frame_patch_equals_the_reference(seed):
    """With a rigid transform the session makes the region on the scan-frame patch: the same
    mesh as mapping the patch-frame one (the reference path), to float32 rounding, and the
    grid vertices are ``S + sum D_k n`` evaluated point by point (NurbsSurface.evaluate and
    .normal, DetailTile.evaluate: none of the grid kernels)."""
    from client_py.layers import is_rigid_motion

    rng = np.random.default_rng(seed)
    rigid = _orthonormal(RIGID)
    assert is_rigid_motion(rigid) and not is_rigid_motion(TRANSFORM)
    base = _base_patch()
    patch = NurbsSurface(base.degree, base.knots, base.control_points, base.weights,
                         trim=base.trim, metadata={"units": "mm", "transform": rigid})
    session = WorkerSession("python")
    session.load_patch(write_patch(patch), "base.tsp")
    patch = read_patch(write_patch(patch))  # as the session holds it (quantised)
    level = 2
    node = (level, int(rng.integers(0, 4)), int(rng.integers(0, 4)))
    tiles = _random_tiles(rng, node)
    names = []
    for tile in tiles:
        name = f"detail/{tile.level}/{tile.i}_{tile.j}.tsd"
        session.add_tile(name, write_detail_tile(tile))
        names.append(name)
    tiles = [session._tiles[name] for name in names]
    n, depth = 9, 0.05
    mesh = session.region_mesh(*node, n, names, depth)
    rect = tile_rect(*node)
    reference = transform_mesh(hang_skirts(tessellate_region(patch, rect, n, n, tiles), patch,
                                           rect, n, tiles, depth), rigid)
    assert mesh.vertex_count == reference.vertex_count
    assert mesh.indices == reference.indices and mesh.uvs == reference.uvs
    positions = np.array(mesh.positions).reshape(-1, 3)
    expected = np.array(reference.positions).reshape(-1, 3)
    scale = np.abs(expected).max()
    assert np.abs(positions - expected).max() <= 1e-6 * scale
    normals = np.array(mesh.normals).reshape(-1, 3)
    assert np.abs(normals - np.array(reference.normals).reshape(-1, 3)).max() <= 1e-6
    # the grid vertices, point by point, in the scan frame
    (a0, a1), (b0, b1) = patch.domain
    a = np.array(rigid)
    for k, (s, t) in enumerate(np.array(mesh.uvs[: 2 * n * n]).reshape(-1, 2)):
        s, t = float(np.float32(s)), float(np.float32(t))
        u0, v0, u1, v1 = rect
        s = min(max(s, u0), u1)
        t = min(max(t, v0), v1)
        u, v = a0 + (a1 - a0) * s, b0 + (b1 - b0) * t
        shift = sum(tile.evaluate(s, t) for tile in tiles)
        point = np.array(patch.evaluate(u, v)) + shift * np.array(patch.normal(u, v))
        point = a[:3, :3] @ point + a[:3, 3]
        assert np.abs(positions[k] - point).max() <= 1e-5 * scale, k


def test_skirts_from_the_samples_equal_skirts_evaluated_again():
    """hang_skirts given the region's samples (as the session passes them) makes the same
    walls, bit for bit, as evaluating the base and the tiles along the borders afresh."""
    from client_py.layers import mesh_of_region, sample_region

    rng = np.random.default_rng(5)
    surface = _base_patch()
    for node in [(2, 1, 2), (1, 0, 1), (2, 3, 0)]:
        tiles = _random_tiles(rng, node)
        rect = tile_rect(*node)
        samples = sample_region(surface, rect, 9, 9, tiles)
        fast = hang_skirts(mesh_of_region(surface, samples, tiles), surface, rect, 9, tiles,
                           0.05, samples=samples)
        slow = hang_skirts(tessellate_region(surface, rect, 9, 9, tiles), surface, rect, 9,
                           tiles, 0.05)
        for field in ("positions", "normals", "uvs", "indices"):
            assert getattr(fast, field) == getattr(slow, field), (node, field)
    with pytest.raises(ValueError, match=r"samples are of a 9x9 grid over .* not of the 5x5"):
        hang_skirts(tessellate_region(surface, rect, 5, 5, tiles), surface, rect, 5, tiles,
                    0.05, samples=samples)


# ------------------------------------------------------------------ an atlas drawn by group
def _corners(mesh, name="positions", width=3):
    """Per triangle corner, the vertex's float32 values (bytes to compare bit for bit)."""
    values = np.frombuffer(getattr(mesh, name), np.float32).reshape(-1, width)
    return values[np.asarray(mesh.indices, np.int64)].tobytes()


def test_atlas_part_mesh_is_its_group_s_share_of_the_welded_mesh(tmp_path):
    """atlas_part_meshes(groups, levels): each group's triangles of atlas_mesh(levels), bit
    for bit, made together or apart (so every group's together are the welded mesh, at the
    base and with detail), from the packs of the group and its neighbours (the groups
    around it on the layout); a change of a group that is no neighbour changes nothing of
    it."""
    from atlas_bundle import write_atlas_bundle

    folder = tmp_path / "sphere"
    write_atlas_bundle(folder, k=2, levels=2, base_resolution=5)
    session = WorkerSession(kernel="python")
    session.load_atlas((folder / "base.tsa").read_bytes(), "base.tsa")
    session.read_manifest((folder / "manifest.json").read_text())
    groups = session.atlas_refinement()["groups"]
    assert len(groups) == 6
    # a cube face per group: each touches the four faces around it, not the opposite one
    assert all(len(g["neighbours"]) == 4 for g in groups)
    opposite = ({0, 1, 3, 4, 5} - set(groups[2]["neighbours"])).pop()
    neighbour = groups[2]["neighbours"][0]

    def parts(levels, together=False):
        meshes = session.atlas_part_meshes([5, 0, 1, 2, 3, 4], levels) if together else \
            [session.atlas_part_meshes([g], levels)[0] for g in range(6)]
        if together:
            meshes = meshes[1:] + meshes[:1]
        return b"".join(map(_corners, meshes))

    def one(g, levels):
        return session.atlas_part_meshes([g], levels)[0]

    base = [-1] * 6
    assert parts(base) == parts(base, together=True) == _corners(session.atlas_mesh(base))
    assert session.atlas_part_meshes([], base) == []
    levels = list(base)
    levels[2] = levels[neighbour] = 1
    with pytest.raises(ValueError, match=f"needs pack detail/0/{min(2, neighbour)}.tsdp"):
        one(2, levels)
    for name in groups[2]["packs"]:
        session.add_pack(name, (folder / name).read_bytes())
    with pytest.raises(ValueError, match=f"group {neighbour} at level 1 needs pack"):
        one(2, levels)  # the neighbour's detail moves the seam
    for name in groups[neighbour]["packs"]:
        session.add_pack(name, (folder / name).read_bytes())
    assert parts(levels) == parts(levels, together=True) == _corners(session.atlas_mesh(levels))
    mine = one(2, levels)
    far = list(levels)
    far[opposite] = 1  # its packs are not even held: group 2 does not need them
    assert _corners(one(2, far)) == _corners(mine)
    assert _corners(one(2, base)) != _corners(mine)

    for groups, levels, match in (([6], base, "group 6"), ([0], [2] + base[1:], r"levels\[0\] = 2"),
                                  ([True], base, "group True"), ([0], base[1:], "5 values"),
                                  ([1, 1], base, "twice")):
        with pytest.raises(ValueError, match=match):
            session.atlas_part_meshes(groups, levels)


def test_the_atlas_error_map_colours_every_mesh_per_vertex_from_its_raster(tmp_path):
    """set_error_map: the welded mesh and a group's mesh take each vertex's colour from the
    error raster's cells (a grey palette: the colour is the code, bilinear between cell
    centres, clamped at the patch's edge; reference: scipy's interpolator), the uncovered
    patch the palette's colour of no point; turned off, the meshes lose it again."""
    import zlib

    from atlas_bundle import ERROR_RASTER_SIDE, write_atlas_bundle
    from scipy.interpolate import RegularGridInterpolator

    folder = tmp_path / "sphere"
    manifest = write_atlas_bundle(folder, k=2, levels=1, base_resolution=5)
    session = WorkerSession(kernel="python")
    session.load_atlas((folder / "base.tsa").read_bytes(), "base.tsa")
    session.read_manifest((folder / "manifest.json").read_text())
    data = (folder / "error_raster.bin").read_bytes()
    palette = bytes(c for k in range(256) for c in ((k, k, k) if k < 255 else (150, 128, 170)))
    with pytest.raises(ValueError, match="palette has 3 bytes"):
        session.set_error_map(data, b"abc")
    with pytest.raises(ValueError, match="not zlib data"):
        session.set_error_map(b"nonsense", palette)
    assert session.set_error_map(data, palette) == {"patches": 24, "rows": ERROR_RASTER_SIDE}
    side = ERROR_RASTER_SIDE
    codes = np.frombuffer(zlib.decompress(data), np.uint8).reshape(-1, side, side)
    centres = (np.arange(side) + 0.5) / side

    def check(mesh):
        patch = np.asarray(mesh.patches)
        uv = np.clip(np.asarray(mesh.uvs, float).reshape(-1, 2), centres[0], centres[-1])
        rgb = np.asarray(mesh.colors).reshape(-1, 3)
        hole = patch == 0
        assert (rgb[hole] == (150, 128, 170)).all()
        for f in set(patch[~hole].tolist()):
            at = patch == f
            expected = RegularGridInterpolator((centres, centres), codes[f].astype(float))(uv[at])
            assert np.abs(rgb[at, 0] - expected).max() <= 0.5 + 1e-9
        return rgb

    welded = session.atlas_mesh([-1] * 6)
    check(welded)
    assert 0 in welded.patches  # the uncovered patch was checked
    for part in session.atlas_part_meshes([1, 4], [-1] * 6):
        check(part)
    assert manifest["error_raster"]["max"] == manifest["stats"]["max"]
    session.set_error_map(None)
    assert session.atlas_mesh([-1] * 6).colors is None
