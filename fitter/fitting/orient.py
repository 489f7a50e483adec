"""The object's view: which way is up and which side faces the visitor, in scan coordinates.

The viewer and the gallery thumbnails show an object upright and from the front; this module
decides both directions once, at fit time, and says which rule decided (the manifest's
``view``, ``docs/format.md``).

Up, the first rule that applies:

1. ``option`` — the fit option ``up`` (``+x`` ... ``-z``) given by the admin;
2. ``format`` — the scan's format records it: glTF 2.0 is +Y up by its specification
   (section 3.4, "Coordinate System and Units": +Y up, the front faces +Z); a Stanford
   ``.conf`` registration is +Y up because its scans are views from a turntable turning
   about the scanner's +Y axis (the ``bmesh`` rotations of the Stanford files are about Y:
   ``happyStandRight_24`` is ``q = (0, -0.21, 0, 0.98)``, 24 degrees about Y);
3. ``base plane`` — busts and statues stand on a flat base: the largest plane of the
   convex hull (the plane the object would rest on, a cut base or the rim of an open one)
   when it is large (at least ``BASE_MIN_SHARE`` of the object's footprint on it) and lies
   at one end of a tall object (height along its normal at least ``BASE_MIN_HEIGHT`` times
   the footprint's size); up is minus its outward normal. A one-sided scan (a mask, a
   relief, a range scan: the mean unit normal has length above ``ONE_SIDED``) has no base:
   its rim plane is its back;
4. ``convention`` — else +Y, the graphics convention the formats without an up axis
   (OBJ, PLY, STL) follow in practice (Stanford's scanner frames, the glTF exporters);
   for a flat scan (a relief or block face: its least principal extent under ``FLAT``
   times its largest) +Y turned to the nearer of its two in-plane principal axes, so a
   relief lying askew in its frame shows with its edges level (``convention (relief)``).

Front (perpendicular to up), the first rule that applies:

1. ``format`` — glTF: +Z (the same section of the specification), made perpendicular to up;
2. ``surface`` — with faces or normals: the horizontal direction ``d`` that the most surface
   faces, ``argmax_d [A(n . d > cos 60) - A(n . d < -cos 60)]`` over 72 azimuths, ``A`` the
   surface area (faces) or point count (normals) facing that way. For a one-sided scan this
   is the side the scanner saw; for a bust the face and chest (eyes, nose, lips, drapery:
   more area per projected area than the back of a head, since for a closed surface the
   projected areas of the two sides are equal, ``sum n dA = 0``);
3. ``convention`` — point clouds without normals: +Z made perpendicular to up (Stanford
   range images are seen from +Z, the scanner looking down -Z); for a flat scan, its
   plane's normal on the +Z side.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from .io.scan import Scan

#: the fit option ``up``'s values other than ``auto``, as unit vectors
AXES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0),
        "-y": (0.0, -1.0, 0.0), "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}
#: scan formats whose files record their up axis (see the module's docstring): format -> up
FORMAT_UP = {"gltf": "+y", "glb": "+y", "conf": "+y"}
#: scan formats whose files record their front: format -> front
FORMAT_FRONT = {"gltf": "+z", "glb": "+z"}
CONVENTION_UP = "+y"
CONVENTION_FRONT = "+z"
HULL_SAMPLE = 20_000  # points whose convex hull is searched for a base plane
BASE_ANGLE_DEG = 10.0  # hull facets within this angle of an axis cap that end
BASE_MIN_SHARE = 0.2  # the cap's area / the bounding box's footprint across the axis
BASE_MIN_HEIGHT = 0.9  # the object's extent along the axis / sqrt(footprint)
BASE_SLAB = 0.02  # points within this fraction of the extent from an end stand on it
FLAT = 0.2  # least / largest principal extent below this: a flat scan (a relief, depth < width / 5)
ONE_SIDED = 0.35  # |mean unit normal| above this: a one-sided scan (mask, relief, range scan)


@dataclass(frozen=True)
class View:
    """The object's up and front: unit vectors ``(3,)`` in scan coordinates, perpendicular,
    and the rules that chose them (``option``, ``format``, ``base plane``, ``surface``,
    ``convention``)."""

    up: tuple[float, float, float]
    front: tuple[float, float, float]
    up_source: str
    front_source: str

    def to_manifest(self) -> dict:
        """The manifest's ``view``: ``up``, ``front`` (rounded to 6 decimals) and sources."""
        return {"up": [round(float(c), 6) for c in self.up],
                "front": [round(float(c), 6) for c in self.front],
                "up_source": self.up_source, "front_source": self.front_source}


