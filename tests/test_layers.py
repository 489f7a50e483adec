"""client_py.layers and the .tsd tile format: the detail field against scipy's BSpline, seams,
tiles acting only inside their rectangles, both kernels, texture sampling, corrupt tiles."""

from __future__ import annotations

import dataclasses
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from nurbs_cases import random_surface
from scipy.interpolate import BSpline

from client_py import (
    DetailTile,
    NurbsSurface,
    PatchFormatError,
    TextureImage,
    read_detail_tile,
    tessellate_grid,
    tessellate_region,
    write_detail_tile,
)
from client_py.layers import displacement_grid, level_knots, transform_mesh
from client_py.trim import TrimMask

FUZZ = settings(max_examples=100, deadline=2000, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow])


def global_field(level: int, degree: int, spans: int, seed: int = 0) -> np.ndarray:
    n = (spans << level) + degree
    return np.random.default_rng(seed).integers(-400, 400, (n, n))


def tile_of(q: np.ndarray, level: int, i: int, j: int, degree: int, spans: int,
            step: float = 2**-7) -> DetailTile:
    size = spans + degree
    block = q[i * spans : i * spans + size, j * spans : j * spans + size]
    return DetailTile(level, i, j, degree, spans, step, tuple(int(x) for x in block.ravel()))


def scipy_field(q: np.ndarray, level: int, degree: int, spans: int, step: float,
                u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The independent reference: scipy B-spline design matrices of the global knots."""
    t = np.array(level_knots(degree, spans, level))
    Bu = BSpline.design_matrix(u, t, degree).toarray()
    Bv = BSpline.design_matrix(v, t, degree).toarray()
    return np.einsum("ma,ab,mb->m", Bu, q * step, Bv)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_tile_field_matches_scipy(degree):
    level, spans = 2, 5
    q = global_field(level, degree, spans, degree)
    tile = tile_of(q, level, 1, 2, degree, spans)
    u0, v0, u1, v1 = tile.uv_rect
    assert (u0, v0, u1, v1) == (0.25, 0.5, 0.5, 0.75)
    rng = np.random.default_rng(1)
    u = np.concatenate([rng.uniform(u0, u1, 40), [u0, u1, u0]])
    v = np.concatenate([rng.uniform(v0, v1, 40), [v0, v1, v1]])
    expected = scipy_field(q, level, degree, spans, 2**-7, u, v)
    got = [tile.evaluate(a, b) for a, b in zip(u, v, strict=True)]
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
    us, vs = np.sort(u[:12]), np.sort(v[:9])
    for kernel in ("python", "numpy"):
        grid = np.array(tile.evaluate_grid(us.tolist(), vs.tolist(), kernel)).reshape(12, 9)
        UU, VV = np.meshgrid(us, vs, indexing="ij")
        ref = scipy_field(q, level, degree, spans, 2**-7, UU.ravel(), VV.ravel()).reshape(12, 9)
        np.testing.assert_allclose(grid, ref, rtol=0, atol=1e-12)


def test_evaluate_outside_the_rectangle_is_refused():
    tile = tile_of(global_field(1, 2, 4), 1, 0, 1, 2, 4)
    with pytest.raises(ValueError, match="outside tile 1/0_1"):
        tile.evaluate(0.6, 0.7)


@pytest.mark.parametrize("degree", [1, 2])
def test_neighbouring_tiles_agree_on_their_border(degree):
    level, spans = 3, 4
    q = global_field(level, degree, spans, 7)
    left, right = tile_of(q, level, 2, 5, degree, spans), tile_of(q, level, 3, 5, degree, spans)
    below = tile_of(q, level, 2, 4, degree, spans)
    border = 3 / 8
    for v in np.linspace(5 / 8, 6 / 8, 17):
        assert left.evaluate(border, v) == pytest.approx(right.evaluate(border, v), abs=1e-13)
    for u in np.linspace(2 / 8, 3 / 8, 17):
        assert left.evaluate(u, 5 / 8) == pytest.approx(below.evaluate(u, 5 / 8), abs=1e-13)


def test_round_trip_and_size():
    tile = tile_of(global_field(2, 2, 16), 2, 3, 1, 2, 16, step=2.5e-4)
    data = write_detail_tile(tile)
    assert read_detail_tile(data) == tile
    assert data[:4] == b"TSDT"
    assert write_detail_tile(tile) == data  # deterministic
    wide = DetailTile(0, 0, 0, 2, 16, 1.0, tuple((-1) ** k * (k * 99991) % (1 << 28)
                                                 for k in range(18 * 18)))  # escapes
    assert read_detail_tile(write_detail_tile(wide)) == wide
    assert len(write_detail_tile(DetailTile(0, 0, 0, 2, 16, 1.0, (0,) * 324))) < 30


@pytest.mark.parametrize("scale", [0.3, 1.0, 4.0])
def test_values_cost_about_their_entropy(scale):
    """Detail coefficients are close to independent Laplacian noise: the range-coded tile
    stays within 10 % (plus framing) of the values' empirical order-0 entropy."""
    q = np.rint(np.random.default_rng(7).laplace(0, scale, 18 * 18)).astype(int)
    _, counts = np.unique(q, return_counts=True)
    entropy = -(counts * np.log2(counts / len(q))).sum() / 8  # bytes
    data = write_detail_tile(DetailTile(3, 2, 5, 2, 16, 0.5, tuple(int(x) for x in q)))
    assert len(data) - 22 <= 1.1 * entropy + 4, (len(data), entropy)


def surface_and_tiles():
    """A gently curved rational patch over the unit square and the four tiles of level 1."""
    rough = random_surface(np.random.default_rng(3), 2, 2, 6, 5)
    a, b = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 5), indexing="ij")
    P = np.stack([a, b, 0.1 * np.sin(3 * a) * np.cos(2 * b)], axis=-1)
    s = NurbsSurface((2, 2), rough.knots, P, rough.weights)
    q = global_field(1, 2, 4, 11)
    tiles = [tile_of(q, 1, i, j, 2, 4, step=2**-16) for i in range(2) for j in range(2)]
    return s, q, tiles


