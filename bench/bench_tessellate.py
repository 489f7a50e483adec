"""Tessellation benchmark: a 40 x 40 degree-2 patch to a 256 x 256 grid with normals.

Runs ``client_py.tessellate_grid`` with the pure-Python kernel and the numpy
kernel in CPython, and the pure-Python kernel in Pyodide under node (the
browser's path: Pyodide from web/node_modules, no numpy), on a rational and a
non-rational patch, and on the rational one with a trim mask. The patch is the
example relief (``fitter.fitting.examples``: rosette, groove, step on a convex face,
200 x 140 mm) sampled as a height field at the Greville abscissae, with smooth
weights ``1 + 0.2 sin cos``.

Regions (issue 14, the zoom path): a bundle fitted from the relief scan (40,000 points,
20 x 20 base, ``REGION_LEVELS`` detail levels of 16 spans per tile) is read in Pyodide under
node by ``client_py.session.WorkerSession`` as the browser's worker reads it, and every region
of the finest level is made as the viewer asks for it (``region_mesh``: a 33² grid with the
four tiles of its chain, skirts, scan frame), ``REGION_REPEAT`` times; the figure is the
median over the regions of each one's best time, with the split into its stages (base and
fields sampled, displaced mesh, skirts, map to the scan frame). ``CLIENT_PY_BEFORE`` (a
directory holding another copy of client_py) times that copy too, in the same run. three.js
(``NURBSSurface`` + ``ParametricGeometry``, npm ``three`` from web/node_modules, under the
same node) tessellates the same 33² regions of the same base patch (scan frame), base only:
three.js has no displacement. Writes ``bench/results/tessellate.json``.
"""

from __future__ import annotations

import base64
import json
import math
import os
import shutil
import statistics
import subprocess
import tempfile
from pathlib import Path

from bench import ROOT, best_of, print_table, write_results
from client_py import NurbsSurface, TrimMask, tessellate_grid, uniform_clamped_knots

GRID = 256
CTRL = 40
DEGREE = 2
REPEAT = 7
RUNNER = ROOT / "tests" / "pyodide_runner.mjs"
PYODIDE = ROOT / "web" / "node_modules" / "pyodide"

# Runs inside Pyodide with INPUT = {"surfaces": {name: spec}, "grid": n, "repeat": r}.
PYODIDE_SCRIPT = """
import statistics, time
from client_py import NurbsSurface, TrimMask, tessellate_grid
from client_py._kernel import KERNEL_NAME

n, repeat = INPUT["grid"], INPUT["repeat"]
timings = {}
for name, spec in INPUT["surfaces"].items():
    trim = TrimMask(spec["trim"]) if spec["trim"] else None
    s = NurbsSurface(tuple(spec["degree"]), tuple(spec["knots"]), spec["control_points"],
                     spec["weights"], trim=trim)
    tessellate_grid(s, n, n)  # warm-up: imports, generated kernel code
    runs = []
    for _ in range(repeat):
        start = time.perf_counter()
        mesh = tessellate_grid(s, n, n)
        runs.append(time.perf_counter() - start)
    assert mesh.vertex_count == n * n
    timings[name] = {"best": min(runs), "median": statistics.median(runs), "runs": runs}
RESULT = {"kernel": KERNEL_NAME, "timings": timings}
"""


REGION_LEVELS = 4
REGION_GRID = 33
REGION_REPEAT = 5
TARGET_REGION_MS = 15.0