@dataclass(frozen=True)
class Surface:
    """``K`` surface elements: unit ``normals (K, 3)``, ``area (K,)`` and ``detail (K,)``."""

    normals: np.ndarray
    area: np.ndarray
    detail: np.ndarray


def _unit(vector: np.ndarray) -> np.ndarray:
    return vector / np.linalg.norm(vector)


def surface_elements(scan: Scan) -> Surface | None:
    """The scan's surface as unit normals and weights: its triangles (normal of
    ``(b - a) x (c - a)``, ``area``, and ``detail`` the sum of the dihedral angles to its
    edge neighbours, ``trimesh.Trimesh.face_adjacency_angles``) or, without faces, its point
    normals (area and detail 1); None for a point cloud without normals."""
    if scan.faces is not None:
        mesh = trimesh.Trimesh(scan.points, scan.faces, process=False)
        area = mesh.area_faces
        keep = area > 0
        detail = np.zeros(len(area))
        pairs, angles = mesh.face_adjacency, mesh.face_adjacency_angles
        np.add.at(detail, pairs[:, 0], angles)
        np.add.at(detail, pairs[:, 1], angles)
        return Surface(mesh.face_normals[keep], area[keep], detail[keep])
    if scan.normals is not None:
        normals = np.asarray(scan.normals, dtype=np.float64)
        length = np.linalg.norm(normals, axis=1)
        keep = length > 0
        ones = np.ones(int(keep.sum()))
        return Surface(normals[keep] / length[keep, None], ones, ones)
    return None


def one_sidedness(surface: Surface) -> float:
    """``|sum_k A_k n_k| / sum_k A_k``: 0 for a closed surface, near 1 for a surface seen
    from one side (a relief, a mask, a single range scan)."""
    return float(np.linalg.norm(surface.area @ surface.normals) / surface.area.sum())


def base_end(points: np.ndarray, seed: int = 0) -> tuple[str, dict] | None:
    """The axis end ``(+x ... -z)`` of the base the object stands on, and the measures that
    chose it; None when no end qualifies.

    For each end ``a`` (a coordinate axis, signed): ``flat``, the area of the convex hull's
    facets (of ``HULL_SAMPLE`` points) whose outward normal is within ``BASE_ANGLE_DEG`` of
    ``a``, over the bounding box's footprint across ``a`` (a cut base or the rim of an open
    one caps the hull with a plane); ``height``, the extent along ``a`` over
    ``sqrt(footprint)``; ``slab``, the share of points within ``BASE_SLAB`` of the extent
    from that end (a real base has surface there, the hull's cap over a raised arm or wing
    tips has little). An end qualifies with ``flat >= BASE_MIN_SHARE`` and
    ``height >= BASE_MIN_HEIGHT`` (a base lies at an end of a standing object, not along
    the back of a mask); the qualifying end with the largest ``slab`` wins.
    """
    rng = np.random.default_rng(seed)
    sample = points if len(points) <= HULL_SAMPLE else points[
        rng.choice(len(points), HULL_SAMPLE, replace=False)]
    try:
        hull = ConvexHull(sample)
    except QhullError:
        return None
    normals = hull.equations[:, :3]
    corners = sample[hull.simplices]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                          corners[:, 2] - corners[:, 0]), axis=1)
    lo, hi = sample.min(axis=0), sample.max(axis=0)
    extent = hi - lo
    best = None
    for name, axis in AXES.items():
        k = int(np.flatnonzero(axis)[0])
        footprint = float(np.prod(np.delete(extent, k)))
        if not footprint > 0:
            continue
        flat = float(areas[normals @ np.array(axis) > np.cos(np.radians(BASE_ANGLE_DEG))].sum())
        end = lo[k] if axis[k] < 0 else hi[k]
        measures = {"flat": flat / footprint, "height": float(extent[k] / np.sqrt(footprint)),
                    "slab": float(np.mean(np.abs(sample[:, k] - end) <= BASE_SLAB * extent[k]))}
        if (measures["flat"] >= BASE_MIN_SHARE and measures["height"] >= BASE_MIN_HEIGHT
                and (best is None or measures["slab"] > best[1]["slab"])):
            best = (name, measures)
    return best