def test_region_positions_are_base_plus_displacement_along_the_normal():
    s, q, tiles = surface_and_tiles()
    nu, nv = 9, 7
    mesh = tessellate_region(s, (0.25, 0.0, 0.75, 1.0), nu, nv, tiles, kernel="python")
    us, vs = np.linspace(0.25, 0.75, nu), np.linspace(0.0, 1.0, nv)
    UU, VV = np.meshgrid(us, vs, indexing="ij")
    D = scipy_field(q, 1, 2, 4, 2**-16, UU.ravel(), VV.ravel())
    base = np.array([s.evaluate(a, b) for a, b in zip(UU.ravel(), VV.ravel(), strict=True)])
    n = np.array([s.normal(a, b) for a, b in zip(UU.ravel(), VV.ravel(), strict=True)])
    pos = np.array(mesh.positions).reshape(-1, 3)
    np.testing.assert_allclose(pos, base + D[:, None] * n, atol=1e-5)
    np.testing.assert_allclose(np.array(mesh.uvs).reshape(-1, 2),
                               np.column_stack([UU.ravel(), VV.ravel()]), atol=1e-7)
    nrm = np.array(mesh.normals).reshape(-1, 3)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-6)
    assert np.all(np.einsum("ij,ij->i", nrm, n) > 0.5)  # same side as the base


def test_a_tile_changes_geometry_only_inside_its_rectangle():
    s, q, tiles = surface_and_tiles()
    one = tiles[1]  # (0, 1): u in [0, 0.5], v in [0.5, 1]
    plain = tessellate_grid(s, 21, 21, kernel="numpy")
    mesh = tessellate_region(s, (0, 0, 1, 1), 21, 21, [one], kernel="numpy")
    moved = np.linalg.norm(np.array(mesh.positions).reshape(-1, 3)
                           - np.array(plain.positions).reshape(-1, 3), axis=1)
    uv = np.array(mesh.uvs).reshape(-1, 2)
    inside = (uv[:, 0] <= 0.5 + 1e-7) & (uv[:, 1] >= 0.5 - 1e-7)
    assert np.all(moved[~inside] == 0.0)
    assert np.count_nonzero(moved[inside] > 1e-6) > 0.8 * inside.sum()


def test_border_vertices_take_a_level_once():
    s, q, tiles = surface_and_tiles()
    us = [0.0, 0.25, 0.5, 0.75, 1.0]
    D = np.array(displacement_grid(tiles, us, us)).reshape(5, 5)
    UU, VV = np.meshgrid(us, us, indexing="ij")
    np.testing.assert_allclose(D.ravel(), scipy_field(q, 1, 2, 4, 2**-16, UU.ravel(), VV.ravel()),
                               atol=1e-12)


def test_kernels_agree():
    s, _, tiles = surface_and_tiles()
    a = tessellate_region(s, (0.1, 0.2, 0.9, 0.7), 33, 25, tiles, kernel="python")
    b = tessellate_region(s, (0.1, 0.2, 0.9, 0.7), 33, 25, tiles, kernel="numpy")
    np.testing.assert_allclose(np.array(a.positions), np.array(b.positions), atol=1e-6)
    np.testing.assert_allclose(np.array(a.normals), np.array(b.normals), atol=1e-6)
    assert a.indices == b.indices


def test_regions_sharing_a_border_share_its_vertices_and_normals():
    s, _, tiles = surface_and_tiles()
    left = tessellate_region(s, (0.0, 0.0, 0.5, 1.0), 11, 21, tiles)
    right = tessellate_region(s, (0.5, 0.0, 1.0, 1.0), 11, 21, tiles)
    pl = np.array(left.positions).reshape(11, 21, 3)[-1]
    pr = np.array(right.positions).reshape(11, 21, 3)[0]
    np.testing.assert_allclose(pl, pr, atol=1e-6)
    nl = np.array(left.normals).reshape(11, 21, 3)[-1]
    nr = np.array(right.normals).reshape(11, 21, 3)[0]
    np.testing.assert_allclose(nl, nr, atol=1e-5)


def test_without_tiles_a_region_is_the_grid_tessellation():
    s, _, _ = surface_and_tiles()
    a = tessellate_region(s, (0, 0, 1, 1), 17, 13)
    b = tessellate_grid(s, 17, 13)
    assert a.positions == b.positions and a.normals == b.normals and a.indices == b.indices


