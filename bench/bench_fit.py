"""Fit benchmark (issue 4): RMS, patch bytes and time of Tessera's methods beside splipy and
scipy, feature-adaptive sampling on real data, and a 10^7-point fit.

Data: the Happy Buddha range scan 0 (with its ``.conf`` pose) and the Bali mask
from ``../shared/data`` (skipped when absent), and the generated example relief.
40x40 control points, degree 2, for every fit.

1. Methods, same run: Tessera's ``linear`` (the paper's initial solution: the
   baseline of the RMS target), ``paper`` (as published) and ``tessera`` (the
   default), and two independent least-squares spline fits on the same
   uniform clamped 40x40 degree-2 grid, heights over the scan's PCA plane:
   scipy's ``LSQBivariateSpline`` (FITPACK, scattered points) and splipy's
   ``surface_factory.least_square_fit`` on the section matrix where it is full
   (splipy fits grids only; with holes, splipy's basis matrices and the
   normal equations of the scattered points). RMS is the foot-point deviation of every
   covered scan point (the points Tessera's map covers) from the surface; for
   Tessera, from the *decoded* ``base.tsp``.
2. Feature-adaptive sampling: the tessera fit from a 20,000-point sample,
   uniform (``feature_strength=0``) against feature-adaptive (the default), with
   the error in the feature regions (the top decile of local-PCA surface
   variation among covered points) and elsewhere.
3. A generated 10^7-point height field through ``fit_scan`` from a binary PLY,
   in a subprocess: wall time, CPU time and peak resident memory.

Writes ``bench/results/fit.json``.

With ``--points`` (``python -m bench fit --points 1e7 1e8``) it runs the out-of-core
benchmark (issue 16, :func:`run_large`) instead: generated float32 binary PLYs of those
sizes, each fitted with default options in a subprocess under ``/usr/bin/time -v`` (wall,
CPU, peak resident memory, stage times, load average), the same cloud written as E57
(``--e57-points``: same ``base.tsp`` bytes? time against the PLY's) and fitted on
LocalClusters of 1 and 2 workers (``--cluster-points``); with ``--vase-vertices 4.5e6``
also (alone, without ``--points``) the example vase as a closed mesh of that size, an atlas
of its working mesh with every vertex measured; writes ``bench/results/fit_large.json``.
"""

from __future__ import annotations

import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench import print_table, write_results

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"
SCANS = {
    "happy-buddha scan 0": DATA / "happy-buddha-rangescans" / "happyStandRight_0.ply.gz",
    "bali-mask": DATA / "bali-mask" / "mask.obj",
}
GRID = (40, 40)
DEGREE = 2
FEATURE_SAMPLES = 20_000

BIG_SCRIPT = """
import json, resource, sys, time
from pathlib import Path
import numpy as np
from fitter.demo import write_scan_ply
from fitter.fitting.examples import relief_height
from fitter.fitting.options import FitOptions
from fitter.fitting.pipeline import fit_scan
n = int(sys.argv[1]); out = Path(sys.argv[2])
rng = np.random.default_rng(0)
x = rng.uniform(-100, 100, n); y = rng.uniform(-70, 70, n)
pts = np.column_stack([x, y, relief_height(x, y) + rng.normal(0, 0.05, n)])
write_scan_ply(out / "big.ply", pts)
del pts, x, y
start, cpu = time.perf_counter(), time.process_time()
bundle = fit_scan(out / "big.ply", out / "bundle", FitOptions(detail_levels=0, texture=False))
wall, cpu = time.perf_counter() - start, time.process_time() - cpu
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"points": n, "wall_s": wall, "cpu_s": cpu, "peak_mb": peak,
                  "rms": bundle.manifest["stats"]["rms"],
                  "bytes": bundle.manifest["files"]["base.tsp"],
                  "timings": bundle.manifest["timings"]}))
"""


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _options(**kw):
    """Base-patch options: the detail and texture layers (issue 6) are not timed here."""
    from fitter.fitting.options import FitOptions

    return FitOptions(grid=GRID, degree=DEGREE, detail_levels=0, texture=False, **kw)


