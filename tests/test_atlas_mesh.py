"""tessellate_atlas: one welded, watertight, consistently oriented mesh of an atlas, for
uniform and mixed resolutions, with and without detail tiles; positions on the reference
evaluator (``patch_surface(f).evaluate``), the two kernels in agreement, one normal per
border vertex, and a PLY that a peer reader (trimesh) reads back."""

from __future__ import annotations

import io
import math
import random
from collections import Counter

import numpy as np
import pytest
from atlas_cases import sphere_atlas
from test_atlas import random_cube_atlas

from client_py import Mesh
from client_py.atlas import AtlasSurface, atlas_edges
from client_py.atlas_mesh import (
    AtlasMesh,
    atlas_part,
    atlas_ply,
    tessellate_atlas,
    tessellate_atlas_part,
)
from client_py.layers import DetailTile

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


def test_an_open_layout_has_exactly_its_border_as_boundary():
    """The cube without its top: the 4 border edges' samples are the only boundary."""
    full = random_cube_atlas(3, 2, seed=7)
    quads = full.quads[:1] + full.quads[2:]  # drop the z = 1 face
    inner = full.side - 2
    edges = full.edges.edges
    table = atlas_edges(quads)
    index = {edge: e for e, edge in enumerate(edges)}
    edge_points = [p for edge in table.edges
                   for p in full.edge_points[index[edge] * inner : (index[edge] + 1) * inner]]
    face_points = full.face_points[: inner * inner] + full.face_points[2 * inner * inner :]
    atlas = AtlasSurface(3, 2, full.vertices, quads, edge_points, face_points)
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


# ------------------------------------------------------------------ parts drawn apart
def _sphere_parts(seam_resolution=5, rational=False):
    atlas = sphere_atlas(2, noise=0.02, seed=4, rational=rational)
    return atlas, [atlas_part(atlas, range(4 * g, 4 * g + 4), seam_resolution)
                   for g in range(6)]  # a cube face each


def _welded_by_position(meshes, surface_only=True):
    """The parts' surfaces (or all their triangles) as one mesh, vertices merged where their
    float32 positions are equal bit for bit."""
    ids: dict[tuple, int] = {}
    points, indices = [], []
    for mesh in meshes:
        xyz = np.frombuffer(mesh.positions, dtype=np.float32).reshape(-1, 3)
        local = []
        for p in map(tuple, xyz.tolist()):
            if p not in ids:
                ids[p] = len(ids)
                points.append(p)
            local.append(ids[p])
        count = 3 * mesh.surface_triangles if surface_only else len(mesh.indices)
        indices += [local[k] for k in mesh.indices[:count]]
    from array import array
    return Mesh(array("f", np.ravel(points).astype(np.float32).tobytes()), array("f"),
                array("f"), array("I", indices))


def test_parts_without_detail_weld_into_the_closed_atlas():
    """Parts at the base resolution share their seam vertices bit for bit: together they
    are the whole atlas's closed, consistently oriented mesh (each edge in two triangles)."""
    atlas, parts = _sphere_parts()
    meshes = [tessellate_atlas_part(part, 5, kernel="python") for part in parts]
    assert all(m.vertex_count == m.surface_vertices for m in meshes)  # no walls
    union = _welded_by_position(meshes)
    assert_closed_and_oriented(union)
    whole = tessellate_atlas(atlas, 5, kernel="python")
    assert union.vertex_count == whole.vertex_count
    assert union.triangle_count == whole.triangle_count
    a = np.sort(np.frombuffer(union.positions, np.float32).reshape(-1, 3), axis=0)
    b = np.sort(np.frombuffer(whole.positions, np.float32).reshape(-1, 3), axis=0)
    assert np.abs(a - b).max() < 1e-6