def flat_frame(points: np.ndarray) -> np.ndarray | None:
    """The principal axes ``(3, 3)`` (rows, by decreasing extent) of a flat scan: its least
    extent (max - min along the axis) under ``FLAT`` times its largest; None otherwise."""
    centred = points - points.mean(axis=0)
    _, _, axes = np.linalg.svd(centred[:: max(1, len(points) // HULL_SAMPLE)],
                               full_matrices=False)
    extent = np.ptp(centred @ axes.T, axis=0)
    return axes if extent[2] < FLAT * extent[0] else None


def _signed_towards(axis: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return axis if axis @ reference >= 0 else -axis


def find_up(scan: Scan, requested: str = "auto",
            surface: Surface | None = None) -> tuple[np.ndarray, str]:
    """The unit up direction ``(3,)`` and the rule that chose it (module docstring).

    Raises
    ------
    ValueError
        ``requested`` is not ``auto`` or one of :data:`AXES`.
    """
    if requested != "auto":
        if requested not in AXES:
            raise ValueError(f"up must be auto or one of {', '.join(AXES)}, got {requested!r}")
        return np.array(AXES[requested]), "option"
    fmt = scan.source.get("format")
    if fmt in FORMAT_UP:
        return np.array(AXES[FORMAT_UP[fmt]]), "format"
    if surface is None or one_sidedness(surface) <= ONE_SIDED:
        found = base_end(scan.points)
        if found is not None:
            return -np.array(AXES[found[0]]), "base plane"
    convention = np.array(AXES[CONVENTION_UP])
    axes = flat_frame(scan.points)
    if axes is not None:
        nearer = max(axes[:2], key=lambda axis: abs(axis @ convention))
        return _signed_towards(nearer, convention), "convention (relief)"
    return convention, "convention"


def _horizontal(direction: np.ndarray, up: np.ndarray) -> np.ndarray | None:
    flat = direction - (direction @ up) * up
    length = np.linalg.norm(flat)
    return flat / length if length > 1e-6 else None


def detail_front(surface: Surface, up: np.ndarray) -> np.ndarray | None:
    """The horizontal unit direction of ``sum_k D_k A_k n_k`` (detail ``D``, area ``A``,
    normal ``n``), the module docstring's front rule 2; None when it is (nearly) vertical."""
    return _horizontal((surface.detail * surface.area) @ surface.normals, up)


def find_view(scan: Scan, up: str = "auto") -> View:
    """The object's :class:`View` (module docstring): up by the first rule that applies,
    then front perpendicular to it.

    Raises
    ------
    ValueError
        ``up`` is not ``auto`` or one of :data:`AXES`.
    """
    surface = surface_elements(scan)
    up_vector, up_source = find_up(scan, up, surface)
    front, front_source = None, "convention"
    fmt = scan.source.get("format")
    if fmt in FORMAT_FRONT:
        front = _horizontal(np.array(AXES[FORMAT_FRONT[fmt]]), up_vector)
        front_source = "format"
    if front is None and surface is not None:
        front = detail_front(surface, up_vector)
        front_source = "surface detail"
    axes = flat_frame(scan.points) if front is None else None
    if axes is not None:
        front = _horizontal(_signed_towards(axes[2], np.array(AXES[CONVENTION_FRONT])),
                            up_vector)
    if front is None:
        front = _horizontal(np.array(AXES[CONVENTION_FRONT]), up_vector)
        if front is None:  # up is +-z: the convention's front is along up
            front = _horizontal(np.array(AXES["-y"]), up_vector)
        front_source = "convention"
    return View(tuple(up_vector.tolist()), tuple(front.tolist()), up_source, front_source)