def _tessera_row(name: str, scan, method: str, out: Path) -> dict:
    from fitter.fitting.pipeline import fit_scan

    start, cpu = time.perf_counter(), _cpu()
    bundle = fit_scan(scan, out / f"{name}-{method}".replace(" ", "_"), _options(method=method))
    wall, cpu = time.perf_counter() - start, _cpu() - cpu
    m = bundle.manifest
    return {"data": name, "method": method, "points": m["provenance"]["points"],
            "projection": m["projection"]["kind"], "coverage": m["projection"]["coverage"],
            "rms": m["stats"]["rms"], "max": m["stats"]["max"], "p99": m["stats"]["p99"],
            "bytes": m["files"]["base.tsp"], "bits": m["base"]["bits"], "wall_s": wall,
            "cpu_s": cpu}


def _height_model(knots_u: np.ndarray, knots_v: np.ndarray, heights: np.ndarray, proj):
    """The height field ``h(u, v)`` over the plane map as a ``PatchModel``: ``x, y`` are
    linear in ``u, v``, hence exact with control points at the Greville abscissae."""
    from fitter.fitting.nurbs import PatchModel

    def greville(t: np.ndarray, n: int) -> np.ndarray:
        return np.array([t[i + 1:i + DEGREE + 1].mean() for i in range(n)])

    n_u, n_v = heights.shape
    gu, gv = greville(knots_u, n_u), greville(knots_v, n_v)
    GU, GV = np.meshgrid(gu, gv, indexing="ij")
    Q = proj.from_uvh(GU.ravel(), GV.ravel(), heights.ravel()).reshape(n_u, n_v, 3)
    return PatchModel((DEGREE, DEGREE), (knots_u, knots_v), Q, np.ones((n_u, n_v)))


def _library_rows(name: str, scan) -> list[dict]:
    """scipy's and splipy's least-squares fits of the height over the PCA plane, measured
    on the points Tessera's chosen map covers."""
    import splipy
    import splipy.surface_factory
    from scipy.interpolate import LSQBivariateSpline
    from scipy.sparse import identity
    from scipy.sparse.linalg import spsolve

    from fitter.fitting.error import deviations
    from fitter.fitting.nurbs import PatchModel
    from fitter.fitting.parameterize import choose_projection
    from fitter.fitting.sections import section_matrix, section_shape

    points = scan.points
    covered = choose_projection(points, None, "auto").covered
    plane = choose_projection(points, None, "plane").projection
    u, v, h = plane.to_uvh(points)
    local = plane.local(points)
    knots = np.concatenate([[0.0] * DEGREE, np.linspace(0, 1, GRID[0] - DEGREE + 1),
                            [1.0] * DEGREE])
    interior = knots[DEGREE + 1:-DEGREE - 1]
    rows = []

    def row(library: str, model, seconds: float, cpu: float) -> dict:
        dev = deviations(model, local[covered], u[covered], v[covered])
        a = np.abs(dev.d)
        return {"data": name, "method": library, "points": len(points), "projection": "plane",
                "coverage": float(covered.mean()), "rms": float(np.sqrt(np.mean(a**2))),
                "max": float(a.max()), "p99": float(np.percentile(a, 99)), "bytes": None,
                "bits": None, "wall_s": seconds, "cpu_s": cpu}

    start, cpu = time.perf_counter(), _cpu()
    spline = LSQBivariateSpline(u, v, h, interior, interior, bbox=[0, 1, 0, 1],
                                kx=DEGREE, ky=DEGREE)
    tx, ty, c = spline.tck
    heights = np.asarray(c).reshape(len(tx) - DEGREE - 1, len(ty) - DEGREE - 1)
    wall, cpu = time.perf_counter() - start, _cpu() - cpu
    rows.append(row("scipy LSQBivariateSpline", _height_model(tx, ty, heights, plane),
                    wall, cpu))

    start, cpu = time.perf_counter(), _cpu()
    basis = splipy.BSplineBasis(order=DEGREE + 1, knots=knots)
    sm = section_matrix(plane, u, v, h, section_shape(len(points), GRID))
    if sm.full:
        surface = splipy.surface_factory.least_square_fit(
            sm.points, [basis, basis], [sm.u, sm.v])
        model = PatchModel((DEGREE, DEGREE), (knots, knots),
                           np.asarray(surface.controlpoints, dtype=float), np.ones(GRID))
        label = "splipy least_square_fit (section matrix)"
    else:
        # splipy fits grids only: its basis matrices, then the normal equations with a
        # ridge of 1e-10 of their trace for the control points no point reaches
        A = _collocation(np.asarray(basis.evaluate(u)), np.asarray(basis.evaluate(v)))
        AtA = (A.T @ A).tocsc()
        ridge = 1e-10 * AtA.diagonal().sum() / AtA.shape[0]
        heights = spsolve(AtA + ridge * identity(AtA.shape[0]), A.T @ h).reshape(GRID)
        model = _height_model(knots, knots, heights, plane)
        label = f"splipy basis, scattered LSQ ({int((~sm.valid).sum())} grid holes)"
    wall, cpu = time.perf_counter() - start, _cpu() - cpu
    rows.append(row(label, model, wall, cpu))
    return rows


