"""client_py inside Pyodide under node: it imports with the standard library alone, matches
scipy there, and produces byte-identical meshes, PLY and .tsp files to CPython's (the
worker's session, client_py.session, included).

tests/pyodide_runner.mjs loads Pyodide from the npm package in web/node_modules and
runs tests/pyodide_checks.py (a plain script: the npm package has no pytest offline)
with reference values computed here with scipy.
"""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pyodide_checks
import pytest
from atlas_cases import random_atlas, sphere_atlas
from conftest import PROJECT_ROOT
from nurbs_cases import oracle, oracle_normals, random_surface

pytestmark = pytest.mark.pyodide

NODE = shutil.which("node")
PYODIDE = PROJECT_ROOT / "web" / "node_modules" / "pyodide" / "pyodide.mjs"
RUNNER = PROJECT_ROOT / "tests" / "pyodide_runner.mjs"
CHECKS = PROJECT_ROOT / "tests" / "pyodide_checks.py"


def surface_spec(s, trim=None, metadata=None) -> dict:
    return {"degree": list(s.degree), "knots": [list(k) for k in s.knots],
            "control_points": s.control_points, "weights": s.weights if s.is_rational else None,
            "trim": trim, "metadata": metadata}


@pytest.fixture(scope="module")
def spec() -> dict:
    """Three patches (rational and not, non-uniform knots, a trim mask) with scipy's values."""
    rng = np.random.default_rng(2024)
    cases = []
    for (p, q), rational, trim, grid in (((2, 2), True, [[1, 0, 1], [1, 1, 1]], (17, 12)),
                                         ((3, 1), False, None, (9, 20)),
                                         ((4, 2), True, None, (6, 7))):
        s = random_surface(rng, p, q, 8, 6, rational=rational, domain=((0.0, 2.0), (-1.0, 1.0)))
        params = np.column_stack([rng.uniform(0, 2, 25), rng.uniform(-1, 1, 25)])
        params = np.vstack([params, [[0, -1], [2, 1], [2, -1]]])
        uu, vv = np.meshgrid(np.linspace(0, 2, grid[0]), np.linspace(-1, 1, grid[1]),
                             indexing="ij")
        cases.append({
            "surface": surface_spec(s, trim, {"units": "mm", "case": len(cases)}),
            "params": params.tolist(),
            "oracle_points": oracle(s, params[:, 0], params[:, 1])[0].tolist(),
            "oracle_normals": oracle_normals(s, params[:, 0], params[:, 1]).tolist(),
            "grid": list(grid),
            "oracle_grid": oracle(s, uu.ravel(), vv.ravel())[0].tolist(),
            "bits": 16 if rational else 12,
        })
    return {"cases": cases, "atlas": atlas_spec(random_atlas(1, 3, 2, seed=7)),
            "atlas_mixed": [3, 5, 9, 3, 5, 2],
            "atlas_timed": atlas_spec(sphere_atlas(10, 3, 2, noise=0.01, rational=True))}


def atlas_spec(atlas) -> dict:
    """An AtlasSurface as the keyword arguments that rebuild it (JSON)."""
    return {"degree": atlas.degree, "spans": atlas.spans, "vertices": atlas.vertices,
            "quads": atlas.quads, "edge_points": atlas.edge_points,
            "face_points": atlas.face_points, "weights": atlas.weights}


@pytest.fixture(scope="module")
def in_pyodide(spec, tmp_path_factory) -> dict:
    if NODE is None:
        pytest.skip("node is not installed: cannot run Pyodide")
    if not PYODIDE.is_file():
        pytest.skip(f"Pyodide's npm package is not installed ({PYODIDE} missing): "
                    "run npm ci in web/")
    path = tmp_path_factory.mktemp("pyodide") / "input.json"
    path.write_text(json.dumps(spec))
    proc = subprocess.run([NODE, str(RUNNER), str(CHECKS), str(path)], capture_output=True,
                          text=True, timeout=300, cwd=PROJECT_ROOT)
    assert proc.returncode == 0, f"the Pyodide run failed:\n{proc.stderr[-4000:]}"
    record = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"Pyodide: load {record['load_seconds']:.1f} s, checks {record['run_seconds']:.1f} s")
    return record


def test_client_py_imports_in_pyodide_without_numpy(in_pyodide):
    assert in_pyodide["python"].startswith("3.")
    assert in_pyodide["result"]["kernel"] == "python"  # numpy is not there: pure Python
    assert in_pyodide["load_seconds"] > 0


def test_checks_pass_in_pyodide(in_pyodide):
    checks = in_pyodide["result"]["checks"]
    # 4 per case, the circle, bad input, detail tiles, 4 of the worker's session (a rigidly
    # placed region among them), 3 atlas, 1 of the session on an atlas bundle, 1 welded pack,
    # 1 control mesh
    assert len(checks) == 3 * 4 + 3 + 4 + 3 + 1 + 1 + 1
    failed = {name: err for name, err in checks.items() if err is not None}
    assert not failed


def test_same_bytes_as_cpython(in_pyodide, spec):
    here = pyodide_checks.run(spec)
    assert {name: err for name, err in here["checks"].items() if err is not None} == {}
    there = in_pyodide["result"]["digests"]
    assert set(there) == set(here["digests"])
    differ = sorted(name for name in there if there[name] != here["digests"][name])
    assert not differ, f"Pyodide and CPython produce different bytes for {differ}"
    for name, seconds in in_pyodide["result"]["timings"].items():  # 600 patches, d=3, s=2
        print(f"{name}: Pyodide {seconds:.2f} s, CPython {here['timings'][name]:.2f} s")
