"""The bench's pleat measures (``bench.pleats``) on hand-made meshes."""

from __future__ import annotations

import numpy as np
import pytest

from bench.pleats import folded_pairs, turned_share

SQUARE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64)


def test_folded_pairs_count_only_folds_inside_one_patch_and_weld_the_edge():
    # (0, 1, 2) faces +z; (5, 6, 4) shares its edge (0, 2) through copies of those corners
    # and folds back under it (normal about -z: cosine -0.99)
    vertices = np.concatenate([SQUARE, [[0.8, 0.2, 0.01], [0, 0, 0], [1, 1, 0]]])
    faces = np.array([[0, 1, 2], [5, 6, 4]])
    assert folded_pairs(vertices, faces, np.array([0, 0])) == (1, 1)
    assert folded_pairs(vertices, faces, np.array([0, 1])) == (0, 0)  # a crease between
    # a flat square: no fold; a right angle (cosine 0) is no fold either
    flat = np.array([[0, 1, 2], [0, 2, 3]])
    assert folded_pairs(SQUARE, flat, np.zeros(2, int)) == (0, 0)
    bent = SQUARE.copy()
    bent[3] = [1, 1, 1]  # (0, 2, 3) stands up over the diagonal
    assert folded_pairs(bent, flat, np.zeros(2, int)) == (0, 0)


def test_turned_share_is_the_area_facing_against_the_base():
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    level = SQUARE.copy()
    level[3] = [0.9, 0.1, 0]  # (0, 2, 3) turned over: area 0.4, against 0.5 kept
    assert turned_share((SQUARE, faces), (level, faces)) == pytest.approx(0.4 / 0.9)
    assert turned_share((SQUARE, faces), (SQUARE, faces)) == 0.0
    # a level whose walls masks leave cells out draws some of the base's triangles
    assert turned_share((SQUARE, faces), (level, faces[1:])) == 1.0
    assert turned_share((SQUARE, faces), (level, faces[:1])) == 0.0
    with pytest.raises(ValueError, match="same resolution"):
        turned_share((SQUARE, faces), (SQUARE, np.array([[0, 1, 3]])))


def test_turned_share_matches_triangles_past_two_million_vertices():
    # vertex numbers up to 2^22 - 1: a key (f0 w + f1) w + f2 with w = 2^22 wraps int64 and
    # (a, b, c), (a + 2^20, b, c) collide; the second faces -z in both, the first +z
    a, b, c = 1 << 19, 7, (1 << 22) - 1
    vertices = np.zeros((1 << 22, 3))  # pages untouched but these rows
    vertices[[b, c, a + (1 << 20)]] = [[1, 0, 0], [0, 1, 0], [1, 1, 0]]
    faces = np.array([[a, b, c], [a + (1 << 20), b, c]])
    assert turned_share((vertices, faces), (vertices, faces[1:])) == 0.0
    flipped = vertices.copy()
    flipped[a + (1 << 20)] = [-1, -1, 0]  # now it faces +z, against the base's -z
    assert turned_share((vertices, faces), (flipped, faces[1:])) == 1.0