def _collocation(Bu: np.ndarray, Bv: np.ndarray):
    """Sparse ``A (m, n_u n_v)`` with ``A_k,(a n_v + b) = N_a(u_k) N_b(v_k)`` from the dense
    one-direction basis matrices (``DEGREE + 1`` non-zeros per row)."""
    import scipy.sparse as sp

    m, n_v = Bv.shape
    k = DEGREE + 1
    ia = np.sort(np.argsort(-Bu, axis=1)[:, :k], axis=1)
    ib = np.sort(np.argsort(-Bv, axis=1)[:, :k], axis=1)
    r = np.arange(m)[:, None]
    data = Bu[r, ia][:, :, None] * Bv[r, ib][:, None, :]
    cols = ia[:, :, None] * n_v + ib[:, None, :]
    return sp.csr_matrix((data.ravel(), cols.ravel(), np.arange(0, m * k * k + 1, k * k)),
                         shape=(m, Bu.shape[1] * n_v))


def _feature_rows(name: str, scan, out: Path) -> list[dict]:
    """The tessera fit from ``FEATURE_SAMPLES`` points, uniform against feature-adaptive."""
    from client_py import read_patch
    from fitter.fitting.error import deviations
    from fitter.fitting.features import surface_variation
    from fitter.fitting.nurbs import PatchModel
    from fitter.fitting.parameterize import choose_projection
    from fitter.fitting.pipeline import fit_scan

    points = scan.points
    cov = choose_projection(points, None, "auto")
    covered = cov.covered
    variation = surface_variation(points)
    feature = covered & (variation >= np.quantile(variation[covered], 0.9))
    rest = covered & ~feature
    proj = cov.projection
    u, v, _ = proj.to_uvh(points)
    rows = []
    for label, strength in (("uniform", 0.0), ("feature-adaptive", None)):
        kw = {"samples": FEATURE_SAMPLES}
        if strength is not None:
            kw["feature_strength"] = strength
        opts = _options(**kw)
        bundle = fit_scan(scan, out / f"features-{label}", opts)
        model = PatchModel.from_surface(read_patch((bundle.path / "base.tsp").read_bytes()))
        d = np.abs(deviations(model, proj.local(points), u, v, proj.periodic_u).d)
        rows.append({"data": name, "sampling": label, "strength": opts.feature_strength,
                     "samples": FEATURE_SAMPLES, "feature_points": int(feature.sum()),
                     "feature_rms": float(np.sqrt(np.mean(d[feature] ** 2))),
                     "feature_p99": float(np.percentile(d[feature], 99)),
                     "feature_max": float(d[feature].max()),
                     "rest_rms": float(np.sqrt(np.mean(d[rest] ** 2))),
                     "rms": float(np.sqrt(np.mean(d[covered] ** 2)))})
    return rows


