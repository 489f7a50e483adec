"""Pleats of an atlas bundle's base and the level-0 area turned over against it.

Two measures from session 11 (``docs/benchmarks.md``, "Whole objects"; first written as a
scratch script on the unmerged branch w21-pleats):

- **in-patch folded pairs**: the base drawn at :data:`PAIR_RESOLUTION` samples a patch side;
  two of its triangles that share an edge and lie in the same patch, with unit normals
  ``n_1 · n_2 < cos 120°``, fold over each other: a pleat. Edges are matched by their
  welded end positions, so triangles of neighbouring patches meet too (those pairs are not
  counted: they are creases between patches, not pleats inside one).
- **turned-over share**: the base and level 0 drawn at level 0's resolution have the same
  triangles in the same order; the share of level 0's area whose triangle's normal points
  against the base triangle at the same ``(u, v)`` (``n_0 · n_b < 0``).

``python -m bench.pleats BUNDLE`` prints both.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from client_py.mesh_arrays import mesh_arrays

PAIR_RESOLUTION = 5  # samples a patch side of the base for the folded pairs
FOLD_COSINE = -0.5  # cos 120°


def _drawn(manifest: dict, bundle: Path, level: int, resolution: int
           ) -> tuple[np.ndarray, np.ndarray]:
    from client_py.bundle import tessellate_bundle

    mesh = tessellate_bundle(manifest, lambda name: (bundle / name).read_bytes(), level=level,
                             resolution=resolution, kernel="numpy")
    return mesh_arrays(mesh)


def unit_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ``(T, 3)`` and areas ``(T,)`` of the triangles."""
    cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                     vertices[faces[:, 2]] - vertices[faces[:, 0]])
    length = np.linalg.norm(cross, axis=1)
    return cross / np.maximum(length, 1e-300)[:, None], 0.5 * length


def folded_pairs(vertices: np.ndarray, faces: np.ndarray, triangle_patch: np.ndarray,
                 cosine: float = FOLD_COSINE) -> tuple[int, int]:
    """Pairs of triangles sharing an edge (ends welded at ``1e-9``) in the same patch whose
    normals' cosine is below ``cosine``, and the number of patches holding one."""
    normals, _ = unit_normals(vertices, faces)
    _, welded = np.unique(np.round(vertices, 9), axis=0, return_inverse=True)
    welded = welded.reshape(-1)[faces]
    edges = np.sort(np.concatenate([welded[:, [0, 1]], welded[:, [1, 2]], welded[:, [2, 0]]]),
                    axis=1)
    owner = np.tile(np.arange(len(faces)), 3)
    key = edges[:, 0] * (int(welded.max()) + 1) + edges[:, 1]
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    same = key[1:] == key[:-1]
    a, b = owner[:-1][same], owner[1:][same]
    folded = (np.einsum("ij,ij->i", normals[a], normals[b]) < cosine) \
        & (triangle_patch[a] == triangle_patch[b])
    return int(folded.sum()), int(len(np.unique(triangle_patch[a[folded]])))


def turned_share(base: tuple[np.ndarray, np.ndarray], level: tuple[np.ndarray, np.ndarray]
                 ) -> float:
    """Share of ``level``'s area whose triangles face against ``base``'s same triangles.

    A level whose walls masks leave cells out (docs/format.md, "Atlas detail packs",
    version 5) draws a subset of the base's triangles, with the same vertex numbers at the
    same resolution: each is matched to the base's triangle of the same three vertices."""
    if base[1].shape != level[1].shape:
        # each triangle's key: its row's rank among the distinct rows of both (exact at any
        # vertex count, where a key (f0 w + f1) w + f2 wraps int64 past 2^21 vertices)
        _, key = np.unique(np.concatenate([base[1], level[1]]), axis=0, return_inverse=True)
        key = key.reshape(-1)
        keys = [key[:len(base[1])], key[len(base[1]):]]
        order = np.argsort(keys[0])
        at = np.searchsorted(keys[0], keys[1], sorter=order)
        found = order[np.minimum(at, len(order) - 1)]
        if len(base[1]) < len(level[1]) or not np.array_equal(keys[0][found], keys[1]):
            raise ValueError(f"the base has {len(base[1])} triangles, the level "
                             f"{len(level[1])}, not all of them the base's: draw both at the "
                             "same resolution")
        base = (base[0], base[1][found])
    nb, _ = unit_normals(*base)
    nl, area = unit_normals(*level)
    return float(area[np.einsum("ij,ij->i", nb, nl) < 0].sum() / area.sum())


def pleat_stats(bundle: Path) -> dict:
    """``{'base_pairs_120', 'base_pleated_patches', 'l0_turned_share'}`` of an atlas bundle.

    The base drawn at :data:`PAIR_RESOLUTION` has ``2 (r - 1)²`` triangles a patch, patch
    after patch (``client_py.atlas_mesh``), which gives each triangle's patch.
    """
    from client_py.bundle import plan_levels

    bundle = Path(bundle)
    manifest = json.loads((bundle / "manifest.json").read_text())
    vertices, faces = _drawn(manifest, bundle, -1, PAIR_RESOLUTION)
    per_patch = 2 * (PAIR_RESOLUTION - 1) ** 2
    patches = (manifest.get("base") or {}).get("patches")
    if patches is not None and len(faces) != per_patch * patches:
        raise ValueError(f"the base drawn at {PAIR_RESOLUTION} has {len(faces)} triangles, not "
                         f"{per_patch} for each of its {patches} patches")
    pairs, pleated = folded_pairs(vertices, faces, np.arange(len(faces)) // per_patch)
    plan = next((p for p in plan_levels(manifest) if p.level == 0), None)
    share = None if plan is None else turned_share(  # a base with no detail level: none
        _drawn(manifest, bundle, -1, plan.resolution), _drawn(manifest, bundle, 0, plan.resolution))
    return {"base_pairs_120": pairs, "base_pleated_patches": pleated, "l0_turned_share": share}


if __name__ == "__main__":
    print(pleat_stats(Path(sys.argv[1])))
