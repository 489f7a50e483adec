"""The atlas data model: edge numbering, shared control points, watertight borders."""

import random

import pytest

from client_py.atlas import AtlasSurface, atlas_edges

CORNERS = [(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)]


def _cube_quads() -> list[tuple[int, ...]]:
    """The unit cube's 6 faces, counter-clockwise seen from outside."""
    index = {v: i for i, v in enumerate(CORNERS)}
    faces = [((0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0)),
             ((0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)),
             ((0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)),
             ((0, 1, 0), (0, 1, 1), (1, 1, 1), (1, 1, 0)),
             ((0, 0, 0), (0, 0, 1), (0, 1, 1), (0, 1, 0)),
             ((1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1))]
    return [tuple(index[p] for p in face) for face in faces]


def random_cube_atlas(degree: int = 3, spans: int = 2, seed: int = 1) -> AtlasSurface:
    """A closed atlas on the cube's layout with random control points and weights."""
    rnd = random.Random(seed)
    quads = _cube_quads()
    inner = spans + degree - 2
    edges = atlas_edges(quads).edges

    def jitter(count: int) -> list[tuple[float, float, float]]:
        return [(rnd.random(), rnd.random(), rnd.random()) for _ in range(count)]

    edge_points, face_points = jitter(len(edges) * inner), jitter(len(quads) * inner ** 2)
    weights = [0.5 + rnd.random() for _ in range(8 + len(edge_points) + len(face_points))]
    return AtlasSurface(degree, spans, CORNERS, quads, edge_points, face_points, weights)


def _side_point(surface, side: int, t: float):
    return surface.evaluate(*((t, 0.0), (1.0, t), (t, 1.0), (0.0, t))[side])


def test_cube_layout_is_closed():
    table = atlas_edges(_cube_quads())
    assert len(table.edges) == 12
    assert table.border_edges == []
    assert all(len(pairs) == 2 for pairs in table.faces)


@pytest.mark.parametrize("degree,spans", [(1, 1), (2, 1), (3, 2), (3, 4)])
def test_neighbouring_patches_share_their_border_curve_exactly(degree, spans):
    atlas = random_cube_atlas(degree, spans)
    table = atlas.edges
    for (f, k), (g, m) in table.faces:
        same_way = table.sides[f][k][1] == table.sides[g][m][1]
        for t in (0.0, 0.13, 0.5, 0.77, 1.0):
            a = _side_point(atlas.patch_surface(f), k, t)
            b = _side_point(atlas.patch_surface(g), m, t if same_way else 1.0 - t)
            assert a == b


def test_layout_errors_name_the_problem():
    quads = _cube_quads()
    with pytest.raises(ValueError, match="consistently oriented"):
        atlas_edges(quads[:1] + [tuple(reversed(quads[0]))[1:] + (quads[0][3],)] + quads[1:])
    with pytest.raises(ValueError, match="4 distinct"):
        atlas_edges([(0, 1, 1, 2)])
    with pytest.raises(ValueError, match="weights must be finite"):
        atlas = random_cube_atlas()
        AtlasSurface(3, 2, atlas.vertices, atlas.quads, atlas.edge_points, atlas.face_points,
                     [0.0] * atlas.control_point_count)