def _big(points: int) -> dict | None:
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.run([sys.executable, "-c", BIG_SCRIPT, str(points), tmp],
                              capture_output=True, text=True, cwd=ROOT,
                              env=dict(os.environ, PYTHONPATH=str(ROOT)))
    if proc.returncode != 0:
        print(f"{points}-point fit failed:", proc.stderr[-2000:])
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_methods(big_points: int = 10_000_000) -> dict:
    from fitter.fitting.examples import relief_scan
    from fitter.fitting.io import load_scan
    from fitter.fitting.io.scan import Scan

    inputs = {"generated relief 80k": Scan.from_array(relief_scan())}
    for name, path in SCANS.items():
        if path.exists():
            inputs[name] = load_scan(path)
        else:
            print(f"skipping {name}: {path} is absent")
    rows, features = [], []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        for name, scan in inputs.items():
            for method in ("linear", "paper", "tessera"):
                rows.append(_tessera_row(name, scan, method, out))
            rows += _library_rows(name, scan)
            if name in SCANS:
                features += _feature_rows(name, scan, out)
    linear = {r["data"]: r["rms"] for r in rows if r["method"] == "linear"}
    for r in rows:
        r["rms_vs_linear"] = r["rms"] / linear[r["data"]]
    print_table(f"fit, {GRID[0]}x{GRID[1]} degree {DEGREE}: RMS of the covered scan points "
                "(Tessera: from the decoded base.tsp)",
                ["data", "method", "points", "map", "cover", "RMS", "RMS/linear", "max",
                 "bytes", "bits", "wall s", "CPU s"],
                [[r["data"], r["method"], r["points"], r["projection"], f"{r['coverage']:.3f}",
                  f"{r['rms']:.4g}", f"{r['rms_vs_linear']:.3f}", f"{r['max']:.4g}",
                  r["bytes"] or "-", r["bits"] or "-", f"{r['wall_s']:.2f}",
                  f"{r['cpu_s']:.2f}"] for r in rows])
    if features:
        print_table(f"feature-adaptive sampling, {FEATURE_SAMPLES} samples (features: top "
                    "decile of surface variation)",
                    ["data", "sampling", "feature RMS", "feature P99", "feature max",
                     "rest RMS", "all RMS"],
                    [[r["data"], r["sampling"], f"{r['feature_rms']:.4g}",
                      f"{r['feature_p99']:.4g}", f"{r['feature_max']:.4g}",
                      f"{r['rest_rms']:.4g}", f"{r['rms']:.4g}"] for r in features])
    big = _big(big_points) if big_points else None
    if big:
        print_table("generated height field, fit_scan from a binary PLY",
                    ["points", "wall s", "CPU s", "peak MB", "RMS", "bytes"],
                    [[big["points"], f"{big['wall_s']:.1f}", f"{big['cpu_s']:.1f}",
                      f"{big['peak_mb']:.0f}", f"{big['rms']:.4g}", big["bytes"]]])
    result = {"rows": rows, "features": features, "big": big}
    write_results("fit", result)
    return result


# ------------------------------------------------------------ out of core (issue 16)
GENERATE_CHUNK = 1 << 22
LARGE_FIT_SCRIPT = """
import json, sys, time
from pathlib import Path
from fitter.fitting.io.limits import InputLimits
from fitter.fitting.options import FitOptions
from fitter.fitting.pipeline import fit_scan
from fitter.fitting.stream import DaskBlocks
scan, out, workers = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
client = None
if workers:
    from distributed import Client, LocalCluster
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=None)
    client = Client(cluster)
start = time.perf_counter()
# the default input limit (20 million points) refuses 10^8: a genuine scan, as --max-points says
bundle = fit_scan(scan, out, FitOptions(), limits=InputLimits(max_points=10**9),
                  blocks=DaskBlocks(client) if client else None)
wall = time.perf_counter() - start
m = bundle.manifest
print(json.dumps({"wall_s": wall, "timings": m["timings"], "rms": m["stats"]["rms"],
                  "points": m["provenance"]["points"],
                  "working_set": m["provenance"].get("working_set"),
                  "detail_levels": len(m["tiles"]["detail"]["levels"]),
                  "base_bytes": m["files"].get("base.tsp", m["files"].get("base.tsa")),
                  "patches": m["base"].get("patches", 1),
                  "within_0.5%": (m.get("coverage") or {}).get("within_0.5%"),
                  "max_relative": m["stats"]["max_relative"]}))
"""


