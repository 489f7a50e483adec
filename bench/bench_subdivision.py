"""A subdivision base against Draco and the atlas's base, at the atlas base's bytes.

The atlas's base (bicubic patches joined C0, ``base.tsa``) had 1.7-2.0 times the RMS of
quadric decimation + Draco at its bytes on Nefertiti, Lucy and Laurana (``bench atlas``).
This measures a candidate: the same decimated mesh Draco codes, used instead as the
*control mesh* of a subdivision surface whose points are fitted to the scan
(``fitter.fitting.atlas.subdivision``), drawn after ``--levels`` steps:

* ``loop``: Loop's rules on the decimated triangles;
* ``catmull-clark``: Catmull-Clark's rules on the same triangles (each becomes three quads
  at the first step, so every face after it could carry the atlas's per-patch
  ``[0, 1]^2`` detail tiles).

For each mesh of ``../shared/data`` (a cloud has no Draco row): the budget is the patches
base's bytes in ``bench/results/atlas-patches.json`` (``atlas.json`` until session 31, when
the smooth base became the default; 24,000 without it); Draco's best decimation
and bits at or under it (``bench.bench_rate_distortion``); the two control meshes are that
decimation, fitted, and coded by Draco at the same bits (a control mesh whose file passes
the budget is made smaller and fitted again). Every figure is measured against ALL scan
points on the mesh a reader draws from the *decoded* control mesh: RMS, the share within
0.5 % of the diagonal, the largest distance from the drawn mesh to the scan (200,000 area
samples) and how its surface turns from the scan's (``bench.scoring.normal_errors``). Six
views of the scan, Draco's mesh and both surfaces are saved to
``bench/results/subdivision/<object>.png``.

Not a format: nothing here is written to a bundle, and a browser would need Draco's
decoder or a coder of our own for the control mesh. It says what a smooth base buys
(docs/benchmarks.md, "Session 28"). All six meshes take about 25 minutes on the 2-core
machine (two fits of ten rounds each, 17-130 s apiece); ``--objects nefertiti`` one.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from bench import RESULTS, print_table, write_results
from bench.bench_atlas import OBJECTS, _scan_mesh
from bench.scoring import (
    diagonal,
    normal_errors,
    point_errors,
    render_views,
    reverse_errors,
    save_picture,
)

PICTURES = RESULTS / "subdivision"
DEFAULT_BUDGET = 24_000
LEVELS = 3  # steps drawn: 64 triangles (Loop) or quads (Catmull-Clark) a control face
ROUNDS = 10
ATTEMPTS = 3  # control meshes tried per scheme, each smaller, to stay within the budget


def add_arguments(parser) -> None:
    parser.add_argument("--objects", default="", help="comma-separated names (default: all "
                        f"meshes: {', '.join(OBJECTS)})")
    parser.add_argument("--levels", type=int, default=LEVELS, help="subdivision steps drawn")
    parser.add_argument("--rounds", type=int, default=ROUNDS, help="fitting rounds")


def _atlas_bases() -> dict[str, dict]:
    """Each object's patches base (level -1) in the last ``TESSERA_ATLAS_BASE=patches python
    -m bench atlas``: its bytes and RMS."""
    path = RESULTS / "atlas-patches.json"
    if not path.exists():
        return {}
    records = json.loads(path.read_text()).get("objects", [])
    return {r["object"]: {"bytes": r["levels"][0]["bytes"],
                          "rms": r["levels"][0]["all_points"]["rms"]}
            for r in records if r.get("levels") and r["levels"][0].get("level") == -1}


def _scored(points, faces, drawn_v, drawn_f, diag) -> dict:
    """Every scan point against the drawn mesh, the drawn mesh against the scan, its turn."""
    errors = point_errors(points, drawn_v, drawn_f, diag)
    back = reverse_errors(drawn_v, drawn_f, points, faces, diag)
    turn = normal_errors(drawn_v, drawn_f, points, faces)
    return {"rms": errors["rms"], "rms_relative": errors["rms_relative"],
            "within_0.5%": errors["within_0.5%"], "max_mesh_to_scan": back["max_relative"],
            "normals": turn}


def _subdivision_row(points, faces, diag, target, bits, scheme, levels, rounds):
    """The scan decimated to ``target`` triangles as the control mesh of ``scheme``, fitted,
    coded by Draco at ``bits``: its record and the mesh a reader draws from the file."""
    from bench.bench_rate_distortion import decimated, draco_coded
    from fitter.fitting.atlas.subdivision import fit_control_points, subdivided

    control, triangles = decimated(points, faces, target)
    control, triangles = control.astype(float), triangles.astype(np.int64)
    start = time.perf_counter()
    surface = subdivided(len(control), [triangles], levels, scheme)
    fitted, history = fit_control_points(points, control, surface, faces, rounds=rounds)
    seconds = time.perf_counter() - start
    size, cv, cf = draco_coded(fitted.astype(np.float32), triangles.astype(np.int32), bits)
    drawn = subdivided(len(cv), [cf], levels, scheme)  # what a reader draws from the file
    x = drawn.matrix @ cv
    row = {"control_triangles": int(len(triangles)), "control_points": int(len(control)),
           "fit_s": seconds, "history": history, "bytes": size,
           **_scored(points, faces, x, drawn.triangles, diag)}
    return row, (x, drawn.triangles)


def score_object(name: str, path: Path, budget: int, levels: int, rounds: int,
                 atlas_base: dict | None = None) -> dict | None:
    """Draco and the two subdivision surfaces of ``path`` at ``budget`` bytes."""
    from bench.bench_rate_distortion import decimated, draco_coded, draco_points, frontier
    from fitter.fitting.io import load_scan
    from fitter.fitting.orient import find_view

    scan = load_scan(path)
    points, faces = _scan_mesh(scan)
    if faces is None:
        return None
    diag = diagonal(points)
    best = frontier(draco_points(points, points, faces), budget)
    if best is None:
        return None
    size, dv, df = draco_coded(*decimated(points, faces, best["target"]), best["bits"])
    record = {"object": name, "points": int(len(points)), "budget": budget,
              "draco_triangles": int(len(df)), "bits": best["bits"], "levels": levels,
              "draco": {"bytes": size, **_scored(points, faces, dv, df, diag)}}
    meshes = {"scan": (points, faces), "draco": (dv, df)}

    for scheme in ("loop", "catmull-clark"):
        target = best["target"]
        for _ in range(ATTEMPTS):  # a control mesh whose file passes the budget is made smaller
            row, drawn = _subdivision_row(points, faces, diag, target, best["bits"], scheme,
                                          levels, rounds)
            row["over_budget"] = row["bytes"] > budget
            if not row["over_budget"]:
                break
            target = int(target * budget / row["bytes"] * 0.98)
        record[scheme], meshes[scheme] = row, drawn
    if atlas_base is not None:
        record["atlas_base"] = atlas_base

    view = find_view(scan)
    picture, _ = render_views(meshes, np.asarray(view.front, float), np.asarray(view.up, float))
    PICTURES.mkdir(parents=True, exist_ok=True)
    save_picture(picture, PICTURES / f"{name.replace(' ', '-')}.png", list(meshes))
    return record


def run(objects: str = "", levels: int = LEVELS, rounds: int = ROUNDS) -> dict | None:
    wanted = [n.strip() for n in objects.split(",") if n.strip()] or list(OBJECTS)
    unknown = [n for n in wanted if n not in OBJECTS]
    if unknown:
        raise SystemExit(f"unknown object(s) {', '.join(unknown)}; known: {', '.join(OBJECTS)}")
    bases = _atlas_bases()
    records = []
    for name in wanted:
        if not OBJECTS[name].exists():
            print(f"{name}: {OBJECTS[name]} is absent, skipped")
            continue
        base = bases.get(name)
        record = score_object(name, OBJECTS[name], base["bytes"] if base else DEFAULT_BUDGET,
                              levels, rounds, base)
        if record is None:
            print(f"{name}: a cloud (no Draco row), skipped")
            continue
        records.append(record)
    if not records:
        print("no scan mesh found under ../shared/data: nothing measured")
        return None
    rows = []
    for r in records:
        draco = r["draco"]
        for method in ("draco", "loop", "catmull-clark"):
            m = r[method]
            rows.append([r["object"], method, f"{m['bytes']:,}", f"{m['rms']:.4g}",
                         f"{m['rms'] / draco['rms']:.2f}", f"{100 * m['within_0.5%']:.2f}",
                         f"{100 * m['max_mesh_to_scan']:.2f}",
                         f"{m['normals']['mean']:.1f} / {m['normals']['p90']:.1f}"])
        if "atlas_base" in r:
            a = r["atlas_base"]
            rows.append([r["object"], "atlas base", f"{a['bytes']:,}", f"{a['rms']:.4g}",
                         f"{a['rms'] / draco['rms']:.2f}", "", "", ""])
    print_table("A subdivision base at the atlas base's bytes (RMS of all scan points)",
                ["object", "surface", "bytes", "RMS all points", "x Draco", "% within 0.5 %",
                 "max mesh->scan %", "turn mean / p90 deg"], rows)
    return write_results("subdivision", {"benchmark": "subdivision", "objects": records})
