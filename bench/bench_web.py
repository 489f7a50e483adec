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
faster).

Zoom (issue 14): a second bundle, the relief (40,000 points) with a 20 x 20 base and
``ZOOM_LEVELS`` detail levels (16 spans per tile: 33² regions), is opened at 1280 x 800 with
the base following the view, and zoomed into ``ZOOM_SPOTS`` spots in turn, back to the fitted
view between them: each time the hook ``window.tessera.zoomTo(u, v, ZOOM_DISTANCE)`` frames the
spot and resolves once the tiles of that view are on screen. The figure is the time from the
call to the last region swap (``stats.tile_timing.at``), with the tile layer's split of its last
update (fetch + decode, regions in the worker, Python time, three.js geometry, swap and draw).
Then ``WHEEL_STEPS`` mouse-wheel steps at the canvas centre, each timed from the wheel event to
the last region swap once nothing has changed for ``QUIET_MS`` (the debounce and a base
re-tessellation included). Target: median zoom-to-refined <= 1 s. ``run_zoom()`` runs this part
alone. Writes ``bench/results/web.json``.
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


ZOOM_LEVELS = 4
ZOOM_SPOTS = 8
ZOOM_DISTANCE = 40.0
WHEEL_STEPS = 4
WHEEL_DELTA = -600  # pixels per wheel step (OrbitControls: a zoom of about 0.95^(600/50))
QUIET_MS = 1500
TARGET_ZOOM_MS = 1000.0

# Zoom into one spot from the fitted view: ms from the call to the last region swap.
ZOOM_JS = """async ([u, v, distance]) => {
    const start = performance.now();
    const stats = await window.tessera.zoomTo(u, v, distance);
    return {ms: stats.tile_timing.at - start, resolved_ms: performance.now() - start,
            regions: stats.regions, timing: stats.tile_timing, tiles_loaded: stats.tiles_loaded,
            panel: document.getElementById("fact-detail").textContent};
}"""

# One wheel step at the canvas centre; resolves once the regions and the base have been quiet
# for `quiet` ms: ms from the event to the last region swap.
WHEEL_JS = """async ([deltaY, quiet]) => {
    const canvas = document.getElementById("view");
    const box = canvas.getBoundingClientRect();
    const stats = window.tessera.stats;
    const start = performance.now();
    const updates = stats.tile_updates;
    canvas.dispatchEvent(new WheelEvent("wheel", {deltaY, clientX: box.left + box.width / 2,
        clientY: box.top + box.height / 2, bubbles: true, cancelable: true}));
    let last = [stats.tile_updates, stats.meshes], since = performance.now();
    while (performance.now() - since < quiet || stats.tiles_busy) {
      await new Promise((resolve) => setTimeout(resolve, 50));
      const now = [stats.tile_updates, stats.meshes];
      if (now[0] !== last[0] || now[1] !== last[1] || stats.tiles_busy) {
        last = now;
        since = performance.now();
      }
    }
    const at = stats.tile_timing ? stats.tile_timing.at : start;
    return {ms: at > start ? at - start : null, updates: stats.tile_updates - updates,
            regions: stats.regions, resolution: stats.resolution, timing: stats.tile_timing};
}"""


def _fit_detail_bundle(root: Path) -> Path:
    from fitter.fitting.examples import relief_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    bundle = root / "relief-detail"
    fit_scan(relief_scan(40_000), bundle,
             FitOptions(grid=(20, 20), detail_levels=ZOOM_LEVELS, title="Relief with detail"))
    return bundle