def write_large_ply(path: Path, points: int) -> None:
    """A float32 binary PLY of ``points`` samples of the example relief (noise 0.05 units),
    written in chunks of ``GENERATE_CHUNK`` (each its own seeded generator), so that
    generating 10^8 points takes one chunk of memory. Its header declares metres, the unit
    an E57 file's lengths have by the standard, so that the same cloud written as E57
    (``write_large_e57``) gives the same bundle: ``base.tsp`` carries the units."""
    from fitter.fitting.examples import relief_height

    header = ("ply\nformat binary_little_endian 1.0\ncomment units m\n"
              "comment generated example relief (synthetic, not a real scan)\n"
              f"element vertex {points}\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n").encode("ascii")
    with open(path, "wb") as fh:
        fh.write(header)
        for k, start in enumerate(range(0, points, GENERATE_CHUNK)):
            m = min(GENERATE_CHUNK, points - start)
            rng = np.random.default_rng([0, k])
            x, y = rng.uniform(-100, 100, m), rng.uniform(-70, 70, m)
            z = relief_height(x, y) + rng.normal(0, 0.05, m)
            fh.write(np.column_stack([x, y, z]).astype("<f4").tobytes())


E57_SCAN_POINTS = 10_000_000  # points per scan of the generated E57 (bounded memory)


def write_large_e57(ply: Path, path: Path) -> None:
    """The cloud of the float32 PLY ``ply`` as an E57 file (pye57), in scans of
    ``E57_SCAN_POINTS`` consecutive points with the identity pose (as float64 cartesian
    coordinates: the same values), so that writing 10^8 points takes one scan of memory."""
    import pye57

    from fitter.fitting.io.ply import open_ply_stream

    stream = open_ply_stream(ply)[0]
    path.unlink(missing_ok=True)
    e57 = pye57.E57(str(path), mode="w")
    try:
        for k, start in enumerate(range(0, stream.count, E57_SCAN_POINTS)):
            points, _ = stream.read(start, min(stream.count, start + E57_SCAN_POINTS))
            e57.write_scan_raw({"cartesianX": np.ascontiguousarray(points[:, 0]),
                                "cartesianY": np.ascontiguousarray(points[:, 1]),
                                "cartesianZ": np.ascontiguousarray(points[:, 2])},
                               name=f"part {k}")
    finally:
        e57.close()


