"""Rate-distortion (issue 6, the project's headline): bytes a visitor downloads vs deviation.

For each real scan a single patch represents (``../shared/data``: Happy Buddha
range scan 0, the Bali mask, the Laurana bust; skipped when absent):

* **Tessera**: ``fit_scan`` at several base grids with the detail pyramid
  (no texture); a point per (grid, level L): bytes of ``base.tsp`` plus every
  ``detail/K/*.tsd`` with ``K <= L`` as stored, against the RMS and max of the
  deviation ``e`` of every covered scan point (``fitter.detail``: the distance
  to the refined surface at the point's foot point along the normal, an upper
  bound of its true distance).
* **Draco**: the scan's own mesh (a point cloud is meshed by Delaunay
  triangulation of its foot points in the patch's ``(u, v)``, triangles with an
  edge over 4x the median left out), restricted to the covered points,
  quadric-decimated (fast-simplification) to a range of face counts and
  Draco-encoded (DracoPy, compression level 10) at 10..14 quantisation bits;
  bytes of the Draco buffer against the exact point-to-triangle distance of
  the same covered points to the decoded mesh.

For each budget 8 KB .. 512 KB the frontier of each method is its lowest RMS
at or under the budget. Writes ``bench/results/rate_distortion.json`` and
``bench/results/rate_distortion.png``.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from bench import RESULTS, print_table, write_results

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"
SCANS = {
    "happy-buddha scan 0": DATA / "happy-buddha-rangescans" / "happyStandRight_0.ply.gz",
    "bali-mask": DATA / "bali-mask" / "mask.obj",
    "laurana-bust": DATA / "laurana-bust" / "laurana.ply",
}
GRIDS = (12, 20, 32)
LEVELS = {12: 5, 20: 5, 32: 6}  # detail levels 0..L-1 per base grid (level 5: the 512 KB end)
STEP_FACTORS = (1.0, 2.0, 4.0)  # detail quantisation step / the level's remaining RMS
BUDGETS_KB = (8, 16, 32, 64, 128, 256, 512)
DRACO_BITS = (10, 11, 12, 14)


def _point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray,
                             c: np.ndarray) -> np.ndarray:
    """Exact distance of points ``p (m, 3)`` to triangles ``(a, b, c)`` (each ``(m, 3)``),
    by the closest-point regions of Ericson, *Real-Time Collision Detection*, 5.1.5."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    safe = np.where(np.abs(denom) > 1e-300, denom, 1.0)
    v, w = vb / safe, vc / safe
    q = a + ab * v[:, None] + ac * w[:, None]  # interior
    def seg(x, y, t):
        return x + (y - x) * np.clip(t, 0, 1)[:, None]
    def proj(x, y, pts):
        d = y - x
        return np.einsum("ij,ij->i", pts - x, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)
    outside = (va <= 0) | (vb <= 0) | (vc <= 0) | ~(np.abs(denom) > 1e-300)
    if outside.any():  # on an edge or a vertex: the nearest of the three edges
        o = outside
        po = p[o]
        cand = [seg(a[o], b[o], proj(a[o], b[o], po)), seg(a[o], c[o], proj(a[o], c[o], po)),
                seg(b[o], c[o], proj(b[o], c[o], po))]
        dist = np.stack([np.linalg.norm(p[o] - x, axis=1) for x in cand])
        q[o] = np.choose(dist.argmin(axis=0)[:, None], cand)
    return np.linalg.norm(p - q, axis=1)


def mesh_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                  k: int = 16) -> np.ndarray:
    """Distance of each point to the mesh: exact to the best of the ``k`` triangles whose
    centroids are nearest plus every triangle at the nearest vertex."""
    from scipy.spatial import cKDTree

    tri = vertices[faces]
    k = min(k, len(faces))
    _, cand = cKDTree(tri.mean(axis=1)).query(points, k=k)
    cand = cand.reshape(len(points), -1)
    best = np.full(len(points), np.inf)
    for col in range(cand.shape[1]):
        t = tri[cand[:, col]]
        best = np.minimum(best, _point_triangle_distance(points, t[:, 0], t[:, 1], t[:, 2]))
    return best


