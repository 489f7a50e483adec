"""The distance of every scan point to the triangle mesh a visitor is drawn.

One implementation for the fitter's error report of an atlas bundle and for the
benchmarks (``bench/scoring.py``): the nearest of ALL triangles by ``open3d``'s ray-casting
scene (a bounding-volume hierarchy, single precision), then the exact point-to-triangle
distance to it in double precision (the closest-point regions of Ericson, *Real-Time
Collision Detection*, 2005, §5.1.5), in chunks so memory stays ``O(chunk)`` whatever the
point count (checked against a brute force in tests/test_atlas_pipeline.py). It replaced
a search among the 16 triangles with the nearest centroids: 41 s of CPU for the 1.1 M
points of the Happy Buddha, and an upper bound only where a large triangle's centroid is
far from its nearest part.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from client_py.errors import TesseraError
from client_py.mesh_arrays import mesh_arrays

CHUNK = 200_000


@dataclass(frozen=True)
class DrawnMesh:
    """The welded mesh a visitor's browser draws of an atlas at one resolution
    (``client_py.atlas_mesh.tessellate_atlas``), as float64/int64 arrays.

    Attributes
    ----------
    vertices : ndarray, shape (V, 3)
        The drawn float32 positions.
    faces : ndarray, shape (T, 3)
    patches : ndarray, shape (V,)
        Each vertex's patch (``AtlasMesh.patches``).
    uvs : ndarray, shape (V, 2)
        Its ``(u, v)`` in that patch.
    """

    vertices: np.ndarray
    faces: np.ndarray
    patches: np.ndarray
    uvs: np.ndarray


def drawn_mesh(atlas, resolution: int, detail: dict | None = None) -> DrawnMesh:
    """``tessellate_atlas(atlas, resolution, detail)`` with the numpy kernel, as a
    :class:`DrawnMesh` (``detail``: ``{patch: [tiles]}``, ``None`` or empty for the base).

    Without shading normals (``normals=False``): nothing here reads them, and the drawn
    positions, triangles, ``(u, v)`` and patches are the same bytes either way
    (tests/test_atlas_mesh.py); the Happy Buddha's finest drawn mesh in 3.9 CPU-s instead of
    5.5."""
    from client_py.atlas_mesh import tessellate_atlas

    mesh = tessellate_atlas(atlas, resolution, detail or None, kernel="numpy", normals=False)
    return DrawnMesh(
        *mesh_arrays(mesh), np.frombuffer(mesh.patches, dtype=np.uintc).astype(np.int64),
        np.frombuffer(mesh.uvs, dtype=np.float32).reshape(-1, 2).astype(float))


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray,
                                c: np.ndarray) -> np.ndarray:
    """The closest point of triangle ``(a_i, b_i, c_i)`` to ``p_i``, all ``(m, 3)``
    (Ericson §5.1.5: the Voronoi regions of the vertices, edges and face)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp, cp = p - b, p - c
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    proper = np.abs(denom) > 1e-300
    safe = np.where(proper, denom, 1.0)
    q = a + ab * (vb / safe)[:, None] + ac * (vc / safe)[:, None]
    outside = (va <= 0) | (vb <= 0) | (vc <= 0) | ~proper
    if outside.any():  # the nearest point of the three edges
        o = outside
        best = None
        best_d = None
        for x, y in ((a[o], b[o]), (a[o], c[o]), (b[o], c[o])):
            e = y - x
            t = np.einsum("ij,ij->i", p[o] - x, e) / np.maximum(np.einsum("ij,ij->i", e, e),
                                                               1e-300)
            cand = x + e * np.clip(t, 0.0, 1.0)[:, None]
            dist = np.einsum("ij,ij->i", p[o] - cand, p[o] - cand)
            if best is None:
                best, best_d = cand, dist
            else:
                closer = dist < best_d
                best[closer], best_d[closer] = cand[closer], dist[closer]
        q[o] = best
    return q


