"""Fit benchmark (issue 4): RMS, patch bytes and wall time of the three methods, 40x40 degree 2.

Data: the Happy Buddha range scan 0 and the Bali mask from ``../shared/data``
(skipped when absent) and the generated example relief. For each: the paper's
linear fit (the baseline of the RMS target), the paper's method as published,
and Tessera's default; RMS is the foot-point deviation of every covered scan
point from the *decoded* ``base.tsp``. Then a generated 10^7-point height field
fitted in a subprocess, for wall time and peak resident memory.
Writes ``bench/results/fit.json``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench import print_table, write_results

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"
SCANS = {
    "happy-buddha scan 0": DATA / "happy-buddha-rangescans" / "happyStandRight_0.ply.gz",
    "bali-mask": DATA / "bali-mask" / "mask.obj",
}

BIG_SCRIPT = """
import json, resource, sys, time
import numpy as np
from fitter.demo import write_scan_ply
from fitter.examples import relief_height
from fitter.pipeline import FitOptions, fit_scan
n = int(sys.argv[1]); out = sys.argv[2]
rng = np.random.default_rng(0)
x = rng.uniform(-100, 100, n); y = rng.uniform(-70, 70, n)
pts = np.column_stack([x, y, relief_height(x, y) + rng.normal(0, 0.05, n)])
write_scan_ply(out + "/big.ply", pts)
del pts, x, y
start = time.perf_counter()
bundle = fit_scan(out + "/big.ply", out + "/bundle", FitOptions())
wall = time.perf_counter() - start
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"points": n, "wall_s": wall, "peak_mb": peak,
                  "rms": bundle.manifest["stats"]["rms"],
                  "bytes": bundle.manifest["files"]["base.tsp"],
                  "timings": bundle.manifest["timings"]}))
"""


def _fit_row(name: str, scan, method: str, out: Path) -> dict:
    from fitter.pipeline import FitOptions, fit_scan

    start = time.perf_counter()
    bundle = fit_scan(scan, out / f"{name}-{method}".replace(" ", "_"), FitOptions(method=method))
    wall = time.perf_counter() - start
    m = bundle.manifest
    return {"data": name, "method": method, "points": m["provenance"]["points"],
            "projection": m["projection"]["kind"], "coverage": m["projection"]["coverage"],
            "rms": m["stats"]["rms"], "max": m["stats"]["max"], "p99": m["stats"]["p99"],
            "bytes": m["files"]["base.tsp"], "wall_s": wall}


def run(big_points: int = 10_000_000) -> dict:
    from fitter.examples import relief_scan
    from fitter.io import load_scan

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        inputs = {"generated relief 80k": relief_scan()}
        for name, path in SCANS.items():
            if path.exists():
                inputs[name] = load_scan(path)
            else:
                print(f"skipping {name}: {path} is absent")
        for name, scan in inputs.items():
            for method in ("linear", "paper", "tessera"):
                rows.append(_fit_row(name, scan, method, out))
        big = None
        if big_points:
            proc = subprocess.run([sys.executable, "-c", BIG_SCRIPT, str(big_points), tmp],
                                  capture_output=True, text=True, cwd=ROOT)
            if proc.returncode == 0:
                big = json.loads(proc.stdout.strip().splitlines()[-1])
            else:
                print("10^7-point fit failed:", proc.stderr[-2000:])
    linear = {r["data"]: r["rms"] for r in rows if r["method"] == "linear"}
    for r in rows:
        r["rms_vs_linear"] = r["rms"] / linear[r["data"]]
    print_table("fit, 40x40 degree 2 (RMS of covered scan points vs decoded base.tsp)",
                ["data", "method", "points", "map", "cover", "RMS", "RMS/linear", "max",
                 "bytes", "wall s"],
                [[r["data"], r["method"], r["points"], r["projection"], f"{r['coverage']:.3f}",
                  f"{r['rms']:.4g}", f"{r['rms_vs_linear']:.3f}", f"{r['max']:.4g}", r["bytes"],
                  f"{r['wall_s']:.2f}"] for r in rows])
    if big:
        print_table("generated height field", ["points", "wall s", "peak MB", "RMS", "bytes"],
                    [[big["points"], f"{big['wall_s']:.1f}", f"{big['peak_mb']:.0f}",
                      f"{big['rms']:.4g}", big["bytes"]]])
    result = {"rows": rows, "big": big}
    write_results("fit", result)
    return result