def _timed_fit(scan: Path, out: Path, workers: int = 0) -> dict | None:
    """``fit_scan`` with default options in a subprocess under ``/usr/bin/time -v``: its
    JSON line plus the peak resident set (MB; with workers, of the client process only)."""
    proc = subprocess.run(["/usr/bin/time", "-v", sys.executable, "-c", LARGE_FIT_SCRIPT,
                           str(scan), str(out), str(workers)], capture_output=True, text=True,
                          cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    if proc.returncode != 0:
        print(f"fit of {scan.name} failed:", proc.stderr[-3000:])
        return None
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    for line in proc.stderr.splitlines():
        if "Maximum resident set size" in line:
            result["peak_mb"] = int(line.split(":")[1]) / 1024
        if "Elapsed (wall clock)" in line:
            result["elapsed"] = line.split(": ", 1)[1].strip()
        for key, label in (("user_s", "User time (seconds)"), ("sys_s", "System time (seconds)")):
            if label in line:  # CPU time: what a loaded machine's wall time hides
                result[key] = float(line.split(":")[1])
    result["workers"] = workers
    return result


def _load_average() -> list[str]:
    with open("/proc/loadavg") as fh:
        return fh.read().split()[:3]


def _base_digest(bundle: Path) -> str | None:
    import hashlib

    base = bundle / "base.tsp"
    return hashlib.sha256(base.read_bytes()).hexdigest() if base.exists() else None


def write_vase_ply(path: Path, vertices: int) -> int:
    """The example vase (``fitter.fitting.examples.vase_mesh``, a closed fluted vase in mm)
    as a binary mesh PLY of about ``vertices`` vertices (``rings`` x ``1.75 rings``); returns
    its vertex count."""
    from fitter.demo import write_mesh_ply
    from fitter.fitting.examples import vase_mesh

    rings = max(4, round(math.sqrt(vertices / 1.75)))
    v, f = vase_mesh(round(1.75 * rings), rings)
    write_mesh_ply(path, v, f)
    return len(v)


def run_large(sizes: tuple[int, ...] = (10_000_000, 100_000_000),
              cluster_points: int | None = None, e57_points: int | None = None,
              scratch: Path | None = None, vase_vertices: int | None = None) -> dict:
    """The out-of-core fit (``fitter.fitting.stream``) of generated float32 binary PLYs of
    ``sizes`` points, default options, each in a subprocess under ``/usr/bin/time -v``;
    for ``e57_points`` (default: the largest size) the same cloud as E57 (``base.tsp``
    compared byte for byte, time against the PLY's), for ``cluster_points`` (default: the
    largest size) LocalClusters of 1 and 2 workers; with ``vase_vertices``, the example vase
    as a closed mesh of about that many vertices (an atlas of its working mesh, every vertex
    measured: the ``vase`` rows). The load average is taken before and after each fit.
    Writes ``bench/results/fit_large.json``; the files are deleted."""
    sizes = tuple(sorted(int(n) for n in sizes))
    largest = sizes[-1] if sizes else 0
    cluster_points = largest if cluster_points is None else int(cluster_points)
    e57_points = largest if e57_points is None else int(e57_points)
    scratch = Path(scratch or tempfile.mkdtemp(prefix="tessera-bench-large-"))
    scratch.mkdir(parents=True, exist_ok=True)
    rows, cluster, e57 = [], [], []
    load_before = _load_average()

    def fit(scan: Path, out: Path, workers: int = 0) -> dict | None:
        before = _load_average()
        row = _timed_fit(scan, out, workers)
        if row:
            row.update(load_before=before, load_after=_load_average(),
                       base_sha256=_base_digest(out), input_bytes=scan.stat().st_size)
        shutil.rmtree(out, ignore_errors=True)
        return row

    for n in sizes:
        ply = scratch / f"relief-{n}.ply"
        start = time.perf_counter()
        write_large_ply(ply, n)
        generated = time.perf_counter() - start
        row = fit(ply, scratch / f"bundle-{n}")
        if row:
            row.update(generate_s=generated)
            rows.append(row)
        if n == e57_points:
            e57_path = scratch / f"relief-{n}.e57"
            write_large_e57(ply, e57_path)
            r = fit(e57_path, scratch / f"bundle-{n}-e57")
            e57_path.unlink()
            if r:
                r["same_base_as_ply"] = bool(row) and r["base_sha256"] == row["base_sha256"]
                r["wall_vs_ply"] = r["wall_s"] / row["wall_s"] if row else None
                e57.append(r)
        if n == cluster_points:
            for workers in (1, 2):
                r = fit(ply, scratch / f"bundle-{n}-w{workers}", workers)
                if r:
                    r["same_base_as_ply"] = bool(row) and r["base_sha256"] == row["base_sha256"]
                    cluster.append(r)
            if len(cluster) == 2:
                cluster[1]["wall_vs_1_worker"] = cluster[1]["wall_s"] / cluster[0]["wall_s"]
        ply.unlink()
    vase = []
    if vase_vertices:
        ply = scratch / "vase.ply"
        start = time.perf_counter()
        count = write_vase_ply(ply, int(vase_vertices))
        generated = time.perf_counter() - start
        row = fit(ply, scratch / "bundle-vase")
        if row:
            row.update(generate_s=generated, vertices=count)
            vase.append(row)
        ply.unlink()

    def stages(r: dict) -> str:
        return " ".join(f"{k} {v:.1f}" for k, v in r["timings"].items())

    print_table("out-of-core fit, default options, generated float32 binary PLY",
                ["points", "wall s", "CPU s", "peak MB", "working set", "levels", "RMS",
                 "load", "stages (wall s)"],
                [[r["points"], f"{r['wall_s']:.1f}", f"{r['user_s'] + r['sys_s']:.0f}",
                  f"{r['peak_mb']:.0f}",
                  r["working_set"]["points_after"] if r["working_set"] else "-",
                  r["detail_levels"], f"{r['rms']:.4g}", r["load_before"][0], stages(r)]
                 for r in rows])
    if e57:
        print_table("the same cloud as E57 (pye57)",
                    ["points", "wall s", "vs PLY", "CPU s", "peak MB", "same base.tsp",
                     "load", "stages (wall s)"],
                    [[r["points"], f"{r['wall_s']:.1f}", f"{r['wall_vs_ply'] or 0:.2f}",
                      f"{r['user_s'] + r['sys_s']:.0f}", f"{r['peak_mb']:.0f}",
                      r["same_base_as_ply"], r["load_before"][0], stages(r)] for r in e57])
    if cluster:
        print_table(f"{cluster_points} points on a LocalCluster",
                    ["workers", "wall s", "vs 1 worker", "client peak MB", "same base.tsp",
                     "load", "stages (wall s)"],
                    [[r["workers"], f"{r['wall_s']:.1f}",
                      f"{r.get('wall_vs_1_worker', 1.0):.2f}", f"{r['peak_mb']:.0f}",
                      r["same_base_as_ply"], r["load_before"][0], stages(r)]
                     for r in cluster])
    if vase:
        print_table("the example vase as a closed mesh (an atlas of its working mesh)",
                    ["vertices", "wall s", "CPU s", "peak MB", "patches", "levels",
                     "RMS (mm)", "within 0.5 %", "max % diag", "load", "stages (wall s)"],
                    [[r["vertices"], f"{r['wall_s']:.1f}", f"{r['user_s'] + r['sys_s']:.0f}",
                      f"{r['peak_mb']:.0f}", r["patches"], r["detail_levels"],
                      f"{r['rms']:.4g}", f"{100 * r['within_0.5%']:.2f}",
                      f"{100 * r['max_relative']:.3f}", r["load_before"][0], stages(r)]
                     for r in vase])
    result = {"rows": rows, "e57": e57, "cluster": cluster, "vase": vase,
              "load_before": load_before, "load_after": _load_average()}
    earlier = ROOT / "bench" / "results" / "fit_large.json"
    if earlier.exists():  # a run of other sizes keeps the figures of the sizes it did not run
        before = json.loads(earlier.read_text())
        for key in ("rows", "e57", "cluster", "vase"):
            ran = {r["points"] for r in result[key]}
            result[key] = [r for r in before.get(key, []) if r.get("points") not in ran] \
                + result[key]
    write_results("fit_large", result)
    return result


def add_arguments(parser) -> None:
    """``python -m bench fit`` options: with ``--points``, the out-of-core benchmark."""
    parser.add_argument("--points", type=float, nargs="+", default=None,
                        help="fit generated float32 binary PLYs of these sizes (e.g. 1e7 1e8) "
                             "out of core instead of the method comparison")
    parser.add_argument("--e57-points", type=float, default=None,
                        help="the size also written as E57 (default: the largest; 0: none)")
    parser.add_argument("--cluster-points", type=float, default=None,
                        help="the size also fitted on LocalClusters of 1 and 2 workers "
                             "(default: the largest; 0: none)")
    parser.add_argument("--vase-vertices", type=float, default=None,
                        help="also (without --points: only) fit the example vase as a closed "
                             "mesh of about this many vertices (e.g. 4.5e6: an atlas of its "
                             "working mesh)")
    parser.add_argument("--scratch", type=Path, default=None,
                        help="directory of the generated files (default: a new temporary one)")


def run(points: list[float] | None = None, e57_points: float | None = None,
        cluster_points: float | None = None, scratch: Path | None = None,
        big_points: int = 10_000_000, vase_vertices: float | None = None) -> dict:
    """The method comparison (module docstring), or with ``points`` :func:`run_large`."""
    if points or vase_vertices:
        return run_large(tuple(int(p) for p in points or ()), cluster_points, e57_points, scratch,
                         None if vase_vertices is None else int(vase_vertices))
    return run_methods(big_points)
