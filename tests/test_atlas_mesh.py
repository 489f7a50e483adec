"""tessellate_atlas: one welded, watertight, consistently oriented mesh of an atlas, for
uniform and mixed resolutions, with and without detail tiles; positions on the reference
evaluator (``patch_surface(f).evaluate``), the two kernels in agreement, one normal per
border vertex, and a PLY that a peer reader (trimesh) reads back."""

from __future__ import annotations

import io
import math
import random
from collections import Counter
from dataclasses import replace

import numpy as np
import pytest
from atlas_cases import sphere_atlas
from test_atlas import random_cube_atlas

from client_py import Mesh
from client_py.atlas import AtlasSurface, atlas_edges
from client_py.atlas_mesh import (
    AtlasMesh,
    PatchGrids,
    atlas_parts,
    atlas_ply,
    patches_without_normal,
    tessellate_atlas,
    tessellate_atlas_parts,
)
from client_py.layers import DetailTile
from client_py.trim import TrimMask

MIXED = [3, 5, 9, 3, 5, 2]  # the cube's six patches: 2, 4 and 8 segments a side


def edge_uses(mesh: Mesh) -> tuple[Counter, Counter]:
    """Triangles per undirected edge, and per directed edge."""
    undirected, directed = Counter(), Counter()
    tris = np.asarray(mesh.indices, dtype=np.int64).reshape(-1, 3)
    for a, b, c in tris.tolist():
        for p, q in ((a, b), (b, c), (c, a)):
            undirected[min(p, q), max(p, q)] += 1
            directed[p, q] += 1
    return undirected, directed


def assert_closed_and_oriented(mesh: Mesh) -> None:
    undirected, directed = edge_uses(mesh)
    assert all(n == 2 for n in undirected.values()), \
        Counter(n for n in undirected.values() if n != 2)
    assert all(n == 1 for n in directed.values())  # each used once in each direction
    assert len(set(mesh.indices)) == mesh.vertex_count  # no stray vertex
    # a closed surface: V - E + F = 2 (the cube layout is a sphere)
    assert mesh.vertex_count - len(undirected) + mesh.triangle_count == 2


def random_tiles(seed: int, levels: int = 2, amplitude: float = 0.05) -> list[DetailTile]:
    rnd = random.Random(seed)
    tiles = []
    for level in range(levels):
        for i in range(1 << level):
            for j in range(1 << level):
                size = 4 + 2
                tiles.append(DetailTile(level, i, j, 2, 4, amplitude / 100,
                                        tuple(rnd.randint(-100, 100) for _ in range(size**2))))
    return tiles


def random_detail(atlas, seed: int = 3) -> dict[int, list[DetailTile]]:
    return {f: random_tiles(seed + f) for f in range(len(atlas.quads))}


@pytest.mark.parametrize("resolution", [2, 3, 9, MIXED, [17, 9, 5, 3, 2, 3]])
@pytest.mark.parametrize("with_detail", [False, True])
def test_the_cube_mesh_is_closed_and_consistently_oriented(resolution, with_detail):
    atlas = random_cube_atlas(3, 2)
    detail = random_detail(atlas) if with_detail else None
    mesh = tessellate_atlas(atlas, resolution, detail, kernel="python")
    assert isinstance(mesh, AtlasMesh) and isinstance(mesh, Mesh)
    assert_closed_and_oriented(mesh)
    assert len(mesh.patches) == mesh.vertex_count
    assert len(mesh.normals) == len(mesh.positions) == 3 * mesh.vertex_count


def test_vertex_count_is_corners_edges_and_interiors_once():
    atlas = random_cube_atlas(3, 2)
    r = 9
    mesh = tessellate_atlas(atlas, r)
    assert mesh.vertex_count == 8 + 12 * (r - 2) + 6 * (r - 2) ** 2
    assert mesh.triangle_count == 6 * 2 * (r - 1) ** 2


@pytest.mark.parametrize("make", [lambda: random_cube_atlas(3, 2), lambda: random_cube_atlas(2, 3),
                                  lambda: random_cube_atlas(1, 1), lambda: sphere_atlas(2)])
def test_positions_are_the_reference_evaluators(make):
    """Every vertex, for every patch that samples it, is patch_surface(f).evaluate(u, v)."""
    atlas = make()
    r = 7
    mesh = tessellate_atlas(atlas, r, kernel="python")
    exact = _positions_in_double(atlas, r, "python")
    for f in range(len(atlas.quads)):
        surface = atlas.patch_surface(f)
        for (i, j), k in _patch_vertex_ids(mesh, atlas, f, r).items():
            point = surface.evaluate(i / (r - 1), j / (r - 1))
            assert max(abs(a - b) for a, b in zip(point, exact[k], strict=True)) < 1e-9
            assert max(abs(a - b) for a, b in zip(point, mesh.positions[3 * k : 3 * k + 3],
                                                  strict=True)) < 1e-6  # float32


