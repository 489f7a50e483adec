"""Web viewer benchmark: cold page load to first frame in headless Chromium, and Tessera's
in-browser tessellation (client_py under Pyodide, in the worker) against three.js.

A 40 x 40 bundle is fitted from the generated relief scan (``fitter.fitting.examples.relief_scan``,
80,000 points) and served by the Flask app on 127.0.0.1. For each grid (128² and 256²
vertices) the viewer page is loaded cold ``COLD_RUNS`` times (a fresh browser context each
time: empty HTTP and code caches) and its ``window.tessera.stats`` read: ``pyodide_load_ms``
(worker: import + ``loadPyodide``), ``first_frame_ms`` (navigation start to the first, coarse
mesh drawn), ``tessellate_ms`` (``tessellate_grid`` in the worker at the requested grid) and
``refined_ms`` (navigation start to that mesh drawn). Target: first frame <= 5 s. Both ways of
starting Pyodide are measured: from the server's memory snapshot (the default,
``fitter.server.snapshot``; made once per client_py version, its build time is reported) and
plainly (``TESSERA_PYODIDE_SNAPSHOT=0``).

Then, in the same page session, the same tessellation is timed warm ``WARM_RUNS`` times both
ways: Tessera (``tessellate_grid`` in Pyodide: positions, analytic normals, indices) and
three.js (``NURBSSurface`` + ``ParametricGeometry``: positions, finite-difference normals,
indices; npm ``three``, used by the benchmark only) on the very same surface (the bundle's
``base.tsp`` in scan coordinates). The headline is the ratio Tessera / three.js (< 1: Tessera
faster). Writes ``bench/results/web.json``.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

from bench import ROOT, print_table, write_results

GRIDS = (128, 256)
COLD_RUNS = 3
WARM_RUNS = 5
TARGET_FIRST_FRAME_MS = 5000.0
MODES = ("snapshot", "plain")  # Pyodide started from the server's memory snapshot, or plainly

# Times three.js on the surface given as {degree, knots, points (n_u x n_v x 4: x, y, z, w)}.
THREE_JS = """async ({surface, grid, runs}) => {
    const THREE = await import("three");
    const { NURBSSurface } = await import("three/addons/curves/NURBSSurface.js");
    const { ParametricGeometry } = await import("three/addons/geometries/ParametricGeometry.js");
    const points = surface.points.map(
      (row) => row.map(([x, y, z, w]) => new THREE.Vector4(x, y, z, w)));
    const nurbs = new NURBSSurface(surface.degree[0], surface.degree[1], surface.knots[0],
                                   surface.knots[1], points);
    const evaluate = (u, v, target) => nurbs.getPoint(u, v, target);
    const times = [];
    let geometry = null;
    for (let k = 0; k < runs + 1; k++) {  // the first run warms the JIT and is not counted
      const start = performance.now();
      geometry = new ParametricGeometry(evaluate, grid - 1, grid - 1);
      const ms = performance.now() - start;
      if (k > 0) times.push(ms);
      if (k < runs) geometry.dispose();
    }
    return {times, vertices: geometry.getAttribute("position").count,
            triangles: geometry.index.count / 3};
}"""


def _surface_json(patch: Path) -> dict:
    from client_py import read_patch

    s = read_patch(patch.read_bytes()).to_scan_frame()
    weights = s.weights
    points = [[[*p, weights[i][j]] for j, p in enumerate(row)]
              for i, row in enumerate(s.control_points)]
    return {"degree": list(s.degree), "knots": [list(s.knots[0]), list(s.knots[1])],
            "points": points}


def _fit_bundle(root: Path) -> Path:
    from fitter.fitting.examples import relief_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    bundle = root / "relief40"
    fit_scan(relief_scan(80_000), bundle,
             FitOptions(grid=(40, 40), title="Carved relief (generated example), 40 x 40"))
    return bundle


def _cold_load(browser, url: str) -> tuple[dict, object, object]:
    """Load ``url`` in a fresh context (no caches) until the refined mesh is drawn."""
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    page = context.new_page()
    page.goto(url)
    page.wait_for_function("document.body.dataset.refined === '1' || !!document.body.dataset.error",
                           timeout=120_000)
    error = page.evaluate("document.body.dataset.error")
    if error:
        raise RuntimeError(f"the viewer failed: {error}")
    return page.evaluate("window.tessera.stats"), page, context


def _measure(browser, base: str, bundle: Path, surface: dict, warm_too: bool):
    cold: dict[int, list[dict]] = {}
    warm: dict[int, dict] = {}
    for grid in GRIDS:
        cold[grid] = []
        url = f"{base}/objects/{bundle.name}/?resolution={grid}"
        for k in range(COLD_RUNS):
            stats, page, context = _cold_load(browser, url)
            cold[grid].append(stats)
            if not (warm_too and k == COLD_RUNS - 1):
                context.close()
        if not warm_too:
            continue
        # warm, same page session: Tessera in the worker, then three.js in the page
        tessera_runs = [page.evaluate(f"window.tessera.tessellate({grid})")
                        for _ in range(WARM_RUNS)]
        three = page.evaluate(THREE_JS, {"surface": surface, "grid": grid, "runs": WARM_RUNS})
        context.close()
        if three["vertices"] != grid * grid:
            raise RuntimeError(f"three.js made {three['vertices']} vertices, not {grid * grid}")
        tess_ms = [r["tessellate_ms"] for r in tessera_runs]
        trip_ms = [r["round_trip_ms"] for r in tessera_runs]
        warm[grid] = {
            "tessera_ms": {"best": min(tess_ms), "median": statistics.median(tess_ms),
                           "runs": tess_ms},
            "tessera_round_trip_ms": {"best": min(trip_ms), "median": statistics.median(trip_ms)},
            "three_ms": {"best": min(three["times"]), "median": statistics.median(three["times"]),
                         "runs": three["times"]},
            "vertices": grid * grid,
            "tessera_triangles": tessera_runs[-1]["triangles"],
            "three_triangles": three["triangles"],
            "kernel": tessera_runs[-1]["kernel"],
        }
        warm[grid]["ratio_tessera_over_three"] = (warm[grid]["tessera_ms"]["best"]
                                                  / warm[grid]["three_ms"]["best"])
    return cold, warm


def run() -> dict | None:
    sys.path.insert(0, str(ROOT / "tests"))  # the tests' live-server helper (not shipped)
    from live import CHROMIUM_PATH, LiveServer, chromium_launch_args

    if not Path(CHROMIUM_PATH).exists():
        print(f"skipped: {CHROMIUM_PATH} is missing (make chromium)")
        return None
    from playwright.sync_api import sync_playwright

    from fitter.server import create_app

    cold: dict[str, dict[int, list[dict]]] = {}
    warm: dict[int, dict] = {}
    snapshot_build_s = None
    with tempfile.TemporaryDirectory(prefix="tessera-bench-web-") as tmp:
        bundle = _fit_bundle(Path(tmp))
        surface = _surface_json(bundle / "base.tsp")
        patch_bytes = (bundle / "base.tsp").stat().st_size
        with sync_playwright() as pw:
            browser = pw.chromium.launch(**chromium_launch_args())
            try:
                for mode in MODES:
                    app = create_app({"TESSERA_COLLECTION": tmp,
                                      "TESSERA_PYODIDE_SNAPSHOT": mode == "snapshot"})
                    builder = app.extensions["tessera_snapshot"]
                    if builder is not None:
                        start = time.perf_counter()
                        if builder.ensure() is None:
                            print(f"no snapshot mode: {builder.failure}")
                            continue
                        snapshot_build_s = time.perf_counter() - start  # 0 when cached
                    with LiveServer(app) as live:
                        cold[mode], measured = _measure(browser, live.url, bundle, surface,
                                                        warm_too=not warm)
                    warm = warm or measured
            finally:
                browser.close()

    def med(mode: str, grid: int, key: str) -> float:
        return statistics.median(s[key] for s in cold[mode][grid])

    print_table(f"Cold page load, 40 x 40 patch, headless Chromium (median of {COLD_RUNS}; ms)",
                ["start", "grid", "pyodide_load", "first_frame", "tessellate", "refined",
                 "best first"],
                [[mode, f"{g}²", med(mode, g, "pyodide_load_ms"), med(mode, g, "first_frame_ms"),
                  med(mode, g, "tessellate_ms"), med(mode, g, "refined_ms"),
                  min(s["first_frame_ms"] for s in cold[mode][g])]
                 for mode in cold for g in GRIDS])
    print_table(f"Same tessellation warm, same page (best of {WARM_RUNS}; ms)",
                ["grid", "Tessera (Pyodide)", "three.js", "Tessera / three.js",
                 "Tessera round trip"],
                [[f"{g}²", warm[g]["tessera_ms"]["best"], warm[g]["three_ms"]["best"],
                  warm[g]["ratio_tessera_over_three"], warm[g]["tessera_round_trip_ms"]["best"]]
                 for g in GRIDS])
    first = {mode: {"median": statistics.median(s["first_frame_ms"] for g in GRIDS
                                                for s in cold[mode][g]),
                    "best": min(s["first_frame_ms"] for g in GRIDS for s in cold[mode][g])}
             for mode in cold}
    for mode, f in first.items():
        verdict = "meets" if f["median"] <= TARGET_FIRST_FRAME_MS else "misses"
        f["meets_target"] = verdict == "meets"
        print(f"first frame ({mode} start): median {f['median']:.0f} ms, best {f['best']:.0f} ms;"
              f" {verdict} the {TARGET_FIRST_FRAME_MS:.0f} ms target")
    result = {
        "patch": {"grid": [40, 40], "degree": surface["degree"], "bytes": patch_bytes},
        "chromium": chromium_launch_args(),
        "target_first_frame_ms": TARGET_FIRST_FRAME_MS,
        "snapshot_build_s": snapshot_build_s,
        "first_frame_ms": first,
        "cold": {mode: {str(g): cold[mode][g] for g in GRIDS} for mode in cold},
        "warm": {str(g): warm[g] for g in GRIDS},
    }
    path = write_results("web", result)
    print(f"wrote {path}")
    return result
