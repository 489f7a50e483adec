"""Tessellation benchmark: a 40 x 40 degree-2 patch to a 256 x 256 grid with normals.

Runs ``client_py.tessellate_grid`` with the pure-Python kernel and the numpy
kernel in CPython, and the pure-Python kernel in Pyodide under node (the
browser's path: Pyodide from web/node_modules, no numpy), on a rational and a
non-rational patch, and on the rational one with a trim mask. The patch is the
example relief (``fitter.fitting.examples``: rosette, groove, step on a convex face,
200 x 140 mm) sampled as a height field at the Greville abscissae, with smooth
weights ``1 + 0.2 sin cos``. Writes ``bench/results/tessellate.json``.
"""

from __future__ import annotations

import json
import math
import shutil
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
    record = {
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
