"""A triangle mesh's edges paired by one sort (fitter.fitting.atlas.mesh_edges), against
brute-force counts, and clean_mesh's check of a mesh MeshLab would leave as it is."""

from collections import Counter

import numpy as np
import pytest
import trimesh

from fitter.fitting.atlas import surface as atlas_surface
from fitter.fitting.atlas.mesh_edges import mesh_edges, vertex_fans
from fitter.fitting.atlas.surface import clean_as_it_is, clean_mesh, manifold_problems


def _brute_problems(faces: np.ndarray) -> dict:
    directed = Counter((int(f[k]), int(f[(k + 1) % 3])) for f in faces for k in range(3))
    undirected = Counter(tuple(sorted(e)) for f in faces
                         for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))
                         for e in [tuple(int(x) for x in e)])
    return {"nonmanifold_edges": sum(c > 2 for c in undirected.values()),
            "misoriented_edges": sum(c > 1 for c in directed.values()),
            "border_edges": sum(c == 1 for c in undirected.values()),
            "edges": len(undirected)}


def _brute_fans(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """At each vertex, the faces around it joined when they share an edge at it (a
    union-find per vertex)."""
    fans = np.zeros(n_vertices, np.int64)
    for v in range(n_vertices):
        around = [t for t, f in enumerate(faces) if v in f]
        parent = {t: t for t in around}

        def root(t, parent=parent):
            while parent[t] != t:
                t = parent[t]
            return t

        for i, s in enumerate(around):
            for t in around[i + 1:]:
                if len(set(faces[s]) & set(faces[t])) >= 2:  # an edge, and v is on it
                    parent[root(s)] = root(t)
        fans[v] = len({root(t) for t in around})
    return fans


def _sphere(subdivisions=2):
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def _bowtie_spheres():
    """Two spheres touching at one vertex (the second's vertex 0 is the first's)."""
    v, f = _sphere(1)
    w = 2 * v[0] - v  # mirrored through the first's vertex 0: turned inside out, so
    g = f + len(v)  # its faces are turned back
    g[g == len(v)] = 0
    return np.vstack([v, w]), np.vstack([f, g[:, ::-1]])


def _random_meshes():
    rng = np.random.default_rng(4)
    v, f = _sphere(1)
    yield "sphere", v, f
    yield "open cap", v, f[v[f].mean(axis=1)[:, 2] > 0]
    yield "bowtie", *_bowtie_spheres()
    yield "fin", v, np.vstack([f, [[f[0, 0], f[0, 1], 5]]])
    flipped = f.copy()
    flipped[:7] = flipped[:7, ::-1]
    yield "seven flipped", v, flipped
    for k in range(3):  # random soups of triangles on few vertices: every kind of defect
        soup = rng.integers(0, 12, size=(30, 3))
        soup = soup[(soup[:, 0] != soup[:, 1]) & (soup[:, 1] != soup[:, 2])
                    & (soup[:, 0] != soup[:, 2])]
        yield f"soup {k}", rng.normal(size=(12, 3)), soup


@pytest.mark.parametrize("name, vertices, faces", list(_random_meshes()))
def test_edge_counts_match_a_brute_force_count(name, vertices, faces):
    assert manifold_problems(faces) == _brute_problems(faces)
    table = mesh_edges(faces)
    m = len(faces)
    for e, twin in enumerate(table.twins):  # a twin runs the other way on the same edge
        if twin >= 0:
            t, j, s, k = e % m, e // m, twin % m, twin // m
            assert (faces[t, j], faces[t, (j + 1) % 3]) == (faces[s, (k + 1) % 3], faces[s, k])
    problems = table.problems
    if not problems["nonmanifold_edges"] and not problems["misoriented_edges"]:
        assert np.array_equal(vertex_fans(table, len(vertices)),
                              _brute_fans(faces, len(vertices))), name


def test_two_spheres_on_one_vertex_have_two_fans_there():
    v, f = _bowtie_spheres()
    fans = vertex_fans(mesh_edges(f), len(v))
    copy = len(v) // 2  # the second sphere's own vertex 0, which no face uses
    assert fans[0] == 2 and fans[copy] == 0 and np.all(np.delete(fans, [0, copy]) == 1)
    # a disk's border vertices are one open fan each
    v, f = _sphere(1)
    cap = f[v[f].mean(axis=1)[:, 2] > 0]
    used = np.unique(cap)
    assert np.all(vertex_fans(mesh_edges(cap), len(v))[used] == 1)


def _defects():
    v, f = _sphere(1)
    yield "clean", v, f, True
    yield "a vertex no face uses", np.vstack([v, [[3.0, 3, 3]]]), f, False
    twice = f.copy()
    t = int(np.flatnonzero((f == 0).any(axis=1))[0])
    twice[t][twice[t] == 0] = len(v)  # one face uses the copy of vertex 0
    yield "a vertex twice", np.vstack([v, v[:1]]), twice, False
    flat = v.copy()
    a, b, c = f[0]
    flat[c] = 0.5 * (flat[a] + flat[b])
    yield "a face without area", flat, f, False
    yield "a face with a vertex twice", v, np.vstack([f, [[0, 0, 1]]]), False
    yield "an edge of three faces", v, np.vstack([f, [[f[0, 1], f[0, 0], 13]]]), False
    yield "a face turned over", v, np.vstack([f[:1, ::-1], f[1:]]), False
    yield "two spheres on one vertex", *_bowtie_spheres(), False
    extra = len(v)
    w = np.vstack([v, [[3.0, 0, 0], [3.0, 1, 0], [3.0, 0, 1]]])
    yield "two faces on the same vertices", w, np.vstack(
        [f, [[extra, extra + 1, extra + 2], [extra, extra + 2, extra + 1]]]), False


@pytest.mark.parametrize("name, vertices, faces, clean", list(_defects()))
def test_a_mesh_is_clean_as_it_is_only_when_meshlab_would_change_nothing(
        name, vertices, faces, clean, monkeypatch):
    assert (clean_as_it_is(vertices, faces) is not None) == clean, name
    if clean:  # the same mesh and repairs as MeshLab's filters give
        fast = clean_mesh(vertices, faces, name)
        monkeypatch.setattr(atlas_surface, "clean_as_it_is", lambda *a: None)
        slow = clean_mesh(vertices, faces, name)
        assert np.array_equal(fast[0], slow[0]) and np.array_equal(fast[1], slow[1])
        assert fast[2] == slow[2]