def _covered_mesh(scan, cov, u, v) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial import Delaunay

    covered = cov.covered
    if scan.faces is not None:
        faces = scan.faces[covered[scan.faces].all(axis=1)]
    else:
        idx = np.flatnonzero(covered)
        tri = idx[Delaunay(np.column_stack([u[idx], v[idx]])).simplices]
        p = scan.points
        edges = np.stack([np.linalg.norm(p[tri[:, a]] - p[tri[:, b]], axis=1)
                          for a, b in ((0, 1), (1, 2), (2, 0))], axis=1).max(axis=1)
        faces = tri[edges <= 4 * np.median(edges)]
    used = np.unique(faces)
    remap = np.full(len(scan.points), -1)
    remap[used] = np.arange(len(used))
    return scan.points[used], remap[faces]


def draco_points(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> list[dict]:
    import DracoPy
    import fast_simplification

    rows = []
    targets = [f for f in (250, 500, 1000, 2000, 4000, 8000, 16000, 32000, 64000)
               if f < len(faces)] + [len(faces)]
    for target in targets:
        if target < len(faces):
            v, f = fast_simplification.simplify(vertices.astype(np.float32),
                                                faces.astype(np.int32),
                                                target_reduction=1.0 - target / len(faces))
        else:
            v, f = vertices.astype(np.float32), faces.astype(np.int32)
        for bits in DRACO_BITS:
            buf = DracoPy.encode(v, f, quantization_bits=bits, compression_level=10)
            mesh = DracoPy.decode(buf)
            dv = np.asarray(mesh.points, dtype=float)
            df = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
            d = mesh_distance(points, dv, df)
            rows.append({"method": "draco", "faces": int(len(df)), "bits": bits,
                         "bytes": len(buf), "rms": float(np.sqrt(np.mean(d**2))),
                         "max": float(d.max())})
    return rows


def tessera_points(scan, out: Path) -> list[dict]:
    """A point per (base grid, quantisation step factor, level): the bundle ``fit_scan``
    writes (step factor ``STEP_FACTOR``), and the same base with the detail pyramid refitted
    at the other ``STEP_FACTORS`` (coarser or finer quantisation of every level)."""
    from client_py import read_patch
    from fitter.detail import STEP_FACTOR, fit_detail
    from fitter.error import deviations
    from fitter.nurbs import PatchModel
    from fitter.parameterize import choose_projection
    from fitter.pipeline import FitOptions, fit_scan

    normals = _unit_normals(scan)
    cov = choose_projection(scan.points, normals, "auto")
    proj = cov.projection
    local = proj.local(scan.points)
    u, v, _ = proj.to_uvh(scan.points)
    rows = []
    for grid in GRIDS:
        start = time.perf_counter()
        bundle = fit_scan(scan, out / f"g{grid}", FitOptions(grid=(grid, grid), texture=False,
                                                              detail_levels=LEVELS[grid]))
        m = bundle.manifest
        wall = time.perf_counter() - start
        detail = m["tiles"]["detail"]
        base = m["files"]["base.tsp"]
        rows.append({"method": "tessera", "grid": grid, "step": None, "level": -1,
                     "bytes": base, "rms": detail["base"]["rms"], "max": detail["base"]["max"],
                     "fit_s": wall})
        levels = {STEP_FACTOR: [(lev["level"], lev["bytes_total"], lev["rms"], lev["max"],
                                 lev["tiles"]) for lev in detail["levels"]]}
        model = PatchModel.from_surface(read_patch((bundle.path / "base.tsp").read_bytes()))
        dev = deviations(model, local, u, v, proj.periodic_u)
        for factor in STEP_FACTORS:
            if factor != STEP_FACTOR:
                pyramid = fit_detail(model, local, dev, cov.covered, proj.periodic_u, LEVELS[grid],
                                     step_factor=factor)
                levels[factor] = [(lev.level, lev.bytes_total, lev.rms, lev.max,
                                   len(lev.tiles)) for lev in pyramid.levels]
        for factor, per_level in levels.items():
            total = base
            for level, size, rms, worst, tiles in per_level:
                total += size
                rows.append({"method": "tessera", "grid": grid, "step": factor,
                             "level": level, "bytes": total, "rms": rms, "max": worst,
                             "tiles": tiles, "fit_s": wall})
    return rows


def _unit_normals(scan) -> np.ndarray | None:
    """The scan's normals, unit length, as ``fit_scan`` uses them to choose the map."""
    if scan.normals is None:
        return None
    length = np.linalg.norm(scan.normals, axis=1, keepdims=True)
    return scan.normals / length if np.all(length > 0) else None


def frontier(rows: list[dict], budget: int) -> dict | None:
    fit = [r for r in rows if r["bytes"] <= budget]
    return min(fit, key=lambda r: r["rms"]) if fit else None


def run() -> dict | None:
    try:
        import DracoPy  # noqa: F401
        import fast_simplification  # noqa: F401
    except ImportError:
        print("skipping: DracoPy and fast-simplification are needed "
              "(pip install -e '.[bench]')")
        return None
    from fitter.io import load_scan
    from fitter.parameterize import choose_projection

    results, table = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for name, path in SCANS.items():
            if not path.exists():
                print(f"skipping {name}: {path} is absent")
                continue
            start = time.perf_counter()
            scan = load_scan(path)
            ours = tessera_points(scan, Path(tmp) / name.replace(" ", "_"))
            cov = choose_projection(scan.points, _unit_normals(scan), "auto")
            u, v, _ = cov.projection.to_uvh(scan.points)
            vertices, faces = _covered_mesh(scan, cov, u, v)
            theirs = draco_points(scan.points[cov.covered], vertices, faces)
            summary = []
            for kb in BUDGETS_KB:
                a, b = frontier(ours, kb * 1024), frontier(theirs, kb * 1024)
                summary.append({"budget_kb": kb, "tessera": a, "draco": b})
                table.append([name, kb,
                              "-" if a is None else f"{a['rms']:.3g}",
                              "-" if a is None else f"{a['max']:.3g}",
                              "-" if a is None else (f"g{a['grid']} L{a['level']}"
                                                     + (f" s{a['step']:g}" if a["step"] else "")
                                                     + f" {a['bytes']}"),
                              "-" if b is None else f"{b['rms']:.3g}",
                              "-" if b is None else f"{b['max']:.3g}",
                              "-" if b is None else f"{b['faces']}f {b['bits']}b {b['bytes']}",
                              "-" if a is None or b is None else
                              ("tessera" if a["rms"] < b["rms"] else "draco")])
            results[name] = {"units": scan.units, "points": int(len(scan.points)),
                             "covered": int(cov.covered.sum()), "mesh_faces": int(len(faces)),
                             "meshed_by": "dataset faces" if scan.faces is not None
                             else "Delaunay of the foot points in (u, v)",
                             "tessera": ours, "draco": theirs, "frontier": summary,
                             "wall_s": time.perf_counter() - start}
    print_table("rate-distortion: lowest RMS at or under each budget (covered scan points)",
                ["data", "KB", "tessera RMS", "max", "config, bytes", "draco RMS", "max",
                 "config, bytes", "lower RMS"], table)
    _plot(results)
    record = {"budgets_kb": list(BUDGETS_KB), "grids": list(GRIDS),
              "step_factors": list(STEP_FACTORS), "levels": {str(g): n for g, n in LEVELS.items()},
              "data": results}
    write_results("rate_distortion", record)
    return record


def _plot(results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not results:
        return
    fig, axes = plt.subplots(1, len(results), figsize=(5.2 * len(results), 4.4), dpi=100,
                             squeeze=False)
    for ax, (name, res) in zip(axes[0], results.items(), strict=True):
        for key, style, label in (("tessera", "o-", "Tessera base + detail"),
                                  ("draco", "s--", "decimation + Draco")):
            pts = sorted((r["bytes"] / 1024, r["rms"]) for r in res[key])
            best, hull = np.inf, []
            for x, y in pts:  # lower-left frontier
                if y < best:
                    best = y
                    hull.append((x, y))
            ax.loglog(*zip(*pts, strict=True), style[0], alpha=0.25, ms=3)
            ax.loglog(*zip(*hull, strict=True), style, label=label)
        ax.axvspan(8, 512, color="0.93", zorder=0)
        ax.set_xlabel("bytes downloaded (KB)")
        ax.set_ylabel(f"RMS deviation ({res['units']})")
        ax.set_title(name)
        ax.legend()
    fig.tight_layout()
    RESULTS.mkdir(parents=True, exist_ok=True)
    fig.savefig(RESULTS / "rate_distortion.png", metadata={"Software": "Tessera"})
    plt.close(fig)