def test_texture_sampling_and_vertex_colours():
    rgb = bytes([10, 20, 30, 200, 100, 0, 0, 0, 255, 40, 40, 40])  # 2 x 2, row 0 on top
    image = TextureImage(1, 1, 0, 2, 2, rgb)  # u in [0.5, 1], v in [0, 0.5]
    assert image.sample(0.625, 0.375) == (10, 20, 30)  # top-left texel centre
    assert image.sample(0.875, 0.375) == (200, 100, 0)
    assert image.sample(0.625, 0.125) == (0, 0, 255)  # bottom row
    mid = image.sample(0.75, 0.25)
    assert mid == tuple(int(sum(rgb[c::3]) / 4 + 0.5) for c in range(3))
    s, _, _ = surface_and_tiles()
    mesh = tessellate_region(s, (0.5, 0.0, 1.0, 0.5), 3, 3, textures=[image])
    assert tuple(mesh.colors[0:3]) == (0, 0, 255)  # (u, v) = (0.5, 0): bottom-left
    with pytest.raises(ValueError, match="rgb has 3 bytes"):
        TextureImage(0, 0, 0, 1, 2, b"abc")


def test_transform_mesh_matches_numpy():
    s, _, tiles = surface_and_tiles()
    mesh = tessellate_region(s, (0, 0, 1, 1), 6, 6, tiles)
    m = np.array([[0.0, -2.0, 0.0, 5.0], [2.0, 0.0, 0.0, -1.0], [0.0, 0.0, -2.0, 3.0],
                  [0, 0, 0, 1]])
    out = transform_mesh(mesh, m)
    p = np.array(mesh.positions).reshape(-1, 3)
    np.testing.assert_allclose(np.array(out.positions).reshape(-1, 3), p @ m[:3, :3].T + m[:3, 3],
                               atol=1e-4)
    n = np.array(mesh.normals).reshape(-1, 3) @ np.linalg.inv(m[:3, :3])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(np.array(out.normals).reshape(-1, 3), n, atol=1e-6)
    assert out.indices[1::3] == mesh.indices[2::3]  # det < 0: winding reversed


@pytest.mark.parametrize("bad, match", [
    (dict(level=16), "level must be"), (dict(i=4), "i must be"), (dict(degree=4), "degree"),
    (dict(spans=0), "spans"), (dict(step=0.0), "step"), (dict(values=(1, 2)), "values"),
])
def test_tile_values_are_checked(bad, match):
    args = dict(level=2, i=1, j=1, degree=1, spans=2, step=0.5, values=(0,) * 9) | bad
    with pytest.raises(ValueError, match=match):
        DetailTile(**args)


# ------------------------------------------------------------------ corrupt tiles
def tile_file() -> bytes:
    """A tile with a drawn mask, so that the fuzz tests reach the mask's checks too."""
    tile = tile_of(global_field(1, 2, 6, 5), 1, 1, 0, 2, 6)
    mask = TrimMask((np.arange(49).reshape(7, 7) % 3 == 0).tolist())
    return write_detail_tile(dataclasses.replace(tile, drawn=mask))


def test_drawn_mask_round_trips_and_its_side_must_match_the_flag():
    data = tile_file()
    tile = read_detail_tile(data)
    assert tile.drawn.rows == tile.drawn.cols == 7
    assert list(tile.drawn.flat) == [int(k % 3 == 0) for k in range(49)]
    for flags, side in ((0, 7), (1, 0)):  # a side without flag 0x1, the flag without a side
        body = bytearray(data[:-4])
        body[5], body[9] = flags, side
        with pytest.raises(PatchFormatError, match="drawn mask side") as info:
            read_detail_tile(bytes(body) + struct.pack("<I", zlib.crc32(body)))
        assert info.value.offset == 9
    with pytest.raises(ValueError, match="square"):
        write_detail_tile(dataclasses.replace(tile, drawn=TrimMask([[1, 0]])))


#: tile_file() as main wrote it before walls masks (flag 0x2) existed: old tiles read the same
OLD_TILE_CRC, OLD_TILE_SIZE = 558161692, 134


def test_walls_mask_round_trips_and_old_tiles_read_and_write_as_before():
    """A walls mask (flag 0x2, its own side up to 256) round-trips after the drawn mask; a
    tile without one is written byte for byte as before the flag (tile_file's bytes as
    main 9ff7160 wrote them) and reads back without walls."""
    data = tile_file()
    assert data[5] == 1 and zlib.crc32(data) == OLD_TILE_CRC and len(data) == OLD_TILE_SIZE
    assert read_detail_tile(data).walls is None
    tile = read_detail_tile(data)
    for side in (1, 5, 256):
        walls = TrimMask((np.arange(side * side).reshape(side, side) % 7 == 1).tolist())
        back = read_detail_tile(write_detail_tile(dataclasses.replace(tile, walls=walls)))
        assert back.walls == walls and back.drawn == tile.drawn and back.values == tile.values
        alone = dataclasses.replace(tile, drawn=None, walls=walls)
        assert read_detail_tile(write_detail_tile(alone)) == alone
    with pytest.raises(ValueError, match="walls mask must be square"):
        write_detail_tile(dataclasses.replace(tile, walls=TrimMask([[1, 0]])))
    with pytest.raises(ValueError, match="walls mask must be square"):
        write_detail_tile(dataclasses.replace(tile, walls=TrimMask(np.zeros((257, 257),
                                                                            bool))))