# Runs inside Pyodide with INPUT = {"patch": b64, "tiles": {name: b64}, "regions": [[level, i,
# j, names, skirt depth]], "grid": R, "repeat": r}: per region its best time (ms) and, when
# client_py has the staged path, the split of that run.
REGION_SCRIPT = """
import base64, time
from client_py import layers, session as session_module
from client_py._kernel import KERNEL_NAME

session = session_module.WorkerSession()
session.load_patch(base64.b64decode(INPUT["patch"]), "base.tsp")
for name, data in INPUT["tiles"].items():
    session.add_tile(name, base64.b64decode(data))
grid, repeat = INPUT["grid"], INPUT["repeat"]
staged = hasattr(layers, "sample_region")
stages = {"sample": 0.0, "mesh": 0.0, "skirts": 0.0, "scan frame": 0.0}
if staged:  # time the stages region_mesh calls, through the names it looks up
    def timed(name, function):
        def run(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                stages[name] += time.perf_counter() - start
        return run
    for attr, name in (("sample_region", "sample"), ("mesh_of_region", "mesh"),
                       ("hang_skirts", "skirts"), ("transform_mesh", "scan frame")):
        setattr(session_module, attr, timed(name, getattr(session_module, attr)))
level, i, j, names, depth = INPUT["regions"][0]
session.region_mesh(level, i, j, grid, names, depth)  # warm-up: generated kernel code
for key in stages:
    stages[key] = 0.0
try:  # node's CPU time of this process (a loaded machine's waits are not the region's)
    from js import process

    def cpu_ms():
        usage = process.cpuUsage()
        return (usage.user + usage.system) / 1000
except ImportError:
    cpu_ms = None
best, best_cpu = [], []
for level, i, j, names, depth in INPUT["regions"]:
    runs, cpu = [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), cpu_ms() if cpu_ms else 0.0
        mesh = session.region_mesh(level, i, j, grid, names, depth)
        runs.append(1000 * (time.perf_counter() - start))
        cpu.append(cpu_ms() - start_cpu if cpu_ms else float("nan"))
    best.append(min(runs))
    best_cpu.append(min(cpu))
count = repeat * len(INPUT["regions"])
RESULT = {"kernel": KERNEL_NAME, "best_ms": best, "best_cpu_ms": best_cpu,
          "vertices": mesh.vertex_count,
          "stages_ms": {k: 1000 * v / count for k, v in stages.items()} if staged else None}
"""

# Runs under node: three.js on the same regions, INPUT as {"surface", "rects", "grid", "repeat"}.
THREE_REGION_SCRIPT = r"""
import { readFileSync } from "node:fs";
const three = process.argv[2];
const THREE = await import(`${three}/build/three.module.js`);
const { NURBSSurface } = await import(`${three}/examples/jsm/curves/NURBSSurface.js`);
const { ParametricGeometry } =
  await import(`${three}/examples/jsm/geometries/ParametricGeometry.js`);
const { surface, rects, grid, repeat } = JSON.parse(readFileSync(process.argv[3], "utf8"));
const points = surface.points.map(
  (row) => row.map(([x, y, z, w]) => new THREE.Vector4(x, y, z, w)));
const nurbs = new NURBSSurface(surface.degree[0], surface.degree[1], surface.knots[0],
                               surface.knots[1], points);
const best = [];
let vertices = 0;
for (let pass = 0; pass < 2; pass++) {  // the first pass warms the JIT and is not counted
  for (const [u0, v0, u1, v1] of rects) {
    const evaluate = (s, t, target) =>
      nurbs.getPoint(u0 + (u1 - u0) * s, v0 + (v1 - v0) * t, target);
    let least = Infinity;
    for (let k = 0; k < repeat; k++) {
      const start = performance.now();
      const geometry = new ParametricGeometry(evaluate, grid - 1, grid - 1);
      least = Math.min(least, performance.now() - start);
      vertices = geometry.getAttribute("position").count;
      geometry.dispose();
    }
    if (pass === 1) best.push(least);
  }
}
process.stdout.write(JSON.stringify({ best_ms: best, vertices }) + "\n");
"""


def _region_bundle(root: Path) -> Path:
    from fitter.fitting.examples import relief_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    bundle = root / "relief-detail"
    fit_scan(relief_scan(40_000), bundle,
             FitOptions(grid=(20, 20), detail_levels=REGION_LEVELS, title="Relief with detail"))
    return bundle


def _region_input(bundle: Path) -> dict:
    """The Pyodide script's INPUT: every finest-level region with its chain of tiles."""
    manifest = json.loads((bundle / "manifest.json").read_text())
    detail = manifest["tiles"]["detail"]
    nodes = {(n["level"], n["i"], n["j"]): n for n in detail["nodes"]}
    finest = max(k for k, _, _ in nodes)
    regions = []
    for level, i, j in sorted(k for k in nodes if k[0] == finest):
        chain = [nodes[key]["file"] for key in
                 ((k, i >> (level - k), j >> (level - k)) for k in range(level + 1))
                 if key in nodes]
        depth = 2 * nodes[(level, i, j)]["geometric_error"]
        regions.append([level, i, j, chain, depth])
    names = {name for region in regions for name in region[3]}
    return {"patch": base64.b64encode((bundle / "base.tsp").read_bytes()).decode(),
            "tiles": {n: base64.b64encode((bundle / n).read_bytes()).decode() for n in names},
            "regions": regions, "grid": REGION_GRID, "repeat": REGION_REPEAT}