@pytest.mark.parametrize("rational", [False, True])
def test_parts_at_mixed_levels_meet_on_shared_lines_with_walls_down_to_the_lower_edge(rational):
    """Detail at different levels on either side of a seam: both parts place their seam
    samples on lines ``S + t n`` of one shared frame (equal bit for bit in both parts), the
    seam's ends on ``S``; a part with detail hangs a wall down from every sample, never above
    its edge, and where two parts with detail meet, the higher edge's wall reaches past the
    lower edge (no crack). The step is real (without the walls the edges are apart)."""
    atlas, parts = _sphere_parts()
    if rational:  # the same layout with weights: the frames come from the rational patches
        w = [1.0 + 0.3 * ((k * 7919) % 5) / 5 for k in range(atlas.control_point_count)]
        atlas = AtlasSurface(atlas.degree, atlas.spans, atlas.vertices, atlas.quads,
                             atlas.edge_points, atlas.face_points, w)
        parts = [atlas_part(atlas, part.patches, 5) for part in parts]
    levels = [0, 1, -1, 1, 0, -1]
    resolution = {-1: 5, 0: 9, 1: 17}
    meshes = []
    for g, part in enumerate(parts):
        detail = None
        if levels[g] >= 0:
            detail = {f: random_tiles(f, levels=levels[g] + 1, amplitude=0.2)
                      for f in part.patches}
        meshes.append(tessellate_atlas_part(part, resolution[levels[g]], detail,
                                            kernel="python"))
    owner = {f: g for g, part in enumerate(parts) for f in part.patches}
    largest_step, seams, covered = 0.0, 0, 0
    for e, pairs in enumerate(atlas.edges.faces):
        ga, gb = owner[pairs[0][0]], owner[pairs[1][0]]
        if ga == gb:
            continue
        seams += 1
        frames = [parts[g].frames[parts[g].full_edges.index(e)] for g in (ga, gb)]
        assert frames[0] == frames[1]
        S, n = (np.array(x, float) for x in frames[0])  # base points, the seam's direction
        tops, lowest = [], []
        for g in (ga, gb):
            mesh = meshes[g]
            xyz = np.frombuffer(mesh.positions, np.float32).reshape(-1, 3).astype(float)
            nodes = mesh.seams[e]
            step = (len(nodes) - 1) // 4  # 5 samples evaluated on every seam
            top = xyz[[nodes[K * step] for K in range(5)]]
            assert np.abs(np.cross(top - S, n)).max() < 1e-5  # on the lines S + t n
            assert np.array_equal(top[[0, 4]], S[[0, 4]].astype(np.float32).astype(float))
            t_top = (top - S) @ n
            tops.append(t_top)
            if levels[g] < 0:
                assert mesh.vertex_count == mesh.surface_vertices  # the base: no wall
                assert np.abs(t_top).max() < 1e-6
                lowest.append(t_top)
                continue
            walls = np.asarray(mesh.indices, np.int64).reshape(-1, 3)[mesh.surface_triangles:]
            for a, b in zip(nodes, nodes[1:], strict=False):
                assert sum(1 for t in walls.tolist() if a in t and b in t) == 1, (e, a, b)
            bottom = []
            for K in range(5):  # the wall under sample K: down from the top, on its line
                a = nodes[K * step]
                under = [v for t in walls.tolist() if a in t for v in t
                         if v >= mesh.surface_vertices]
                t_under = [(xyz[v] - S[K]) @ n for v in under
                           if np.abs(np.cross(xyz[v] - S[K], n)).max() < 1e-5]
                assert t_under and max(t_under) <= t_top[K] + 1e-6  # no fin
                bottom.append(min(t_under))
            lowest.append(np.array(bottom))
        for K in range(1, 4):
            hi = 0 if tops[0][K] >= tops[1][K] else 1
            if levels[(ga, gb)[hi]] >= 0 and levels[(ga, gb)[1 - hi]] >= 0:
                assert lowest[hi][K] <= tops[1 - hi][K] + 1e-6  # the higher wall covers
                covered += 1
        largest_step = max(largest_step, float(np.abs(tops[0] - tops[1]).max()))
    assert seams == 24  # the cube's 12 edges, cut in two
    assert covered > 0 and largest_step > 1e-3


def test_part_walls_fold_against_the_surface():
    """Surface and walls of a part are consistently oriented: every seam edge is used once
    in each direction (the surface's triangle and its wall's)."""
    _, parts = _sphere_parts()
    part = parts[1]
    mesh = tessellate_atlas_part(part, 9, {f: random_tiles(f) for f in part.patches},
                                 kernel="python")
    _, directed = edge_uses(mesh)
    for nodes in mesh.seams.values():
        for a, b in zip(nodes, nodes[1:], strict=False):
            assert directed[a, b] == 1 and directed[b, a] == 1


def test_a_part_needs_a_stitchable_resolution_and_its_own_detail():
    atlas, parts = _sphere_parts()
    with pytest.raises(ValueError, match="seam resolution"):
        tessellate_atlas_part(parts[0], 3)
    with pytest.raises(ValueError, match="power-of-2"):
        tessellate_atlas_part(parts[0], 7)
    with pytest.raises(ValueError, match="no patch of the part"):
        tessellate_atlas_part(parts[0], 9, {20: random_tiles(1)})
    with pytest.raises(ValueError, match="twice"):
        atlas_part(atlas, [0, 0], 5)
    with pytest.raises(ValueError, match="no patch index"):
        atlas_part(atlas, [24], 5)


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