def test_drawn_masks_bring_back_cells_the_base_trim_leaves_out():
    """Cells drawn = base trim covers the cell's centre, or a given tile's mask does."""
    s, q, tiles = surface_and_tiles()
    trim = np.ones((8, 8), bool)
    trim[2:6, 1:7] = False
    base = NurbsSurface((2, 2), s.knots, s.control_points, s.weights, trim=TrimMask(trim))
    mask = np.zeros((4, 4), bool)
    mask[1:3, 2:4] = True  # tile (0, 1): u in [0, 0.5], v in [0.5, 1]; cells of 1/8
    redraw = dataclasses.replace(tiles[1], drawn=TrimMask(mask))
    others = [t for t in tiles if t is not tiles[1]]
    n = 33
    centre = (np.arange(n - 1) + 0.5) / (n - 1)
    U, V = np.meshgrid(centre, centre, indexing="ij")
    in_tile = (U <= 0.5) & (V >= 0.5)
    by_mask = in_tile & mask[np.minimum((U * 8).astype(int), 3),
                             np.minimum(((V - 0.5) * 8).astype(int), 3)]
    expected = trim[(U * 8).astype(int), (V * 8).astype(int)] | by_mask
    for kernel in ("python", "numpy"):
        mesh = tessellate_region(base, (0, 0, 1, 1), n, n, [*others, redraw], kernel=kernel)
        assert len(mesh.indices) == 6 * expected.sum()
        plain = tessellate_region(base, (0, 0, 1, 1), n, n, tiles, kernel=kernel)
        assert len(plain.indices) == 6 * trim[(U * 8).astype(int), (V * 8).astype(int)].sum()


def test_rejects_with_offsets():
    data = tile_file()
    with pytest.raises(PatchFormatError, match="not a Tessera detail tile"):
        read_detail_tile(b"TSPF" + data[4:])
    with pytest.raises(PatchFormatError, match="truncated"):
        read_detail_tile(data[:21])
    for cut in (data[:-1], data + b"\0"):  # the coded bytes run to the CRC, which catches it
        with pytest.raises(PatchFormatError, match="CRC32"):
            read_detail_tile(cut)
    short = data[:30]  # a valid CRC over too few coded bytes
    with pytest.raises(PatchFormatError, match="end early") as info:
        read_detail_tile(short + struct.pack("<I", zlib.crc32(short)))
    assert info.value.offset == 30
    broken = bytearray(data)
    broken[40] ^= 1
    with pytest.raises(PatchFormatError, match="CRC32") as info:
        read_detail_tile(bytes(broken))
    assert info.value.offset == len(data) - 4