def _positions_in_double(atlas, r, kernel):
    """Each vertex's float64 position from the first patch sampling it (the module's
    evaluator and numbering; the mesh itself is float32)."""
    from client_py import atlas_mesh

    captured = {}
    comps = atlas_mesh._homogeneous(atlas)
    tol = atlas_mesh._normal_tolerance(comps)
    evaluate = atlas_mesh._evaluate_python if kernel == "python" else atlas_mesh._evaluate_numpy
    grids = evaluate(atlas, comps, list(range(len(atlas.quads))), r, tol)
    layout = atlas_mesh._Layout(atlas, [r] * len(atlas.quads))
    for f, (pos, _, _) in grids.items():
        ids, _ = layout.patch_vertices(f)
        for slot, k in enumerate(ids):
            captured.setdefault(k, tuple(pos[3 * slot : 3 * slot + 3]))
    return captured


def _patch_vertex_ids(mesh, atlas, f, r):
    from client_py import atlas_mesh

    layout = atlas_mesh._Layout(atlas, [r] * len(atlas.quads))
    ids, _ = layout.patch_vertices(f)
    return {(slot // r, slot % r): k for slot, k in enumerate(ids)}


def test_border_vertices_are_one_vertex_for_both_patches_with_the_same_point():
    """The neighbours' own evaluations of a shared border sample agree (one curve), and the
    welded vertex is it: the edge's lo->hi order read reversed by the other side."""
    atlas = random_cube_atlas(3, 2, seed=5)
    r = 6
    mesh = tessellate_atlas(atlas, r)
    seen: dict[int, list] = {}
    for f in range(6):
        surface = atlas.patch_surface(f)
        for (i, j), k in _patch_vertex_ids(mesh, atlas, f, r).items():
            if i in (0, r - 1) or j in (0, r - 1):
                seen.setdefault(k, []).append(surface.evaluate(i / (r - 1), j / (r - 1)))
    assert len(seen) == 8 + 12 * (r - 2)
    for k, points in seen.items():
        assert len(points) == (3 if k < 8 else 2)
        for point in points[1:]:
            assert max(abs(a - b) for a, b in zip(point, points[0], strict=True)) < 1e-12


@pytest.mark.parametrize("resolution", [9, MIXED])
@pytest.mark.parametrize("with_detail", [False, True])
def test_python_and_numpy_kernels_agree(resolution, with_detail):
    pytest.importorskip("numpy")
    atlas = random_cube_atlas(3, 2)
    detail = random_detail(atlas) if with_detail else None
    a = tessellate_atlas(atlas, resolution, detail, kernel="python")
    b = tessellate_atlas(atlas, resolution, detail, kernel="numpy")
    assert a.indices == b.indices and a.patches == b.patches
    for name in ("positions", "normals", "uvs"):
        diff = np.abs(np.asarray(getattr(a, name)) - np.asarray(getattr(b, name)))
        assert diff.max() < 1e-6, name


def test_normals_are_unit_outward_and_one_per_border_vertex():
    """On the sphere atlas the welded normals are the sphere's (outward, C_u x C_v), and the
    mesh holds one normal per vertex: a border vertex has no second copy to disagree."""
    atlas = sphere_atlas(2)
    mesh = tessellate_atlas(atlas, 9)
    P = np.asarray(mesh.positions).reshape(-1, 3)
    N = np.asarray(mesh.normals).reshape(-1, 3)
    assert np.allclose(np.linalg.norm(N, axis=1), 1.0, atol=1e-6)
    radial = P / np.linalg.norm(P, axis=1)[:, None]
    assert (np.sum(N * radial, axis=1) > 0.95).all()
    # positions are unique: no border vertex was emitted twice
    assert len({tuple(p) for p in P.round(7).tolist()}) == len(P)


def test_border_normal_is_the_mean_of_the_patches_normals():
    atlas = random_cube_atlas(3, 2, seed=2)
    r = 5
    mesh = tessellate_atlas(atlas, r)
    table = atlas.edges
    for e, ((f, k), (g, m)) in enumerate(table.faces):
        lo, _ = table.edges[e]
        k_id = _patch_vertex_ids(mesh, atlas, f, r)
        # sample t = 2 (the middle) of side k of f
        ij = ((2, 0), (r - 1, 2), (2, r - 1), (0, 2))[k]
        vertex = k_id[ij]
        u, v = ij[0] / (r - 1), ij[1] / (r - 1)
        nf = np.array(atlas.patch_surface(f).normal(u, v))
        ij_g = ((2, 0), (r - 1, 2), (2, r - 1), (0, 2))[m]  # the middle is the middle
        ng = np.array(atlas.patch_surface(g).normal(ij_g[0] / (r - 1), ij_g[1] / (r - 1)))
        assert _patch_vertex_ids(mesh, atlas, g, r)[ij_g] == vertex
        mean = (nf + ng) / np.linalg.norm(nf + ng)
        assert np.allclose(mesh.normals[3 * vertex : 3 * vertex + 3], mean, atol=1e-6)


def test_detail_moves_border_vertices_by_the_mean_displacement():
    """A tile on one patch only: a shared border vertex moves by half its displacement
    along the mean normal; an interior vertex by the whole of it."""
    atlas = random_cube_atlas(3, 2, seed=4)
    r = 5
    tile = DetailTile(0, 0, 0, 1, 1, 0.5, (2, 2, 2, 2))  # D = 1 everywhere
    base = tessellate_atlas(atlas, r)
    moved = tessellate_atlas(atlas, r, {0: [tile]})
    ids = _patch_vertex_ids(base, atlas, 0, r)
    P0 = np.asarray(base.positions).reshape(-1, 3)
    P1 = np.asarray(moved.positions).reshape(-1, 3)
    s0 = atlas.patch_surface(0)
    inner = ids[(2, 2)]
    assert np.allclose(P1[inner] - P0[inner], s0.normal(0.5, 0.5), atol=1e-6)
    edge = ids[(2, 0)]  # side 0 of patch 0: shared with one neighbour
    (e, _) = atlas.edges.sides[0][0]
    (g, m) = next(pair for pair in atlas.edges.faces[e] if pair[0] != 0)
    ij_g = ((2, 0), (r - 1, 2), (2, r - 1), (0, 2))[m]
    ng = np.array(atlas.patch_surface(g).normal(ij_g[0] / (r - 1), ij_g[1] / (r - 1)))
    mean = np.array(s0.normal(0.5, 0.0)) + ng
    mean /= np.linalg.norm(mean)
    assert np.allclose(P1[edge] - P0[edge], 0.5 * mean, atol=1e-6)


def test_mixed_resolution_border_vertices_lie_on_the_coarse_segment():
    atlas = sphere_atlas(1)
    mesh = tessellate_atlas(atlas, MIXED)
    P = np.asarray(mesh.positions, dtype=float).reshape(-1, 3)
    # every vertex is on a triangle of positive area: no T-gap leaves a sliver unfilled
    tris = np.asarray(mesh.indices).reshape(-1, 3)
    area = 0.5 * np.linalg.norm(np.cross(P[tris[:, 1]] - P[tris[:, 0]],
                                         P[tris[:, 2]] - P[tris[:, 0]]), axis=1)
    assert area.min() > 0
    # the surface encloses the sphere's volume nearly (closed: the divergence theorem)
    volume = np.einsum("ij,ij->i", P[tris[:, 0]], np.cross(P[tris[:, 1]], P[tris[:, 2]])).sum() / 6
    assert 0.6 * 4 / 3 * math.pi < volume < 4 / 3 * math.pi


def test_bad_arguments_are_named():
    atlas = random_cube_atlas()
    with pytest.raises(ValueError, match="atlas must be an AtlasSurface"):
        tessellate_atlas({}, 3)
    with pytest.raises(ValueError, match="resolution of patch 0 = 1; an int in 2..8192"):
        tessellate_atlas(atlas, 1)
    with pytest.raises(ValueError, match="resolution has 2 values; the atlas has 6 patches"):
        tessellate_atlas(atlas, [3, 3])
    with pytest.raises(ValueError, match="resolution must be an int or a sequence"):
        tessellate_atlas(atlas, 3.0)
    with pytest.raises(ValueError, match="neighbours need 2\\^k c \\+ 1 samples"):
        tessellate_atlas(atlas, [3, 4, 3, 3, 3, 3])
    with pytest.raises(ValueError, match="at most 16777216 are accepted"):
        tessellate_atlas(atlas, 8000)
    with pytest.raises(ValueError, match="detail key 6 is no patch index"):
        tessellate_atlas(atlas, 3, {6: []})
    with pytest.raises(ValueError, match="detail\\[0\\] holds a int, not a DetailTile"):
        tessellate_atlas(atlas, 3, {0: [1]})
    with pytest.raises(ValueError, match="kernel must be 'python' or 'numpy'"):
        tessellate_atlas(atlas, 3, kernel="gpu")


def test_atlas_ply_is_read_by_trimesh_as_one_closed_mesh():
    trimesh = pytest.importorskip("trimesh")
    atlas = sphere_atlas(2)
    data = atlas_ply(atlas, MIXED * 4, comments=["atlas test"])
    header = data[: data.index(b"end_header")].decode()
    for line in ("property float x", "property float nx", "property float nz"):
        assert line in header
    mesh = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    ours = tessellate_atlas(atlas, MIXED * 4)
    assert len(mesh.vertices) == ours.vertex_count and len(mesh.faces) == ours.triangle_count
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward: counter-clockwise seen from outside


def test_a_two_sample_patch_between_finer_neighbours_gets_a_centre_vertex():
    """Patch 0 at r = 2 with all four neighbours at r = 3: no corner of its one cell is free
    of extra border vertices, so the fan runs from its centre, C_0(1/2, 1/2)."""
    atlas = random_cube_atlas(3, 2, seed=6)
    for detail in (None, random_detail(atlas)):
        mesh = tessellate_atlas(atlas, [2, 3, 3, 3, 3, 3], detail)
        assert_closed_and_oriented(mesh)
        uniform = 8 + 12 * 1 + 5 * 1  # corners, one sample per edge, 5 patch interiors
        assert mesh.vertex_count == uniform + 1
        centre = mesh.vertex_count - 1
        assert mesh.patches[centre] == 0 and tuple(mesh.uvs[2 * centre :]) == (0.5, 0.5)
        if detail is None:
            point = atlas.patch_surface(0).evaluate(0.5, 0.5)
            assert np.allclose(mesh.positions[3 * centre :], point, atol=1e-6)


def open_cube_atlas(seed: int = 7) -> AtlasSurface:
    """:func:`random_cube_atlas` without its second face (z = 1): an open layout, 4 border
    edges."""
    full = random_cube_atlas(3, 2, seed=seed)
    quads = full.quads[:1] + full.quads[2:]  # drop the z = 1 face
    inner = full.side - 2
    edges = full.edges.edges
    table = atlas_edges(quads)
    index = {edge: e for e, edge in enumerate(edges)}
    edge_points = [p for edge in table.edges
                   for p in full.edge_points[index[edge] * inner : (index[edge] + 1) * inner]]
    face_points = full.face_points[: inner * inner] + full.face_points[2 * inner * inner :]
    return AtlasSurface(3, 2, full.vertices, quads, edge_points, face_points)


def test_an_open_layout_has_exactly_its_border_as_boundary():
    """The cube without its top: the 4 border edges' samples are the only boundary."""
    atlas = open_cube_atlas()
    assert len(atlas.edges.border_edges) == 4
    r = 6
    for resolution in (r, [9, 5, 3, 5, 9]):
        mesh = tessellate_atlas(atlas, resolution)
        undirected, directed = edge_uses(mesh)
        boundary = [edge for edge, n in undirected.items() if n == 1]
        assert all(n in (1, 2) for n in undirected.values())
        assert all(n == 1 for n in directed.values())
        expected = sum(resolution[f] - 1 if isinstance(resolution, list) else r - 1
                       for f, _ in (atlas.edges.faces[e][0] for e in atlas.edges.border_edges))
        assert len(boundary) == expected


def pole_cube_atlas() -> AtlasSurface:
    """:func:`random_cube_atlas` with edge 0's first inner control point on its ``lo`` corner:
    ``C_t = 0`` there along the edge, so the two patches on it have no ``C_u x C_v`` at that
    corner (a pole: the limit normal from inside the patch is drawn)."""
    cube = random_cube_atlas(3, 2, seed=6)
    edge_points = list(cube.edge_points)
    edge_points[0] = cube.vertices[cube.edges.edges[0][0]]
    return AtlasSurface(3, 2, cube.vertices, cube.quads, edge_points, cube.face_points,
                        cube.weights)


def _weld_cases():
    """(atlas, resolution, detail) with open borders, detail on some patches, poles, rational
    weights, mixed resolutions and a 2-sample patch between finer neighbours."""
    cube, open_cube = random_cube_atlas(3, 2, seed=6), open_cube_atlas()
    sphere = sphere_atlas(2, noise=0.02, seed=4, rational=True)
    pole = pole_cube_atlas()
    some = {f: random_tiles(f, levels=2, amplitude=0.2) for f in range(0, 24, 3)}
    return [(cube, 9, None), (cube, MIXED, random_detail(cube)),
            (cube, [2, 3, 3, 3, 3, 3], random_detail(cube)), (cube, [2, 3, 3, 3, 3, 3], None),
            (open_cube, 6, None), (open_cube, [9, 5, 3, 5, 9], random_detail(open_cube)),
            (open_cube, [9, 5, 3, 5, 9], {1: random_tiles(1)}),
            (sphere, [5, 9, 17] * 8, some), (sphere, 2, None), (sphere, 17, some),
            (pole, 5, None), (pole, [5, 9, 5, 3, 5, 5], random_detail(pole))]


@pytest.mark.parametrize("case", range(12))
def test_the_numpy_weld_gives_the_bytes_of_the_pure_python_weld(case):
    """The whole mesh welded by the numpy kernel (``_kernel_numpy.weld_atlas``) and by the
    pure-Python weld from the same evaluated grids: the same positions, normals, ``(u, v)``,
    triangles and patches, byte for byte."""
    pytest.importorskip("numpy")
    from client_py.atlas_mesh import _check_detail, _check_resolutions, _welded_mesh

    atlas, resolution, detail = _weld_cases()[case]
    res, tiles = _check_resolutions(atlas, resolution), _check_detail(atlas, detail)
    (fast,) = _welded_mesh(atlas, res, tiles, "numpy")
    (slow,) = _welded_mesh(atlas, res, tiles, "numpy", weld="python")
    assert fast.triangle_count > 0
    for name in ("positions", "normals", "uvs", "indices", "patches"):
        a, b = getattr(fast, name), getattr(slow, name)
        assert a.typecode == b.typecode and a.tobytes() == b.tobytes(), name


@pytest.mark.parametrize("weld", ["numpy", "numpy weld='python'", "python"])
@pytest.mark.parametrize("case", range(12))
def test_a_mesh_without_normals_is_the_drawn_mesh_bit_for_bit(case, weld):
    """``normals=False`` (what the fitter's error stage measures): empty normals, and the
    positions, ``(u, v)``, triangles and patches of the mesh with normals, byte for byte,
    with the numpy weld, the pure-Python weld of numpy grids and the pure-Python kernel."""
    from client_py.atlas_mesh import _check_detail, _check_resolutions, _welded_mesh

    kernel, _, python_weld = weld.partition(" ")
    if kernel == "numpy":
        pytest.importorskip("numpy")
    atlas, resolution, detail = _weld_cases()[case]
    res, tiles = _check_resolutions(atlas, resolution), _check_detail(atlas, detail)
    how = {"weld": "python"} if python_weld else {}
    (full,) = _welded_mesh(atlas, res, tiles, kernel, **how)
    (bare,) = _welded_mesh(atlas, res, tiles, kernel, normals=False, **how)
    assert len(full.normals) == len(full.positions) > 0 and len(bare.normals) == 0
    for name in ("positions", "uvs", "indices", "patches"):
        a, b = getattr(full, name), getattr(bare, name)
        assert a.typecode == b.typecode and a.tobytes() == b.tobytes(), name
    if case == 1:  # the public function passes it on
        mesh = tessellate_atlas(atlas, resolution, detail, kernel=kernel, normals=False)
        assert mesh.positions.tobytes() == full.positions.tobytes() and not mesh.normals


# ------------------------------------------------------------------ walls masks
def walled_tiles(seed: int, levels: int = 2, side: int = 8, share: float = 0.3
                 ) -> list[DetailTile]:
    """:func:`random_tiles` with random walls masks (``side`` cells a side) on about half
    the tiles of each level, the rest without one (a coarser level's then decides)."""
    rnd = random.Random(1000 + seed)
    return [replace(tile, walls=TrimMask.from_flat(
                side, side, bytes(rnd.random() < share for _ in range(side * side))))
            if rnd.random() < 0.5 else tile for tile in random_tiles(seed, levels)]


def _left_out(tiles: list[DetailTile], r: int) -> set[tuple[int, int]]:
    """Reference: the cells ``(i, j)`` of an ``r x r`` grid whose centre the walls mask of
    the finest tile carrying one and holding it covers (docs/format.md, walls masks)."""
    out = set()
    for i in range(r - 1):
        for j in range(r - 1):
            u, v = (i + 0.5) / (r - 1), (j + 0.5) / (r - 1)
            finest = None
            for tile in tiles:
                n = 1 << tile.level
                if tile.walls is not None and (tile.i, tile.j) == (min(int(u * n), n - 1),
                                                                   min(int(v * n), n - 1)):
                    if finest is None or tile.level > finest.level:
                        finest = tile
            if finest is not None:
                n, w = 1 << finest.level, finest.walls.rows
                a = min(int((u * n - finest.i) * w), w - 1)
                b = min(int((v * n - finest.j) * w), w - 1)
                if finest.walls.flat[a * w + b]:
                    out.add((i, j))
    return out


@pytest.mark.parametrize("kernel", ["python", "numpy"])
@pytest.mark.parametrize("r", [5, 9, 17])
def test_walls_masks_leave_out_their_cells_and_nothing_else(kernel, r):
    """With walls masks on the tiles, the welded mesh has the same vertices bit for bit
    and exactly the triangles of the mesh without them less the two of every cell the
    reference (:func:`_left_out`) leaves out; no edge is used by more than two
    triangles, and one used by one borders a left-out cell."""
    if kernel == "numpy":
        pytest.importorskip("numpy")
    atlas = random_cube_atlas(3, 2)
    walled = {f: walled_tiles(f) for f in range(len(atlas.quads))}
    plain = {f: [replace(t, walls=None) for t in tiles] for f, tiles in walled.items()}
    full = tessellate_atlas(atlas, r, plain, kernel=kernel)
    cut = tessellate_atlas(atlas, r, walled, kernel=kernel)
    for name in ("positions", "normals", "uvs", "patches"):
        assert getattr(cut, name).tobytes() == getattr(full, name).tobytes(), name
    cells = (r - 1) ** 2
    tris = np.asarray(full.indices).reshape(len(atlas.quads), cells, 2, 3)
    expected, dropped = [], 0
    for f in range(len(atlas.quads)):
        out = _left_out(walled[f], r)
        dropped += len(out)
        expected += [tris[f, i * (r - 1) + j] for i in range(r - 1) for j in range(r - 1)
                     if (i, j) not in out]
    assert 0 < dropped < len(atlas.quads) * cells
    assert np.array_equal(np.asarray(cut.indices).reshape(-1, 2, 3), np.array(expected))
    undirected, _ = edge_uses(cut)
    assert max(undirected.values()) == 2 and min(undirected.values()) == 1


def test_a_finer_walls_mask_gives_back_what_a_coarser_one_took():
    """Level 0 leaves out every cell; an all-clear level-1 mask on one tile draws that
    quarter again (the finest applied walls mask decides)."""
    atlas = random_cube_atlas(3, 2)
    tiles = random_tiles(0)
    every = TrimMask.from_flat(8, 8, b"\x01" * 64)
    clear = TrimMask.from_flat(8, 8, bytes(64))
    walled = [replace(t, walls=every) if t.level == 0 else
              replace(t, walls=clear) if (t.level, t.i, t.j) == (1, 1, 0) else t for t in tiles]
    mesh = tessellate_atlas(atlas, 9, {0: walled}, kernel="python")
    full = np.asarray(tessellate_atlas(atlas, 9, {0: tiles}, kernel="python").indices)
    cells = full.reshape(6, 8, 8, 6)  # patch, cell row i (u), cell column j (v), triangles
    expected = np.concatenate([cells[0, 4:, :4].reshape(-1), cells[1:].reshape(-1)])
    assert np.array_equal(np.asarray(mesh.indices), expected)


@pytest.mark.parametrize("kernel", ["python", "numpy"])
def test_walled_parts_are_the_walled_welded_mesh_bit_for_bit(kernel):
    """Groups drawn apart at mixed levels with walls masks are the whole welded mesh's
    triangles (the viewer's parts honour the masks as the download does), fans at
    resolution changes included."""
    if kernel == "numpy":
        pytest.importorskip("numpy")
    atlas = sphere_atlas(2, noise=0.02, seed=4)
    groups = _groups_of(atlas, 1)
    rnd = random.Random(3)
    resolution, detail = [], {}
    for group in groups:
        level = rnd.randrange(-1, 2)
        resolution += [(5, 9, 17)[level + 1]] * len(group)
        if level >= 0:
            detail.update({f: walled_tiles(f, levels=level + 1, side=4, share=0.4)
                           for f in group})
    whole = tessellate_atlas(atlas, resolution, detail, kernel=kernel)
    plain = tessellate_atlas(atlas, resolution,
                             {f: [replace(t, walls=None) for t in ts] for f, ts in detail.items()},
                             kernel=kernel)
    assert 0 < whole.triangle_count < plain.triangle_count
    apart = [tessellate_atlas_parts(atlas_parts(atlas, [group]), resolution, detail,
                                    kernel=kernel)[0] for group in groups]
    for name, width in (("positions", 3), ("normals", 3), ("uvs", 2), ("patches", 1)):
        joined = np.concatenate([_drawn(m, name, width) for m in apart])
        assert joined.tobytes() == _drawn(whole, name, width).tobytes(), name


# ------------------------------------------------------------------ one group's share of it
def _groups_of(atlas, seed):
    """A random partition of the patches into runs of 1..7 (the bundle's detail groups)."""
    rnd, groups, first = random.Random(seed), [], 0
    while first < len(atlas.quads):
        count = min(rnd.randint(1, 7), len(atlas.quads) - first)
        groups.append(range(first, first + count))
        first += count
    return groups


def _drawn(mesh, name, width):
    """Per triangle corner, the vertex's ``name`` values, as bytes to compare bit for bit."""
    values = np.frombuffer(getattr(mesh, name), dtype=getattr(mesh, name).typecode)
    values = values.reshape(-1, width)
    return values[np.asarray(mesh.indices, dtype=np.int64)]


@pytest.mark.parametrize("kernel", ["python", "numpy"])
@pytest.mark.parametrize(("rational", "resolutions", "rings"),
                         [(False, (5, 9, 17), 1), (True, (5, 9, 17), 1),
                          (False, (2, 3, 5), 2)])
def test_the_parts_of_a_partition_are_the_welded_mesh_bit_for_bit(kernel, rational,
                                                                 resolutions, rings):
    """Every group's mesh (:func:`tessellate_atlas_parts`, made alone or all together) at a
    random level vector, with detail, concatenated in group order, is
    :func:`tessellate_atlas` of the same arguments: the same triangles with the same float32
    positions, normals, ``(u, v)`` and patches, bit for bit (so two groups' shared seam
    vertices are equal, and the GPU draws no crack)."""
    atlas = sphere_atlas(2, noise=0.02, seed=4, rational=rational)
    kept = PatchGrids()  # grids kept between the parts of both level vectors
    for seed in range(2):
        groups = _groups_of(atlas, seed)
        rnd = random.Random(10 + seed)
        levels = [rnd.randrange(-1, 2) for _ in groups]
        resolution, detail = [], {}
        for group, level in zip(groups, levels, strict=True):
            resolution += [resolutions[level + 1]] * len(group)
            if level >= 0:
                detail.update({f: random_tiles(f, levels=level + 1, amplitude=0.2)
                               for f in group})
        whole = tessellate_atlas(atlas, resolution, detail, kernel=kernel)
        apart = [tessellate_atlas_parts(atlas_parts(atlas, [group], rings), resolution,
                                        detail, kernel=kernel,
                                        cache=kept if g % 2 else None)[0]
                 for g, group in enumerate(groups)]
        order = [*range(1, len(groups), 2), *range(0, len(groups), 2)]  # any order
        made = tessellate_atlas_parts(atlas_parts(atlas, [groups[g] for g in order], rings),
                                      resolution, detail, kernel=kernel)
        together = [made[order.index(g)] for g in range(len(groups))]
        for meshes in (apart, together):
            for name, width in (("positions", 3), ("normals", 3), ("uvs", 2), ("patches", 1)):
                joined = np.concatenate([_drawn(m, name, width) for m in meshes])
                assert joined.tobytes() == _drawn(whole, name, width).tobytes(), name
        for mesh, group in zip(apart, groups, strict=True):
            assert len(set(mesh.indices)) == mesh.vertex_count  # only the vertices it uses
            assert set(mesh.patches) <= set(atlas_parts(atlas, [group]).patches)


def test_a_part_is_its_patches_and_their_vertex_ring():
    atlas = sphere_atlas(2, noise=0.02, seed=4)
    part = atlas_parts(atlas, [[0]])
    ring = {f for f, quad in enumerate(atlas.quads) if set(quad) & set(atlas.quads[0])}
    assert part.patches == tuple(sorted(ring)) and len(ring) == 8  # at a cube corner
    assert [[part.patches[k] for k in group] for group in part.drawn] == [[0]]
    assert len(atlas_parts(atlas, [[0]], rings=2).patches) > len(ring)


def test_a_part_needs_good_arguments():
    atlas = sphere_atlas(2, noise=0.02, seed=4)
    part = atlas_parts(atlas, [range(4)])
    with pytest.raises(ValueError, match="power-of-2"):
        tessellate_atlas_parts(part, [7] + [5] * 23)
    with pytest.raises(ValueError, match="24 patches"):
        tessellate_atlas_parts(part, [5] * 4)
    with pytest.raises(ValueError, match="no patch index"):
        tessellate_atlas_parts(part, 9, {24: random_tiles(1)})
    with pytest.raises(ValueError, match="two rings"):
        tessellate_atlas_parts(part, 2, {0: random_tiles(1)})
    with pytest.raises(ValueError, match="twice"):
        atlas_parts(atlas, [[0], [1, 0]])
    with pytest.raises(ValueError, match="no patch index"):
        atlas_parts(atlas, [[24]])
    with pytest.raises(ValueError, match="at least one patch"):
        atlas_parts(atlas, [[0], []])
    with pytest.raises(ValueError, match="rings"):
        atlas_parts(atlas, [[0]], rings=3)


def test_patch_grids_drop_the_least_recently_used_beyond_their_samples():
    kept = PatchGrids(max_samples=10)
    for k in range(3):
        kept.put(("grid", k, 2), k, 4)
    assert kept.get(("grid", 0, 2)) is None and kept.get(("grid", 2, 2)) == 2
    kept.get(("grid", 1, 2))  # used: 2 is now the oldest
    kept.put(("grid", 3, 2), 3, 4)
    assert kept.get(("grid", 2, 2)) is None and kept.get(("grid", 1, 2)) == 1


@pytest.mark.parametrize("later", [0, 3])
def test_patch_grids_first_kept_is_the_first_put_that_outlives_the_later_ones(later):
    """PatchGrids.first_kept: the puts before it are all dropped by the puts after them
    (and ``later`` samples more), the one at it is held at the end."""
    rng = np.random.default_rng(5)
    for _ in range(50):
        sizes = [int(s) for s in rng.integers(1, 6, rng.integers(1, 12))]
        kept = PatchGrids(max_samples=int(rng.integers(1, 20)))
        first = kept.first_kept(sizes, later)
        for k, size in enumerate(sizes):
            kept.put(("grid", k, 2), k, size)
        if later:
            kept.put(("detail", 0, 2), None, later)
        assert all(not kept.holds(("grid", k, 2)) for k in range(first))
        if first < len(sizes) and sum(sizes[first:]) + later <= kept.max_samples:
            assert all(kept.holds(("grid", k, 2)) for k in range(first, len(sizes)))


@pytest.mark.parametrize("kernel", ["python", "numpy"])
def test_progress_reports_rise_to_the_end_and_change_nothing(kernel):
    """tessellate_atlas(progress=...): one report per PROGRESS_BATCH patches evaluated and
    displaced, rising, within (0, 1]; the mesh is the one made without it."""
    from client_py.atlas_mesh import PROGRESS_BATCH

    atlas = sphere_atlas(6, noise=0.02, seed=1)  # 216 patches: several batches
    reports: list[float] = []
    with_progress = tessellate_atlas(atlas, 5, kernel=kernel, progress=reports.append)
    plain = tessellate_atlas(atlas, 5, kernel=kernel)
    assert list(with_progress.positions) == list(plain.positions)
    assert list(with_progress.indices) == list(plain.indices)
    batches = -(-len(atlas.quads) // PROGRESS_BATCH)
    assert len(reports) == batches + len(atlas.quads) // PROGRESS_BATCH
    assert reports == sorted(reports) and 0 < reports[0] and reports[-1] <= 1
    assert reports[batches - 1] == pytest.approx(0.5) and reports[-1] > 0.9


@pytest.mark.parametrize("kernel", ["python", "numpy"])
def test_a_part_whose_every_cell_is_left_out_is_an_empty_mesh(kernel):
    """A detail group over a part the scan lacks can have every cell walled: the viewer's
    part is then an empty mesh (it raised TypeError from an empty itemgetter), and the
    other parts are drawn as before."""
    if kernel == "numpy":
        pytest.importorskip("numpy")
    atlas = sphere_atlas(2, noise=0.02, seed=4)
    walled = TrimMask.from_flat(4, 4, bytes([1] * 16))
    detail = {0: [replace(t, walls=walled) for t in random_tiles(0, 1)]}
    resolution = [9] * len(atlas.quads)
    rest = range(1, len(atlas.quads))
    empty, other = tessellate_atlas_parts(atlas_parts(atlas, [range(1), rest]), resolution,
                                          detail, kernel=kernel)
    assert empty.triangle_count == 0 and len(empty.patches) == 0
    alone = tessellate_atlas_parts(atlas_parts(atlas, [rest]), resolution, detail,
                                   kernel=kernel)[0]
    assert other.triangle_count == alone.triangle_count > 0


def _refused(atlas, resolution, kernel) -> bool:
    try:
        tessellate_atlas(atlas, resolution, kernel=kernel)
    except ValueError:
        return True
    return False


@pytest.mark.parametrize("kernel", ["python", "numpy"])
def test_patches_without_normal_are_what_the_tessellation_refuses(kernel):
    """Bases that draw (a random cube, a sphere; a pole of the sphere has its normal as a
    limit) give no patch, and a base whose rounding collapsed patches (a tetrahedron 2e-4
    the size of another, written at 8 bits) gives those patches, where the tessellation
    raises (on patches of the small one alone)."""
    from client_py.atlas_format import AtlasWriter
    from fitter.fitting.atlas.layout import bilinear_atlas, quad_layout

    tetra = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    both = bilinear_atlas(quad_layout(np.concatenate([tetra, 0.5 + 2e-4 * tetra]),
                                      np.concatenate([faces, faces + 4])), spans=1)
    collapsed = AtlasWriter(both).decoded(8, 3.0)
    for atlas, resolution in ((random_cube_atlas(3, 2), 9), (sphere_atlas(3, 2, 3), 5),
                              (random_cube_atlas(2, 1), [3, 5, 9, 3, 5, 2]),
                              (AtlasWriter(both).decoded(12, 3.0), 9)):
        assert patches_without_normal(atlas, resolution, kernel) == []
        assert not _refused(atlas, resolution, kernel)
    refused = patches_without_normal(collapsed, 9, kernel)
    assert refused and _refused(collapsed, 9, kernel)
    small = [f for f, quad in enumerate(collapsed.quads)
             if all(abs(c - 0.5) < 0.01 for k in quad for c in collapsed.vertices[k])]
    assert set(refused) <= set(small) and len(small) == 12  # the small one's 4 x 3 quads


def test_the_garbage_collector_comes_back_as_it_was_after_a_failed_mesh():
    """tessellate_atlas pauses the cyclic collector (client_py.gc_pause): a progress callback
    that raises leaves it enabled as it was, and paused when the caller had paused it."""
    import gc

    atlas = sphere_atlas(1)

    def stop(share):
        raise RuntimeError("stop")

    for enabled in (True, False):
        (gc.enable if enabled else gc.disable)()
        try:
            with pytest.raises(RuntimeError, match="stop"):
                tessellate_atlas(atlas, 5, progress=stop)
            assert gc.isenabled() is enabled
        finally:
            gc.enable()