def _zoom_spots(bundle: Path) -> list[tuple[float, float]]:
    """Centres of ``ZOOM_SPOTS`` finest-level tiles spread over the bundle (fixed choice)."""
    import json

    nodes = json.loads((bundle / "manifest.json").read_text())["tiles"]["detail"]["nodes"]
    finest = max(n["level"] for n in nodes)
    side = 2**finest
    present = {(n["i"], n["j"]) for n in nodes if n["level"] == finest}
    # a ring of spots around the centre and its diagonals, each far from the others
    wanted = [(1, 1), (1, side - 2), (side - 2, 1), (side - 2, side - 2), (side // 2, 1),
              (1, side // 2), (side // 2, side - 2), (side - 2, side // 2)]
    keys = [key for key in wanted if key in present] or sorted(present)
    return [((i + 0.5) / side, (j + 0.5) / side) for i, j in keys[:ZOOM_SPOTS]]


def _zoom_runs(browser, base: str, bundle: Path) -> dict:
    """Zoom-to-refined times on one page: ``ZOOM_SPOTS`` hooked zooms, ``WHEEL_STEPS`` wheels."""
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    page = context.new_page()
    problems: list[str] = []
    page.on("pageerror", lambda exc: problems.append(str(exc)))
    try:
        page.goto(f"{base}/objects/{bundle.name}/")
        page.wait_for_function("document.body.dataset.refined === '1' || "
                               "!!document.body.dataset.error", timeout=120_000)
        error = page.evaluate("document.body.dataset.error")
        if error:
            raise RuntimeError(f"the viewer failed: {error}")
        page.evaluate("window.tessera.tilesIdle()")
        spots = []
        for u, v in _zoom_spots(bundle):
            spots.append({"u": u, "v": v, **page.evaluate(ZOOM_JS, [u, v, ZOOM_DISTANCE])})
            page.click("#fit-view")
            page.evaluate("window.tessera.tilesIdle()")
        wheels = [page.evaluate(WHEEL_JS, [WHEEL_DELTA, QUIET_MS]) for _ in range(WHEEL_STEPS)]
        panel = page.locator("#fact-detail").inner_text()
        if problems or page.evaluate("document.body.dataset.tileError"):
            raise RuntimeError(f"the viewer reported problems: {problems}")
    finally:
        context.close()
    ms = [s["ms"] for s in spots]
    wheel_ms = [w["ms"] for w in wheels if w["ms"] is not None]
    return {"spots": spots, "wheel": wheels, "panel_detail": panel,
            "zoom_ms": {"median": statistics.median(ms), "best": min(ms), "worst": max(ms)},
            "resolved_ms": {"median": statistics.median(s["resolved_ms"] for s in spots)},
            "wheel_ms": {"median": statistics.median(wheel_ms) if wheel_ms else None,
                         "best": min(wheel_ms, default=None),
                         "worst": max(wheel_ms, default=None)},
            "target_ms": TARGET_ZOOM_MS}


def _print_zoom(zoom: dict) -> None:
    rows = []
    for s in zoom["spots"]:
        t = s["timing"]
        rows.append([f"({s['u']:.3f}, {s['v']:.3f})", s["ms"], s["regions"], t["made"],
                     t.get("cached", "-"),
                     t.get("bytes_ms"), t["fetch_ms"], t["regions_ms"], t["python_ms"],
                     t["build_ms"], t["swap_ms"]])
    print_table("Zoom to the refined view (ms from zoomTo to the last region swap; the last "
                "update's split)",
                ["spot", "zoom→refined", "regions", "made", "cached", "fetch", "fetch+decode",
                 "regions (worker)", "Python", "geometry", "swap+draw"], rows)
    rows = [[k, w["ms"] if w["ms"] is not None else "no new regions", w["updates"], w["regions"],
             w["resolution"]] for k, w in enumerate(zoom["wheel"], 1)]
    print_table("Wheel zoom at the centre (ms from the event to the last region swap)",
                ["step", "wheel→refined", "updates", "regions", "base grid"], rows)
    z, w = zoom["zoom_ms"], zoom["wheel_ms"]
    verdict = "meets" if z["median"] <= TARGET_ZOOM_MS else "misses"
    print(f"zoom to refined: median {z['median']:.0f} ms (best {z['best']:.0f}, worst "
          f"{z['worst']:.0f}; zoomTo resolved: median {zoom['resolved_ms']['median']:.0f}); "
          f"wheel median {w['median']}; {verdict} the "
          f"{TARGET_ZOOM_MS:.0f} ms target; panel: {zoom['panel_detail']}")


def _zoom_with_server(browser, root: Path) -> dict:
    from live import LiveServer

    from fitter.server import create_app

    root.mkdir(parents=True, exist_ok=True)
    bundle = _fit_detail_bundle(root)
    # a loaded machine starts Pyodide slowly: the page's own 45 s limit is not what is measured
    app = create_app({"TESSERA_COLLECTION": str(root), "TESSERA_PYODIDE_TIMEOUT": 300})
    builder = app.extensions["tessera_snapshot"]
    if builder is not None:
        builder.ensure()
    with LiveServer(app) as live:
        return _zoom_runs(browser, live.url, bundle)


def run_zoom() -> dict | None:
    """The zoom part alone (prints its tables; writes nothing)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from live import CHROMIUM_PATH, chromium_launch_args

    if not Path(CHROMIUM_PATH).exists():
        print(f"skipped: {CHROMIUM_PATH} is missing (make chromium)")
        return None
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="tessera-bench-zoom-") as tmp, \
            sync_playwright() as pw:
        browser = pw.chromium.launch(**chromium_launch_args())
        try:
            zoom = _zoom_with_server(browser, Path(tmp))
        finally:
            browser.close()
    _print_zoom(zoom)
    return zoom


def run_zoom_before_after(before: str | Path | None = None, rounds: int = 2) -> dict | None:
    """The zoom part for another checkout (``before``, or ``$TESSERA_BEFORE``: a ``git
    archive`` of the commit to compare with, its ``web/node_modules`` linked) and for this
    one, alternately ``rounds`` times in one session (a noisy machine's load changes within
    minutes: pairs taken back to back are compared, never runs of different hours). Each
    checkout runs its own code (viewer, worker, client_py) under the same protocol (this
    module's, run in a subprocess for ``before``). Prints the tables and a summary; writes
    ``bench/results/web_zoom.json``."""
    import json
    import os
    import subprocess

    before = before or os.environ.get("TESSERA_BEFORE")
    if not before:
        print("zoom before/after skipped: give the other checkout (TESSERA_BEFORE=DIR)")
        return None
    before = Path(before)
    script = ("import json, sys; sys.path.insert(0, {root!r}); import bench.bench_web as b; "
              "json.dump(b.run_zoom(), open({out!r}, 'w'))")
    runs: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="tessera-zoom-pair-") as tmp:
        for k in range(rounds):
            for label, root in (("before", before), ("after", ROOT)):
                out = Path(tmp) / f"{label}-{k}.json"
                load = os.getloadavg()
                proc = subprocess.run(
                    [sys.executable, "-c", script.format(root=str(root), out=str(out))],
                    cwd=root, env={**os.environ, "PYTHONPATH": str(root)}, timeout=1800,
                    capture_output=True, text=True)
                print(proc.stdout)
                if proc.returncode != 0:
                    raise RuntimeError(f"the {label} zoom run failed:\n{proc.stderr[-3000:]}")
                runs.append({"label": label, "round": k, "load_before": list(load),
                             "load_after": list(os.getloadavg()),
                             **json.loads(out.read_text())})
    rows = [[r["round"] + 1, r["label"], r["zoom_ms"]["median"], r["zoom_ms"]["best"],
             r["zoom_ms"]["worst"], r["resolved_ms"]["median"], r["wheel_ms"]["median"],
             f"{r['load_before'][0]:.1f}-{r['load_after'][0]:.1f}"] for r in runs]
    print_table("Zoom to the refined view, before and after in one session (ms)",
                ["round", "code", "zoomTo median", "best", "worst", "resolved median",
                 "wheel median", "load (1 min)"], rows)
    summary = {label: statistics.median(r["zoom_ms"]["median"] for r in runs
                                        if r["label"] == label) for label in ("before", "after")}
    print(f"zoom to refined, median of the rounds' medians: before {summary['before']:.0f} ms, "
          f"after {summary['after']:.0f} ms (target {TARGET_ZOOM_MS:.0f} ms)")
    record = {"runs": runs, "median_of_medians_ms": summary, "target_ms": TARGET_ZOOM_MS,
              "before": str(before)}
    path = write_results("web_zoom", record)
    print(f"wrote {path}")
    return record


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
                zoom = _zoom_with_server(browser, Path(tmp) / "zoom")
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
    _print_zoom(zoom)
    result = {
        "zoom": zoom,
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