@FUZZ
@given(st.data())
def test_truncations_and_bit_flips_raise_format_errors_only(data):
    blob = bytearray(tile_file())
    if data.draw(st.booleans()):
        blob = blob[: data.draw(st.integers(0, len(blob) - 1))]
    else:
        for bit in data.draw(st.lists(st.integers(0, 8 * len(blob) - 1), min_size=1,
                                      max_size=6, unique=True)):
            blob[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(PatchFormatError):
        read_detail_tile(bytes(blob))


@FUZZ
@given(st.binary(max_size=300))
def test_random_bytes_raise_format_errors_only(blob):
    with pytest.raises(PatchFormatError):
        read_detail_tile(b"TSDT" + blob)


@FUZZ
@given(st.binary(min_size=14, max_size=14), st.binary(max_size=200))
def test_random_headers_with_valid_crc_raise_format_errors_only(header, payload):
    body = b"TSDT" + header + payload
    blob = body + struct.pack("<I", zlib.crc32(body))
    try:
        tile = read_detail_tile(blob)
    except PatchFormatError:
        return
    assert isinstance(tile, DetailTile)  # a valid header by chance decodes to a valid tile


# ------------------------------------------------------------------ kernels on whole grids
def masked_surface_and_tiles(seed: int = 5, walls: float = 0.0):
    """A trimmed patch and tiles of levels 1..3 (some absent, some without a drawn mask),
    drawn masks of different sides; with ``walls``, that share of the tiles carries a walls
    mask of its own side (some all clear)."""
    s, _, _ = surface_and_tiles()
    rng = np.random.default_rng(seed)
    trim = rng.random((13, 11)) < 0.5
    base = NurbsSurface((2, 2), s.knots, s.control_points, s.weights, trim=TrimMask(trim))
    tiles = []
    for level, spans in ((1, 4), (2, 3), (3, 2)):
        q = global_field(level, 2, spans, seed + level)
        for i in range(1 << level):
            for j in range(1 << level):
                if rng.random() < 0.25:
                    continue  # absent: a zero field, no drawn cells
                tile = tile_of(q, level, i, j, 2, spans, step=2**-12)
                if rng.random() < 0.7:
                    side = int(rng.integers(1, 9))
                    tile = dataclasses.replace(tile, drawn=TrimMask(rng.random((side, side))
                                                                    < 0.4))
                if rng.random() < walls:
                    side = int(rng.integers(1, 12))
                    share = 0.0 if rng.random() < 0.3 else 0.5
                    tile = dataclasses.replace(tile, walls=TrimMask(rng.random((side, side))
                                                                    < share))
                tiles.append(tile)
    return base, trim, tiles


def reference_drawn(trim: np.ndarray, tiles, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """The definition, cell by cell with numpy: the centre covered by the base trim, or by
    the drawn mask of a tile whose closed rectangle contains it; a centre on the border of
    two tiles of a level belongs to the one ``min(floor(u 2^L), 2^L - 1)`` names (the
    tile above the border), as for the base trim's cells. Then, of the tiles with a walls
    mask holding the centre, the finest one's mask leaves the cell out where it covers it."""
    cu, cv = 0.5 * (us[:-1] + us[1:]), 0.5 * (vs[:-1] + vs[1:])
    U, V = np.meshgrid(cu, cv, indexing="ij")
    rows, cols = trim.shape
    drawn = trim[np.minimum((U * rows).astype(int), rows - 1),
                 np.minimum((V * cols).astype(int), cols - 1)].copy()

    def held(t, mask):  # the centres tile t holds, and its mask's value at every centre
        u0, v0, u1, v1 = t.uv_rect
        n = 1 << t.level
        named = ((np.minimum(np.floor(U * n), n - 1) == t.i)
                 & (np.minimum(np.floor(V * n), n - 1) == t.j))
        inside = named & (U >= u0) & (U <= u1) & (V >= v0) & (V <= v1)
        cells = np.frombuffer(mask.flat, np.uint8).reshape(mask.rows, mask.cols)
        r = np.clip(((U - u0) / (u1 - u0) * mask.rows).astype(int), 0, mask.rows - 1)
        c = np.clip(((V - v0) / (v1 - v0) * mask.cols).astype(int), 0, mask.cols - 1)
        return inside, cells[r, c] != 0

    for t in tiles:
        if t.drawn is not None:
            inside, covered = held(t, t.drawn)
            drawn |= inside & covered
    veto = np.zeros_like(drawn)
    for t in sorted(tiles, key=lambda t: t.level):
        if t.walls is not None:
            inside, covered = held(t, t.walls)
            veto[inside] = covered[inside]
    return drawn & ~veto


@pytest.mark.parametrize("rect, nu, nv", [((0, 0, 1, 1), 57, 45), ((0.1, 0.3, 0.77, 0.9), 41, 37),
                                          ((0.26, 0.51, 0.49, 0.74), 19, 23)])
@pytest.mark.parametrize("walls", [0.0, 0.6])
def test_drawn_cells_are_the_base_trim_or_a_tile_mask_in_both_kernels(rect, nu, nv, walls):
    """... less the cells the finest given walls mask holding them covers (``walls``)."""
    base, trim, tiles = masked_surface_and_tiles(walls=walls)
    # the grid as tessellate_region makes it (u0 + k step, to the bit: a centre one ulp
    # across a mask cell's border is in the other cell)
    us = np.array([rect[0] + k * ((rect[2] - rect[0]) / (nu - 1)) for k in range(nu - 1)]
                  + [rect[2]])
    vs = np.array([rect[1] + k * ((rect[3] - rect[1]) / (nv - 1)) for k in range(nv - 1)]
                  + [rect[3]])
    expected = reference_drawn(trim, tiles, us, vs)
    assert 0 < expected.sum() < expected.size
    # the tiles' masks add cells the base trim leaves out
    assert expected.sum() > reference_drawn(trim, [], us, vs).sum()
    if walls:  # the walls masks take some away, and a finer one gives some back
        plain = [dataclasses.replace(t, walls=None) for t in tiles]
        assert expected.sum() < reference_drawn(trim, plain, us, vs).sum()
        if rect == (0, 0, 1, 1):
            coarsest = [t if t.level == 1 else dataclasses.replace(t, walls=None)
                        for t in tiles]
            assert (expected & ~reference_drawn(trim, coarsest, us, vs)).any()
    meshes = {k: tessellate_region(base, rect, nu, nv, tiles, kernel=k)
              for k in ("python", "numpy")}
    assert meshes["python"].indices == meshes["numpy"].indices
    idx = np.frombuffer(meshes["python"].indices, np.uint32).reshape(-1, 6).astype(np.int64)
    k = idx[:, 0]
    corners = np.stack([k, k + nv, k + 1, k + 1, k + nv, k + nv + 1], axis=1)
    assert np.array_equal(idx, corners)
    got = np.zeros((nu - 1, nv - 1), bool)
    got[k // nv, k % nv] = True
    assert np.array_equal(got, expected)
    assert np.all(np.diff(k) > 0)  # row-major, each cell once


def test_displacement_grid_kernels_agree_exactly_and_match_scipy():
    """Levels 1..3 with tiles missing: the sum of each level's scipy field where the level
    has the tile, on a grid with vertices on tile borders and between them."""
    _, _, tiles = masked_surface_and_tiles(9)
    us = np.unique(np.concatenate([np.linspace(0, 1, 17), [0.3, 0.61, 0.999]]))
    vs = np.unique(np.concatenate([np.linspace(0.25, 0.75, 9), [0.0, 0.07, 1.0]]))
    got = {k: displacement_grid(tiles, us.tolist(), vs.tolist(), k) for k in ("python", "numpy")}
    assert got["python"].tobytes() == got["numpy"].tobytes()
    U, V = np.meshgrid(us, vs, indexing="ij")
    expected = np.zeros(U.shape)
    for level, spans in ((1, 4), (2, 3), (3, 2)):
        have = {(t.i, t.j): t for t in tiles if t.level == level}
        q = np.zeros(((spans << level) + 2,) * 2)
        for (i, j), t in have.items():
            q[i * spans : i * spans + t.size, j * spans : j * spans + t.size] = \
                np.array(t.values).reshape(t.size, t.size)
        field = scipy_field(q, level, 2, spans, 2**-12, U.ravel(), V.ravel()).reshape(U.shape)
        n = 1 << level
        applies = np.zeros(U.shape, bool)
        for i, j in have:  # a vertex takes a level where a given tile's closed rectangle holds it
            applies |= (U >= i / n) & (U <= (i + 1) / n) & (V >= j / n) & (V <= (j + 1) / n)
        expected += np.where(applies, field, 0.0)
    np.testing.assert_allclose(np.array(got["python"]).reshape(U.shape), expected, rtol=0,
                               atol=1e-12)


@pytest.mark.parametrize("flip", [False, True])
def test_transform_mesh_kernels_agree_exactly_and_match_numpy(flip):
    from array import array

    s, _, tiles = surface_and_tiles()
    mesh = tessellate_region(s, (0, 0, 1, 1), 9, 7, tiles)
    mesh.normals[0:3] = array("f", [0.0, 0.0, 0.0])  # a zero normal stays zero
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3))
    if (np.linalg.det(A) < 0) != flip:
        A[0] *= -1
    m = np.hstack([A, rng.normal(size=(3, 1))])
    out = {k: transform_mesh(mesh, m, kernel=k) for k in ("python", "numpy")}
    for name in ("positions", "normals", "uvs", "indices"):
        assert getattr(out["python"], name) == getattr(out["numpy"], name), name
    p = np.array(mesh.positions, dtype=float).reshape(-1, 3)
    np.testing.assert_allclose(np.array(out["numpy"].positions).reshape(-1, 3),
                               p @ A.T + m[:, 3], rtol=1e-6, atol=1e-6)
    n = np.array(mesh.normals, dtype=float).reshape(-1, 3) @ np.linalg.inv(A)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = n / np.where(length > 0, length, 1.0)
    np.testing.assert_allclose(np.array(out["numpy"].normals).reshape(-1, 3), n, atol=1e-6)
    assert out["numpy"].normals[0:3].tolist() == [0.0, 0.0, 0.0]
    reversed_ = out["numpy"].indices[1::3] == mesh.indices[2::3]
    assert reversed_ == flip


def test_displace_grid_kernels_agree_exactly_and_keep_the_base_normal_at_a_pole():
    """X = S + D n and normals by clamped central differences, against a numpy reference;
    a row collapsed to one point (a pole) keeps the base normal."""
    from array import array

    from client_py._kernel import backend

    rng = np.random.default_rng(8)
    rows, cols = 7, 6
    S = rng.normal(size=(rows, cols, 3))
    S[0] = S[0, 0]  # row 0 is one point: no tangent along it
    n = rng.normal(size=(rows, cols, 3))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    D = rng.normal(size=(rows, cols)) * 0.1
    D[0] = 0.0
    window = (0, rows, 1, cols)
    args = (array("d", S.ravel()), array("d", n.ravel()), array("d", D.ravel()), rows, cols,
            window)
    a, b = backend("python").displace_grid(*args), backend("numpy").displace_grid(*args)
    assert a[0] == b[0] and a[1] == b[1]
    X = S + D[..., None] * n
    i, j = np.arange(rows)[:, None], np.arange(1, cols)[None, :]
    du = X[np.minimum(i + 1, rows - 1), j] - X[np.maximum(i - 1, 0), j]
    dv = X[i, np.minimum(j + 1, cols - 1)] - X[i, np.maximum(j - 1, 0)]
    m = np.cross(du, dv)
    length = np.linalg.norm(m, axis=2, keepdims=True)
    assert np.all(length[0] == 0) and np.all(length[1:] > 0)
    m = np.where(length > 0, m / np.where(length > 0, length, 1.0), n[:, 1:])
    np.testing.assert_allclose(np.array(a[0]).reshape(rows, cols - 1, 3), X[:, 1:], atol=1e-6)
    np.testing.assert_allclose(np.array(a[1]).reshape(rows, cols - 1, 3), m, atol=1e-6)


def test_displace_grid_panels_are_the_grids_alone_in_both_kernels():
    """Grids side by side as panels of one call: each panel's normals (one-sided on its own
    outer columns, the base normal at a pole) and positions are those of the grid alone,
    bit for bit, in both kernels; without positions, the same normals."""
    from array import array

    from client_py._kernel import backend

    rng = np.random.default_rng(9)
    rows, width, count = 5, 4, 3
    S = rng.normal(size=(count, rows, width, 3))
    S[1, 2] = S[1, 2, 0]  # a row of panel 1 collapsed to one point: no tangent along it
    n = rng.normal(size=(count, rows, width, 3))
    n /= np.linalg.norm(n, axis=3, keepdims=True)
    D = rng.normal(size=(count, rows, width)) * 0.1
    D[1, 2] = 0.0

    def side_by_side(x):  # (count, rows, width, ...) -> rows of all panels
        return array("d", np.ascontiguousarray(np.swapaxes(x, 0, 1)).ravel())

    for name in ("python", "numpy"):
        kernel = backend(name)
        pos, nrm = kernel.displace_grid(side_by_side(S), side_by_side(n), side_by_side(D),
                                        rows, count * width, (0, rows, 0, count * width),
                                        width)
        pos = np.array(pos).reshape(rows, count, width, 3)
        nrm = np.array(nrm).reshape(rows, count, width, 3)
        for g in range(count):
            alone = kernel.displace_grid(array("d", S[g].ravel()), array("d", n[g].ravel()),
                                         array("d", D[g].ravel()), rows, width,
                                         (0, rows, 0, width))
            assert pos[:, g].tobytes() == np.array(alone[0]).tobytes()
            assert nrm[:, g].tobytes() == np.array(alone[1]).tobytes()
        bare = kernel.displace_grid(side_by_side(S), side_by_side(n), side_by_side(D), rows,
                                    count * width, (0, rows, 0, count * width), width,
                                    with_positions=False)
        assert len(bare[0]) == 0 and np.array(bare[1]).tobytes() == nrm.tobytes()
        for panel in (3, 0, True):  # 11 columns are no whole panels of 3; 0, True no width
            with pytest.raises(ValueError, match="whole panels"):
                kernel.displace_grid(side_by_side(S), side_by_side(n), side_by_side(D), rows,
                                     count * width - 1 if panel == 3 else count * width,
                                     (0, rows, 0, 1), panel)


def test_add_level_takes_each_vertex_from_the_first_block_covering_it():
    """Overlapping blocks of different values: both kernels add, at each vertex, the value
    of the first block that covers it (a numpy loop over the blocks as the reference)."""
    from array import array

    from client_py._kernel import backend

    rng = np.random.default_rng(4)
    rows, cols = 9, 11
    start = rng.normal(size=(rows, cols))
    blocks, expected, done = [], start.copy(), np.zeros((rows, cols), bool)
    for _ in range(6):
        r0, c0 = int(rng.integers(0, rows - 1)), int(rng.integers(0, cols - 1))
        r1, c1 = int(rng.integers(r0 + 1, rows + 1)), int(rng.integers(c0 + 1, cols + 1))
        values = rng.normal(size=(r1 - r0, c1 - c0))
        blocks.append((r0, r1, c0, c1, array("d", values.ravel())))
        fresh = ~done[r0:r1, c0:c1]
        expected[r0:r1, c0:c1][fresh] += values[fresh]
        done[r0:r1, c0:c1] = True
    assert done.sum() < done.size  # some vertices no block covers
    for kernel in ("python", "numpy"):
        total = array("d", start.ravel())
        backend(kernel).add_level(total, cols, blocks)
        assert np.array_equal(np.array(total).reshape(rows, cols), expected), kernel


def test_texture_nodes_keep_coarser_tiles_where_the_finest_level_has_none():
    from client_py.bundle import texture_nodes

    def node(k, i, j):
        return {"level": k, "i": i, "j": j, "file": f"texture/{k}/{i}_{j}.webp"}

    nodes = ([node(0, 0, 0)] + [node(1, i, j) for i in (0, 1) for j in (0, 1)]
             + [node(2, i, j) for i in range(4) for j in range(4) if (i, j) != (3, 3)])
    manifest = {"tiles": {"texture": {"nodes": nodes}}}
    picked = {(n["level"], n["i"], n["j"]) for n in texture_nodes(manifest)}
    # level 2 lacks (3, 3): its parent (1, 1, 1) stands in; (0, 0, 0) is then covered
    assert picked == {(2, i, j) for i in range(4) for j in range(4) if (i, j) != (3, 3)} | {
        (1, 1, 1)}
    assert {(n["level"], n["i"], n["j"]) for n in texture_nodes(manifest, 1)} == {
        (1, i, j) for i in (0, 1) for j in (0, 1)}
    assert texture_nodes({"tiles": {"texture": None}}) == []


# ------------------------------------------------------------------ vertex colours on grids
def reference_colours(uvs, textures) -> bytes:
    """The per-vertex loop vertex_colours was before its kernel path: the finest level whose
    node holds the vertex, last image of a node, sampled by ``TextureImage.sample`` (the
    scalar contract the kernels' block sampling must keep bit for bit)."""
    by_level: dict = {}
    for t in sorted(textures, key=lambda t: -t.level):
        by_level.setdefault(t.level, {})[(t.i, t.j)] = t
    out = bytearray(3 * (len(uvs) // 2))
    for k in range(len(uvs) // 2):
        u, v = uvs[2 * k], uvs[2 * k + 1]
        for level, images in by_level.items():
            n = 1 << level
            image = images.get((min(int(u * n), n - 1), min(int(v * n), n - 1)))
            if image is not None:
                out[3 * k : 3 * k + 3] = bytes(image.sample(u, v))  # the scalar sampler
                break
    return bytes(out)


def random_textures(rng: np.random.Generator, levels=(0, 1, 2, 3), keep: float = 0.7,
                    sizes=(1, 2, 3, 5, 16)) -> list[TextureImage]:
    """Random images (random sizes, 1x1 and 2x2 among them) over a random subset of the
    nodes of the given levels, plus a second image for one node (the last one counts)."""
    out = []
    for level in levels:
        for i in range(1 << level):
            for j in range(1 << level):
                if rng.random() < keep:
                    w, h = (int(x) for x in rng.choice(sizes, 2))
                    out.append(TextureImage(level, i, j, w, h, rng.bytes(3 * w * h)))
    out.append(dataclasses.replace(out[0], rgb=rng.bytes(len(out[0].rgb))))
    return out


def grid_uvs(rect, nu: int, nv: int):
    """uvs laid out as tessellate_region stores them (float32, vertex k = i nv + j)."""
    from array import array

    us, vs = np.linspace(rect[0], rect[2], nu), np.linspace(rect[1], rect[3], nv)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    return array("f", np.column_stack([uu.ravel(), vv.ravel()]).astype(np.float32).tobytes())


@pytest.mark.parametrize("seed", range(4))
def test_grid_vertex_colours_are_the_per_vertex_reference_bit_for_bit(seed, monkeypatch):
    """Random tiles of levels 0-3 with nodes missing, 1x1/2x2/odd images; grids whose
    vertices fall on tile borders (2^k + 1 over the unit square, regions ending on
    borders) and grids that do not; both kernels give the reference's bytes, on the
    grid path (TextureImage.sample, the per-vertex path, is made to fail)."""
    from client_py.layers import vertex_colours

    rng = np.random.default_rng(seed)
    textures = random_textures(rng)
    cases = [((0, 0, 1, 1), 17, 33), ((0, 0, 1, 1), 9, 9), ((0.25, 0.5, 0.75, 1.0), 13, 5),
             ((0.1, 0.03, 0.97, 0.6), 23, 31), ((0.5, 0.5, 1.0, 1.0), 1, 7),
             ((0.0, 0.3, 0.126, 0.4), 6, 1), ((0.3, 0.3, 0.3 + 1e-6, 0.9), 4, 3)]
    expected = {}
    for rect, nu, nv in cases:
        uvs = grid_uvs(rect, nu, nv)
        expected[rect, nu, nv] = reference_colours(uvs, textures)
    assert any(any(e) for e in expected.values())  # colours, not only black
    assert any(0 in e for e in expected.values())
    monkeypatch.setattr(TextureImage, "sample", None)  # the grid path must not need it
    for rect, nu, nv in cases:
        uvs = grid_uvs(rect, nu, nv)
        for kernel in ("python", "numpy"):
            for columns in (None, nv):
                got = vertex_colours(uvs, textures, kernel=kernel, columns=columns)
                assert got.typecode == "B"
                assert got.tobytes() == expected[rect, nu, nv], (rect, nu, nv, kernel, columns)


def test_vertex_colours_off_the_grid_and_through_tessellate_region():
    """Scattered uvs (outside [0, 1] too, where the node lookup clamps or finds none), a
    wrong ``columns`` and lists fall back to the per-vertex path; tessellate_region's
    colours are the reference at its uvs in both kernels."""
    from client_py.layers import vertex_colours

    rng = np.random.default_rng(7)
    textures = random_textures(rng, levels=(1, 2, 4), keep=0.6)
    uv = rng.uniform(-0.3, 1.3, (400, 2))
    uv[:40] = rng.integers(0, 17, (40, 2)) / 16  # exactly on tile borders
    uvs = uv.ravel().tolist()
    want = reference_colours(uvs, textures)
    for kernel in ("python", "numpy"):
        assert vertex_colours(uvs, textures, kernel=kernel).tobytes() == want
        assert vertex_colours(uvs + [0.5], textures, kernel=kernel).tobytes() == want
    grid = grid_uvs((0, 0, 1, 1), 9, 12)
    want = reference_colours(grid, textures)
    assert vertex_colours(grid, textures, columns=7).tobytes() == want  # not a 7-column grid
    assert vertex_colours(grid.tolist(), textures, columns=12).tobytes() == want
    assert vertex_colours(grid, []).tobytes() == bytes(3 * 9 * 12)
    s, _, tiles = surface_and_tiles()
    with pytest.raises(ValueError, match="must be TextureImage objects, got DetailTile"):
        vertex_colours(grid, [*textures, tiles[0]])
    for kernel in ("python", "numpy"):
        mesh = tessellate_region(s, (0.125, 0.25, 1.0, 0.875), 21, 15, tiles, kernel=kernel,
                                 textures=textures)
        assert mesh.colors.tobytes() == reference_colours(mesh.uvs, textures), kernel