def _run_pyodide(script_text: str, data: dict, client_py_dir: str | None = None) -> dict:
    node = shutil.which("node")
    env = dict(os.environ)
    if client_py_dir:
        env["CLIENT_PY_DIR"] = client_py_dir
    with tempfile.TemporaryDirectory() as tmp:
        script, path = Path(tmp) / "bench.py", Path(tmp) / "input.json"
        script.write_text(script_text)
        path.write_text(json.dumps(data))
        proc = subprocess.run([node, str(RUNNER), str(script), str(path)], capture_output=True,
                              text=True, timeout=900, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"Pyodide benchmark failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _three_regions(surface: dict, rects: list) -> dict:
    node = shutil.which("node")
    with tempfile.TemporaryDirectory() as tmp:
        script, path = Path(tmp) / "three.mjs", Path(tmp) / "input.json"
        script.write_text(THREE_REGION_SCRIPT)
        path.write_text(json.dumps({"surface": surface, "rects": rects, "grid": REGION_GRID,
                                    "repeat": REGION_REPEAT}))
        proc = subprocess.run([node, str(script), str(ROOT / "web" / "node_modules" / "three"),
                               str(path)], capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"three.js region benchmark failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _scan_surface_json(patch: Path) -> dict:
    from client_py import read_patch

    s = read_patch(patch.read_bytes()).to_scan_frame()
    weights = s.weights
    return {"degree": list(s.degree), "knots": [list(s.knots[0]), list(s.knots[1])],
            "points": [[[*p, weights[i][j]] for j, p in enumerate(row)]
                       for i, row in enumerate(s.control_points)]}


def run_regions() -> dict | None:
    """The region part (prints its table; returns its record, writes nothing)."""
    if shutil.which("node") is None or not (PYODIDE / "pyodide.mjs").is_file():
        print("regions skipped: needs node and web/node_modules/pyodide (npm ci in web/)")
        return None
    with tempfile.TemporaryDirectory() as tmp:
        bundle = _region_bundle(Path(tmp))
        data = _region_input(bundle)
        surface = _scan_surface_json(bundle / "base.tsp")
    versions = {"after": None}
    before = os.environ.get("CLIENT_PY_BEFORE")
    if before:
        versions = {"before": before, **versions}
    record: dict = {"regions": len(data["regions"]), "grid": [REGION_GRID, REGION_GRID],
                    "levels": REGION_LEVELS, "repeat": REGION_REPEAT,
                    "target_ms": TARGET_REGION_MS, "load_average": list(os.getloadavg())}
    rows = []
    for label, directory in versions.items():
        out = _run_pyodide(REGION_SCRIPT, data, directory)
        best = out["result"]["best_ms"]
        record[label] = {"median_ms": statistics.median(best), "best_ms": min(best),
                         "worst_ms": max(best),
                         "cpu_median_ms": statistics.median(out["result"]["best_cpu_ms"]),
                         "stages_ms": out["result"]["stages_ms"],
                         "vertices": out["result"]["vertices"],
                         "kernel": out["result"]["kernel"], "python": out["python"].split()[0]}
        rows.append([f"Tessera, Pyodide ({label})", record[label]["median_ms"],
                     record[label]["cpu_median_ms"], record[label]["best_ms"],
                     record[label]["worst_ms"], record[label]["vertices"]])
    rects = [[i / 2**level, j / 2**level, (i + 1) / 2**level, (j + 1) / 2**level]
             for level, i, j, _, _ in data["regions"]]
    three = _three_regions(surface, rects)
    record["three"] = {"median_ms": statistics.median(three["best_ms"]),
                       "best_ms": min(three["best_ms"]), "worst_ms": max(three["best_ms"]),
                       "vertices": three["vertices"]}
    rows.append(["three.js (node), base only", record["three"]["median_ms"], None,
                 record["three"]["best_ms"], record["three"]["worst_ms"], three["vertices"]])
    print_table(f"Region tessellation: {len(rects)} regions of level {REGION_LEVELS - 1}, "
                f"{REGION_GRID}² each (ms per region: median of each region's best of "
                f"{REGION_REPEAT})",
                ["runtime", "median", "median CPU", "best", "worst", "vertices"], rows)
    stages = record["after"]["stages_ms"]
    if stages:
        print("after, mean ms per region: " + ", ".join(f"{k} {v:.2f}" for k, v in stages.items()))
    record["ratio_tessera_over_three"] = record["after"]["median_ms"] / record["three"]["median_ms"]
    verdict = "meets" if record["after"]["median_ms"] <= TARGET_REGION_MS else "misses"
    print(f"region in Pyodide: median {record['after']['median_ms']:.1f} ms (CPU "
          f"{record['after']['cpu_median_ms']:.1f} ms); {verdict} the "
          f"{TARGET_REGION_MS:.0f} ms target; Tessera / three.js = "
          f"{record['ratio_tessera_over_three']:.2f}")
    return record


# Atlas refinement (issue 14): an atlas bundle's groups change level as a visitor zooms;
# per refinement, the old viewer's work (WorkerSession.atlas_mesh: the whole atlas welded
# again) against the new one's (WorkerSession.atlas_part_meshes of the groups whose mesh at
# their new level and their neighbours' levels was not made before in the visit: AtlasLayer
# keeps the others). Step 1 is
# the first frame: the welded base in both viewers; the new one then makes every group's base
# mesh in the background (its "after" figure), which its first refinement shows. INPUT:
# {"atlas": b64, "manifest": text, "packs": {name: b64}, "steps": [levels per group, ...]}.
ATLAS_SCRIPT = """
import base64, time
from client_py import session as session_module
from client_py._kernel import KERNEL_NAME

try:  # node's CPU time of this process (a loaded machine's waits are not the work's)
    from js import process

    def cpu_ms():
        usage = process.cpuUsage()
        return (usage.user + usage.system) / 1000
except ImportError:
    def cpu_ms():
        return time.process_time() * 1000

session = session_module.WorkerSession()
session.load_atlas(base64.b64decode(INPUT["atlas"]), "base.tsa")
session.read_manifest(INPUT["manifest"])
for name, data in INPUT["packs"].items():
    session.add_pack(name, base64.b64decode(data))
neighbours = [g["neighbours"] for g in session.atlas_refinement()["groups"]]
made = set()
rows = []
for levels in INPUT["steps"]:
    start, start_cpu = time.perf_counter(), cpu_ms()
    whole = session.atlas_mesh(levels)
    before = (1000 * (time.perf_counter() - start), cpu_ms() - start_cpu)
    keys = [(g, k, tuple(levels[h] for h in neighbours[g])) for g, k in enumerate(levels)]
    wanted = [key for key in keys if key not in made]
    start, start_cpu = time.perf_counter(), cpu_ms()
    parts = session.atlas_part_meshes([g for g, _, _ in wanted], levels)
    after = (1000 * (time.perf_counter() - start), cpu_ms() - start_cpu)
    made.update(wanted)
    rows.append({"levels": levels, "before_ms": before[0], "before_cpu_ms": before[1],
                 "before_vertices": whole.vertex_count, "after_ms": after[0],
                 "after_cpu_ms": after[1], "groups_made": len(wanted),
                 "after_vertices_made": sum(p.vertex_count for p in parts)})
RESULT = {"kernel": KERNEL_NAME, "rows": rows}
"""

#: the viewer's budget of drawn vertices (web/src/atlas-layer.js MAX_VERTICES)
ATLAS_MAX_VERTICES = 250_000


def _atlas_steps(manifest: dict) -> list[list[int]]:
    """A visit: the first frame (every group at the base), then its refinements: zoom into
    the first groups one level at a time (as far as the viewer's vertex budget lets each
    group go), pan to the next groups, zoom out, zoom back in; each step the level of every
    group."""
    detail = manifest["tiles"]["detail"]
    counts = [g["count"] for g in detail["groups"]]
    resolutions = [manifest["base"]["resolution"]] + [max(manifest["base"]["resolution"],
                                                          level["resolution"])
                                                      for level in detail["levels"]]
    top = len(detail["levels"]) - 1
    groups = len(counts)

    def within_budget(levels):
        return sum(c * resolutions[k + 1] ** 2 for c, k in zip(counts, levels, strict=True)) \
            <= ATLAS_MAX_VERTICES

    def zoom(chosen, level):
        levels = [-1] * groups
        for g in chosen:  # as the viewer grants: one level at a time, within the budget
            for k in range(level + 1):
                trial = levels[:g] + [k] + levels[g + 1:]
                if within_budget(trial):
                    levels = trial
        return levels

    first, second = range(min(3, groups)), range(min(3, groups), min(6, groups))
    steps = [[-1] * groups]  # the first frame: every group at the base
    steps += [zoom(first, k) for k in range(top + 1)]
    steps += [zoom(second, top), [-1] * groups, zoom(first, top)]
    # a choice equal to the one before changes nothing on screen: no refinement
    return [levels for k, levels in enumerate(steps) if k == 0 or levels != steps[k - 1]]


def run_atlas(bundle: str | Path | None = None) -> dict | None:
    """Per refinement of an atlas bundle in Pyodide: the whole atlas welded again (before)
    against the changed groups alone (after); ``bundle`` or ``$TESSERA_ATLAS_BUNDLE`` (fit
    one with ``python -m fitter.cli fit SCAN -o DIR --detail-levels 3``). Prints its table;
    returns its record, writes nothing."""
    bundle = bundle or os.environ.get("TESSERA_ATLAS_BUNDLE")
    if not bundle:
        print("atlas refinement skipped: give an atlas bundle (TESSERA_ATLAS_BUNDLE=DIR)")
        return None
    if shutil.which("node") is None or not (PYODIDE / "pyodide.mjs").is_file():
        print("atlas refinement skipped: needs node and web/node_modules/pyodide")
        return None
    bundle = Path(bundle)
    manifest = json.loads((bundle / "manifest.json").read_text())
    from client_py.atlas_detail import pack_name

    packs = [pack_name(p["level"], p["group"]) for p in manifest["tiles"]["detail"]["packs"]]
    steps = _atlas_steps(manifest)
    data = {"atlas": base64.b64encode((bundle / "base.tsa").read_bytes()).decode(),
            "manifest": (bundle / "manifest.json").read_text(),
            "packs": {n: base64.b64encode((bundle / n).read_bytes()).decode() for n in packs},
            "steps": steps}
    out = _run_pyodide(ATLAS_SCRIPT, data)
    rows = out["result"]["rows"]
    print_table(f"Atlas refinement in Pyodide: {bundle.name}, {manifest['base']['patches']} "
                f"patches in {len(manifest['tiles']['detail']['groups'])} groups (ms per "
                "refinement; CPU time of node)",
                ["step", "levels", "before: whole atlas", "CPU", "vertices",
                 "after: changed groups", "CPU", "groups made", "vertices made"],
                [[k, " ".join(str(x) for x in r["levels"]), r["before_ms"], r["before_cpu_ms"],
                  r["before_vertices"], r["after_ms"], r["after_cpu_ms"], r["groups_made"],
                  r["after_vertices_made"]] for k, r in enumerate(rows, 1)])
    refinements = rows[1:]  # the first frame is no refinement
    before = statistics.median(r["before_cpu_ms"] for r in refinements)
    after = statistics.median(r["after_cpu_ms"] for r in refinements)
    print(f"atlas refinement (steps 2-{len(rows)}), median CPU per refinement: before "
          f"{before:.0f} ms, after {after:.0f} ms; step 1: the first frame (the welded base, "
          f"both) {rows[0]['before_cpu_ms']:.0f} ms, then every group's base mesh, made in the "
          f"background after it, {rows[0]['after_cpu_ms']:.0f} ms")
    return {"bundle": bundle.name, "patches": manifest["base"]["patches"],
            "groups": len(manifest["tiles"]["detail"]["groups"]), "steps": rows,
            "kernel": out["result"]["kernel"], "load_average": list(os.getloadavg()),
            "median_cpu_ms": {"before": before, "after": after},
            "max_vertices": ATLAS_MAX_VERTICES}


def relief_patch(rational: bool, trimmed: bool = False) -> NurbsSurface:
    """The example relief as a ``CTRL x CTRL`` degree-``DEGREE`` height-field patch.

    ``trimmed``: with a 100 x 100 trim mask covering an ellipse inscribed in the
    domain (78.5 % of it), like the coverage mask of a fitted scan.
    """
    from fitter.fitting.examples import relief_height  # numpy: CPython only

    knots_x = uniform_clamped_knots(CTRL, DEGREE, -100.0, 100.0)
    knots_y = uniform_clamped_knots(CTRL, DEGREE, -70.0, 70.0)
    xs = [sum(knots_x[i + 1 : i + DEGREE + 1]) / DEGREE for i in range(CTRL)]  # Greville
    ys = [sum(knots_y[i + 1 : i + DEGREE + 1]) / DEGREE for i in range(CTRL)]
    import numpy as np

    X, Y = np.meshgrid(xs, ys, indexing="ij")
    P = np.stack([X, Y, relief_height(X, Y)], axis=-1)
    W = 1.0 + 0.2 * np.sin(3 * X / 100) * np.cos(2 * Y / 70) if rational else None
    knots = uniform_clamped_knots(CTRL, DEGREE)
    trim = None
    if trimmed:
        side = 100
        trim = TrimMask([[((r + 0.5) / side - 0.5) ** 2 + ((c + 0.5) / side - 0.5) ** 2 <= 0.25
                          for c in range(side)] for r in range(side)])
    return NurbsSurface((DEGREE, DEGREE), (knots, knots), P, W, trim=trim)


def _spec(s: NurbsSurface) -> dict:
    return {"degree": list(s.degree), "knots": [list(k) for k in s.knots],
            "control_points": s.control_points, "weights": s.weights if s.is_rational else None,
            "trim": None if s.trim is None else [list(s.trim.flat[r * s.trim.cols :
                                                                  (r + 1) * s.trim.cols])
                                                 for r in range(s.trim.rows)]}


def _pyodide(surfaces: dict) -> dict | None:
    """Timings in Pyodide under node, or None (with the reason printed) when unavailable."""
    node = shutil.which("node")
    if node is None or not (PYODIDE / "pyodide.mjs").is_file():
        print("Pyodide skipped: needs node and web/node_modules/pyodide (npm ci in web/)")
        return None
    with tempfile.TemporaryDirectory() as tmp:
        script, data = Path(tmp) / "bench.py", Path(tmp) / "input.json"
        script.write_text(PYODIDE_SCRIPT)
        data.write_text(json.dumps({"surfaces": {k: _spec(s) for k, s in surfaces.items()},
                                    "grid": GRID, "repeat": REPEAT}))
        proc = subprocess.run([node, str(RUNNER), str(script), str(data)], capture_output=True,
                              text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"Pyodide benchmark failed:\n{proc.stderr[-3000:]}")
    record = json.loads(proc.stdout.strip().splitlines()[-1])
    package = json.loads((PYODIDE / "package.json").read_text())
    return {"pyodide": package["version"], "python": record["python"].split()[0],
            "load_seconds": record["load_seconds"], "kernel": record["result"]["kernel"],
            "timings": record["result"]["timings"]}


def run() -> dict:
    import platform

    surfaces = {"rational": relief_patch(True), "non-rational": relief_patch(False),
                "rational, trimmed": relief_patch(True, trimmed=True)}
    cpython = f"CPython {platform.python_version()}"
    rows, results = [], []
    for kernel in ("python", "numpy"):
        for name, s in surfaces.items():
            t = best_of(lambda s=s, k=kernel: tessellate_grid(s, GRID, GRID, kernel=k), REPEAT)
            results.append({"runtime": cpython, "kernel": kernel, "patch": name, **t})
    pyodide = _pyodide(surfaces)
    if pyodide is not None:
        runtime = f"Pyodide {pyodide['pyodide']} (Python {pyodide['python']}, node)"
        for name, t in pyodide["timings"].items():
            results.append({"runtime": runtime, "kernel": pyodide["kernel"], "patch": name, **t})
    for r in results:
        rows.append([r["runtime"], r["kernel"], r["patch"], r["best"], r["median"],
                     round(GRID * GRID / r["best"] / 1e6, 3)])
    print_table(f"tessellate_grid: {CTRL}x{CTRL} degree-{DEGREE} patch -> {GRID}x{GRID} "
                f"vertices with normals (seconds, best and median of {REPEAT})",
                ["runtime", "kernel", "patch", "best s", "median s", "Mvertex/s"], rows)
    if pyodide is not None:
        print(f"Pyodide load (loadPyodide under node): {pyodide['load_seconds']:.2f} s")
    regions = run_regions()
    atlas = run_atlas()
    record = {
        "regions": regions,
        "atlas": atlas,
        "task": f"tessellate_grid of a {CTRL}x{CTRL} degree-{DEGREE} patch to {GRID}x{GRID} "
                "vertices with normals",
        "patch": "example relief (fitter.fitting.examples.relief_height) as a height field at the "
                 "Greville abscissae; rational: weights 1 + 0.2 sin(3x/100) cos(2y/70)",
        "grid": [GRID, GRID], "control_points": [CTRL, CTRL], "degree": [DEGREE, DEGREE],
        "repeat": REPEAT, "results": results,
        "pyodide": None if pyodide is None else {k: v for k, v in pyodide.items()
                                                  if k != "timings"},
    }
    path = write_results("tessellate", record)
    print(f"wrote {path.relative_to(ROOT)}")
    assert all(math.isfinite(r["best"]) for r in results)
    return record