SCENES = 2  # meshes whose ray-casting scene (BVH) is kept for the next query (mesh_scene)
_scenes: list[tuple[np.ndarray, np.ndarray, object]] = []  # (vertices, faces, scene), newest first
_scenes_lock = threading.Lock()


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two float32 or uint32 arrays hold the same bits (``-0.0`` is not ``0.0``)."""
    return a.shape == b.shape and np.array_equal(a.view(np.uint32), b.view(np.uint32))


def mesh_scene(vertices: np.ndarray, faces: np.ndarray):
    """``open3d``'s ``RaycastingScene`` of the mesh ``vertices (V, 3) float32, faces (T, 3)
    uint32``, kept for the :data:`SCENES` meshes queried last.

    The fit queries the same meshes again and again (each round's reverse rows, the far
    samples, the layout's triangle distances, each detail level's far nodes: the 15-scan
    Happy Buddha's fit made 119 queries, nearly all of its 187,000-triangle surface and of
    the layout's stand-in), and ``open3d`` builds a scene's bounding-volume hierarchy at
    its first query (0.07-0.12 s for that surface at load 10). A
    mesh is the same mesh when its float32 vertices and uint32 faces have the same bits
    (compared here, about 1 ms for those triangles), so a kept scene answers exactly as a
    new one built from those arrays would. Threads may share one."""
    import open3d as o3d

    with _scenes_lock:
        for k, (v, f, scene) in enumerate(_scenes):
            if _same_bits(v, vertices) and _same_bits(f, faces):
                _scenes.insert(0, _scenes.pop(k))
                return scene
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces))
        # its first query builds the hierarchy: here, under the lock, so that threads
        # querying it at once (fit.layout_candidates) only read it
        scene.compute_closest_points(o3d.core.Tensor(vertices[:1]))
        _scenes.insert(0, (vertices.copy(), faces.copy(), scene))
        del _scenes[SCENES:]
        return scene


def forget_scenes() -> None:
    """Drop the kept scenes (:func:`mesh_scene`), and with them their meshes and
    hierarchies: called when a fit ends, so a server process that fits many scans holds
    none of the last fit's meshes."""
    with _scenes_lock:
        _scenes.clear()


def nearest_triangles(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray
                      ) -> np.ndarray:
    """The index of the triangle nearest to each point, shape (N,): ``open3d``'s
    ``RaycastingScene.compute_closest_points`` (a BVH over every triangle, Embree, in
    single precision, on every core; the scene kept for the next query of the same mesh,
    :func:`mesh_scene`), in chunks of ``CHUNK`` points."""
    import open3d as o3d

    scene = mesh_scene(np.ascontiguousarray(vertices, np.float32),
                   np.ascontiguousarray(faces, np.uint32))
    out = np.empty(len(points), np.int64)
    for start in range(0, len(points), CHUNK):
        query = o3d.core.Tensor(np.ascontiguousarray(points[start:start + CHUNK], np.float32))
        out[start:start + CHUNK] = scene.compute_closest_points(query)["primitive_ids"].numpy()
    return out


def barycentric(q: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates ``(N, 3)`` of points ``q`` in triangles ``(a, b, c)``, all
    ``(N, 3)`` (Ericson, *Real-Time Collision Detection*, §3.4; a degenerate triangle gives
    its first vertex)."""
    v0, v1, v2 = b - a, c - a, q - a
    d00, d01, d11 = (np.einsum("ij,ij->i", x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    ok = np.abs(den) > 1e-300
    safe = np.where(ok, den, 1.0)
    wb = np.where(ok, (d11 * d20 - d01 * d21) / safe, 0.0)
    wc = np.where(ok, (d00 * d21 - d01 * d20) / safe, 0.0)
    w = np.clip(np.stack([1.0 - wb - wc, wb, wc], axis=1), 0.0, 1.0)
    return w / w.sum(axis=1, keepdims=True)


def closest_points_on_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closest point of the mesh ``(vertices (V, 3), faces (T, 3))`` to each of
    ``points (N, 3)``: ``(distance (N,), triangle (N,), closest (N, 3))``.

    The nearest triangle of every point is found over all triangles
    (:func:`nearest_triangles`, single precision), the closest point on it and the
    distance are then computed in double precision (:func:`closest_points_on_triangles`).

    Raises
    ------
    ValueError
        An empty mesh or point set.
    """
    points = np.asarray(points, dtype=float)
    vertices, faces = np.asarray(vertices), np.asarray(faces)  # converted where used (below)
    if len(points) == 0 or len(faces) == 0:
        raise ValueError(f"a point-to-mesh distance needs points and triangles, got {len(points)} "
                         f"points and {len(faces)} triangles")
    nearest = nearest_triangles(points, vertices, faces)
    out = np.empty(len(points))
    out_q = np.empty_like(points)
    for start in range(0, len(points), CHUNK):
        p = points[start:start + CHUNK]
        t = np.asarray(vertices[faces[nearest[start:start + CHUNK]]], dtype=float)
        q = closest_points_on_triangles(p, t[:, 0], t[:, 1], t[:, 2])
        out[start:start + CHUNK] = np.linalg.norm(p - q, axis=1)
        out_q[start:start + CHUNK] = q
    return out, nearest, out_q


#: :func:`farther_than`'s margin, a share of the largest ``|coordinate|``: far above
#: ``open3d``'s single-precision rounding of the points and triangles (``2^-24``, a few
#: times over), which can make :func:`closest_points_on_mesh` choose a triangle whose
#: distance passes the nearest one's by that much
FLOAT32_MARGIN = 1e-6


def farther_than(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, reach: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points of ``points (N, 3)`` farther than ``reach`` from the mesh ``(vertices
    (V, 3), faces (T, 3))``: their indices (ascending), distances and closest points, each
    as :func:`closest_points_on_mesh` of every point gives it, shapes ``(K,)``, ``(K,)``,
    ``(K, 3)``.

    A distance to a set is at most that to any of its members, so a point within ``reach``
    of a vertex of a triangle is within ``reach`` of the mesh: a k-d tree of the triangles'
    vertices (nearest-neighbour queries bounded by ``reach``, which stop early) lets those
    go, and only the others are measured (the BVH of every triangle, per point: the same
    numbers as for all points). A vertex must be within ``reach - m`` to let its point go,
    ``m`` = :data:`FLOAT32_MARGIN` of the largest ``|coordinate|``: the BVH compares
    distances in single precision. Where the mesh follows the points (a detail level's
    drawn nodes against the scan, a cloud against its own surface) nearly every point goes:
    the 15-scan Happy Buddha's 2.55 M level-1 nodes, its 1.10 M points.

    Raises
    ------
    ValueError
        An empty mesh, or ``reach`` not a finite number >= 0.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=float)
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0:
        raise ValueError("a point-to-mesh distance needs triangles, got none")
    if isinstance(reach, bool) or not isinstance(reach, (int, float)) \
            or not math.isfinite(reach) or reach < 0:
        raise ValueError(f"reach must be a finite number >= 0, got {reach!r}")
    used = np.zeros(len(vertices), bool)
    used[faces.reshape(-1)] = True  # np.unique(faces)'s set, without its sort
    corners = vertices[used]
    scale = max(float(np.abs(corners).max()), float(np.abs(points).max(initial=0.0)))
    bound = reach - FLOAT32_MARGIN * (scale + reach)
    unsure = np.arange(len(points))
    if bound > 0 and len(points):
        gap, _ = cKDTree(corners).query(points, distance_upper_bound=bound, workers=-1)
        unsure = np.flatnonzero(~(gap <= bound))
    if not len(unsure):
        return unsure, np.zeros(0), np.zeros((0, 3))
    dist, _, closest = closest_points_on_mesh(points[unsure], vertices, faces)
    far = dist > reach
    return unsure[far], dist[far], closest[far]


def signed_point_mesh_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`closest_points_on_mesh` with the distance signed: positive on the side the
    closest triangle's normal ``(b - a) x (c - a)`` points to. Returns ``(d (N,),
    triangle (N,), closest (N, 3))``.

    Raises
    ------
    ValueError
        An empty mesh or point set.
    """
    points = np.asarray(points, dtype=float)
    dist, tri, q = closest_points_on_mesh(points, vertices, faces)
    t = np.asarray(np.asarray(vertices)[np.asarray(faces)[tri]], dtype=float)
    normal = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return np.where(np.einsum("ij,ij->i", points - q, normal) < 0, -dist, dist), tri, q


def signed_distance_to_drawn(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`signed_point_mesh_distance` of a drawn mesh passed as its float32 vertices
    and uint32 faces (exactly the :class:`DrawnMesh`'s values, half the bytes to send to
    a :class:`MeasuringProcess`). They are measured as they are: the scene takes them
    without a copy, and only the points' nearest triangles are made float64 (exactly: the
    same numbers as the whole mesh converted to float64 and int64 and back for the scene,
    which for the dense vase's 18.7 M-triangle finest level took 1 s and 1 GB)."""
    return signed_point_mesh_distance(points, vertices, faces)


@dataclass(frozen=True)
class FarPlace:
    """One place where a drawn mesh lies far from the scan (:func:`far_places`).

    Attributes
    ----------
    distance : float
        The largest distance of its samples to the scan.
    samples : int
        How many far samples it holds (with area-uniform samples: its area over the
        samples' density).
    where : ndarray, shape (3,)
        Its farthest sample.
    facing : float
        ``|n . t|`` at that sample, ``n`` the drawn mesh's unit normal and ``t`` the unit
        direction to its closest point on the scan: near 1 the scan lies along the normal,
        where a displacement along it (the detail levels') reaches it; near 0 it lies
        beside the drawn surface (a web across a gap, a fin), where only the base's shape
        can.
    """

    distance: float
    samples: int
    where: np.ndarray
    facing: float


def far_places(samples: np.ndarray, normals: np.ndarray, closest: np.ndarray, reach: float,
               link: float) -> list[FarPlace]:
    """The places where samples of a drawn mesh lie farther than ``reach`` from the scan,
    farthest first.

    ``samples (N, 3)`` of the drawn mesh with their unit ``normals (N, 3)`` and their
    ``closest (N, 3)`` points on the scan (:func:`closest_points_on_mesh`). The samples
    farther than ``reach`` are linked when closer than ``link`` to each other (a
    ``cKDTree`` pair query) and each connected component of those links (single-linkage
    clustering) is one :class:`FarPlace`. A largest distance alone does not say whether it
    is one fin or a scattering of them, nor whether the scan lies along the drawn normal
    (the detail's job) or beside it (the base's layout): the Bali mask's level 0 (main
    732fe1f, the benchmark's 200,000 samples) has five places over 1 % of the diagonal
    (1.44, 1.30, 1.28, 1.20, 1.04 %; areas 0.036, 0.016, 0.005, 0.005, 0.002 %), facing
    0.03, 0.38, 0.03, 0.80, 0.26, each on a layout edge whose two triangles bridge the gap
    between two parts of the mask (a tusk and the face beside it) that the layout's
    stand-in keeps apart.

    Raises
    ------
    ValueError
        Shapes that do not match, or ``reach`` or ``link`` not a finite number > 0.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    samples, normals, closest = (np.asarray(x, dtype=float) for x in (samples, normals, closest))
    if samples.ndim != 2 or samples.shape[1] != 3 or normals.shape != samples.shape \
            or closest.shape != samples.shape:
        raise ValueError(f"samples, normals and closest must share a shape (N, 3), got "
                         f"{samples.shape}, {normals.shape}, {closest.shape}")
    for name, value in (("reach", reach), ("link", link)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    toward = closest - samples
    distance = np.linalg.norm(toward, axis=1)
    far = np.flatnonzero(distance > reach)
    if len(far) == 0:
        return []
    pairs = cKDTree(samples[far]).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(far), len(far)))
    _, label = connected_components(graph, directed=False)
    places = []
    for members in np.split(far[np.argsort(label, kind="stable")],
                            np.cumsum(np.bincount(label))[:-1]):
        top = members[np.argmax(distance[members])]
        places.append(FarPlace(float(distance[top]), int(len(members)), samples[top].copy(),
                               float(abs(normals[top] @ toward[top]) / distance[top])))
    return sorted(places, key=lambda place: -place.distance)


class MeasuringProcessError(TesseraError, RuntimeError):
    """A :class:`MeasuringProcess` that failed, died or answered short."""


class MeasuringProcess:
    """:func:`signed_distance_to_drawn` of one point set against one or more meshes in a
    fresh Python process (``python -m fitter.fitting.atlas.measure``), which imports
    ``open3d`` as soon as it starts.

    ``open3d`` holds the GIL while it builds its BVH (one core: 6 s for the 9.4 M triangles
    of the Happy Buddha's finest level) and queries it, so no thread of this process runs
    beside it; another process does. The arrays travel through pipes as raw bytes
    (``dtype`` and shape on a line, then the data): no pickle, and no re-import of the
    caller's ``__main__`` (as ``multiprocessing``'s spawn would). :meth:`measure` and
    :meth:`measure_all` block in pipe I/O, which releases the GIL: call them from a thread.

    Raises
    ------
    OSError
        When no process can be started.
    """

    def __init__(self) -> None:
        if not sys.executable:  # an embedded interpreter: no Python to start
            raise OSError("no Python executable to start a measuring process with")
        root = str(Path(__file__).resolve().parents[3])  # the folder holding fitter/
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            x for x in (root, os.environ.get("PYTHONPATH")) if x)}
        self.process = subprocess.Popen([sys.executable, "-m", "fitter.fitting.atlas.measure"],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)

    def measure(self, points: np.ndarray, vertices: np.ndarray, faces: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`signed_distance_to_drawn` ``(points, vertices, faces)`` in the process,
        which then exits."""
        return self.measure_all(points, [(vertices, faces)])[0]

    def measure_all(self, points: np.ndarray, meshes: list[tuple[np.ndarray, np.ndarray]]
                    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """:func:`signed_distance_to_drawn` ``(points, vertices, faces)`` of each ``(vertices,
        faces)`` of ``meshes``, in order, in the process, which then exits.

        The process measures each mesh as it arrives and answers once its input has ended:
        an answer written while this side still writes the next mesh would fill the one
        pipe while this side fills the other, each waiting for the other to read."""
        try:
            _write_arrays(self.process.stdin, [np.asarray(points, dtype=float)])
            for vertices, faces in meshes:
                _write_arrays(self.process.stdin, [np.asarray(vertices, dtype=np.float32),
                                                   np.asarray(faces, dtype=np.uint32)])
            self.process.stdin.close()
            out = [tuple(_read_arrays(self.process.stdout, 3)) for _ in meshes]
        except (OSError, ValueError) as exc:
            raise MeasuringProcessError(f"the measuring process failed: {exc}") from exc
        finally:
            code = self.process.wait()
        if code != 0:
            raise MeasuringProcessError(f"the measuring process exited with {code}")
        return out

    def close(self) -> None:
        """End the process if it still runs (an error elsewhere)."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        for stream in (self.process.stdin, self.process.stdout):
            try:
                stream.close()
            except BrokenPipeError:  # bytes still buffered for a process that died: moot
                pass


def _write_arrays(stream, arrays: list[np.ndarray]) -> None:
    for a in arrays:
        a = np.ascontiguousarray(a)
        stream.write(f"{a.dtype.str} {' '.join(map(str, a.shape))}\n".encode())
        stream.write(a.reshape(-1).view(np.uint8))
    stream.flush()


def _read_arrays(stream, count: int, at_end: bool = False) -> list[np.ndarray] | None:
    """``count`` arrays from ``stream``; with ``at_end``, ``None`` when the stream ends
    before the first (else that is an error)."""
    out = []
    for _ in range(count):
        line = stream.readline()
        if not line and at_end and not out:
            return None
        dtype, *shape = line.decode().split()
        size = np.dtype(dtype).itemsize * math.prod(int(x) for x in shape)
        data = stream.read(size)
        if len(data) != size:
            raise ValueError(f"an array of {size} bytes ended after {len(data)}")
        out.append(np.frombuffer(data, dtype=dtype).reshape([int(x) for x in shape]))
    return out


def _serve() -> None:
    """The :class:`MeasuringProcess` side: the points on stdin, then each mesh's two
    arrays until stdin ends; three arrays per mesh out on the original stdout once it has
    (anything a library prints goes to stderr)."""
    import open3d  # noqa: F401  (imported while the caller still tessellates)

    answer = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    points, = _read_arrays(sys.stdin.buffer, 1)
    answers = []
    while (mesh := _read_arrays(sys.stdin.buffer, 2, at_end=True)) is not None:
        answers.append(signed_distance_to_drawn(points, *mesh))
    for arrays in answers:
        _write_arrays(answer, list(arrays))
    answer.close()


def point_mesh_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                        signed: bool = False) -> np.ndarray:
    """Distance of each of ``points (N, 3)`` to the mesh ``(vertices (V, 3), faces (T, 3))``
    (:func:`closest_points_on_mesh`; ``signed``: :func:`signed_point_mesh_distance`).

    Raises
    ------
    ValueError
        An empty mesh or point set.
    """
    if signed:
        return signed_point_mesh_distance(points, vertices, faces)[0]
    return closest_points_on_mesh(points, vertices, faces)[0]


if __name__ == "__main__":
    _serve()
