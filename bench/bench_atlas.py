"""Whole objects: every scan point against the mesh a visitor is drawn, at every level.

For each object of ``../shared/data`` (a closed bust, statues, a mask, a range scan and a
registration of 15 range scans), fit with the DEFAULT options (as ``tessera fit SCAN OUT``
does), then for every level the bundle offers (the base alone, then each detail level):

* the bytes a visitor downloads to see it: the manifest as served (gzip) + the base (with
  a single patch's ``pieces.tsa``, drawn at every level) + the detail tiles of levels
  ``0..L`` (:func:`client_py.bundle.plan_level`);
* the distance of ALL scan points to the drawn mesh (``client_py``'s tessellation of that
  level in the scan frame, at the resolution ``tessera tessellate --level L`` uses):
  RMS, max, and the share within 0.5 % of the bounding-box diagonal;
* dense samples of the drawn mesh against the scan: the largest distance (fins, spikes,
  walls, skirts), as a share of the diagonal;
* an atlas's folds (:func:`bench.pleats.pleat_stats`): pleats of its base and the share of
  level 0's area turned over against it;
* the welded mesh's open border, against the scan's own, and the share of it farther than
  ``BORDER_REACH`` of the diagonal from the scan's border (a hole or skirt where the object
  is closed: the issue's border must lie only where the scan is open);
* beside it, quadric decimation + Draco of the scan mesh at the nearest byte count at or
  under Tessera's (``bench.bench_rate_distortion.draco_points``), scored the same way.

It writes ``bench/results/atlas.json`` and, per object, a picture of the scan and the
finest drawn level from six directions (``bench/results/atlas/<object>.png``) with the
silhouette IoU of each view. ``TESSERA_ATLAS_OBJECTS=bunny,lucy`` picks objects; the
others keep their records from the earlier ``atlas.json`` (with their own ``date``).
The base is the fit's default (``--base smooth`` since session 31);
``TESSERA_ATLAS_BASE=patches`` fits the patches base (``--base patches``) into
``atlas-patches.json`` and ``atlas-patches/``.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from bench import RESULTS, print_table, write_results
from bench.pleats import pleat_stats
from bench.scoring import (
    border_edges,
    boundary_length,
    diagonal,
    normal_errors,
    point_errors,
    render_views,
    reverse_errors,
    save_picture,
)
from client_py.mesh_arrays import mesh_arrays
from fitter.fitting.io import ScanError
from fitter.fitting.options import OPTION

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"
OBJECTS = {
    "bunny": DATA / "stanford-bunny" / "bun_zipper.ply.gz",
    "nefertiti": DATA / "nefertiti" / "nefertiti-lowres.obj",
    "lucy": DATA / "stanford-lucy" / "lucy.ply",
    "laurana": DATA / "laurana-bust" / "laurana.ply",
    "buddha scan 0": DATA / "happy-buddha-rangescans" / "happyStandRight_0.ply.gz",
    "bali-mask": DATA / "bali-mask" / "mask.obj",
    "happy-buddha 15 scans": DATA / "happy-buddha-rangescans" / "happyStandRight.conf",
}
#: the atlas base fitted (``--base``), the fit's default unless ``TESSERA_ATLAS_BASE`` names
#: another: the default's results are ``atlas.json`` and ``atlas/``, another base's
#: ``atlas-<base>.json`` and ``atlas-<base>/`` (``atlas-patches``)
DEFAULT_BASE = OPTION["base"].default
BASE = os.environ.get("TESSERA_ATLAS_BASE", DEFAULT_BASE)
NAME = "atlas" if BASE == DEFAULT_BASE else f"atlas-{BASE}"
PICTURES = RESULTS / NAME
BORDER_REACH = 0.005  # a drawn border farther than this (x diagonal) from the scan's is off it


def _objects() -> dict[str, Path]:
    wanted = [n.strip() for n in os.environ.get("TESSERA_ATLAS_OBJECTS", "").split(",")
              if n.strip()]
    unknown = [n for n in wanted if n not in OBJECTS]
    if unknown:
        raise ValueError(f"TESSERA_ATLAS_OBJECTS: unknown object(s) {', '.join(unknown)}; "
                         f"known: {', '.join(OBJECTS)}")
    chosen = {n: OBJECTS[n] for n in wanted} if wanted else dict(OBJECTS)
    return {n: p for n, p in chosen.items() if p.exists()}


def served_manifest_bytes(bundle: Path) -> int:
    """The manifest as the server sends it to a visitor that accepts gzip:
    ``fitter.collection.bundles.served_manifest`` of the file, compressed as
    ``fitter.server.files.compress`` does (a browser that accepts brotli gets fewer)."""
    from fitter.collection.bundles import served_manifest
    from fitter.server.files import compress

    manifest = json.loads((bundle / "manifest.json").read_text())
    return len(compress(served_manifest(manifest), "gzip"))


def drawn_levels(bundle: Path) -> list[dict]:
    """Every level a visitor can see (``-1`` the base alone, then each detail level): its
    drawn mesh in the scan frame and the bytes downloaded to see it."""
    from client_py.bundle import (
        base_file,
        pieces_entry,
        plan_level,
        plan_levels,
        tessellate_bundle,
    )

    manifest = json.loads((bundle / "manifest.json").read_text())
    pieces = pieces_entry(manifest)  # a single patch's pieces are drawn at every level
    base_bytes = sum((bundle / name).stat().st_size
                     for name in [base_file(manifest)] + ([pieces["file"]] if pieces else []))
    manifest_bytes = served_manifest_bytes(bundle)
    plans = [plan_level(manifest, -1)] + plan_levels(manifest)
    out = []
    for plan in plans:
        mesh = tessellate_bundle(manifest, lambda name: (bundle / name).read_bytes(),
                                 level=plan.level, resolution=plan.resolution, kernel="numpy")
        vertices, faces = mesh_arrays(mesh)
        out.append({"level": plan.level, "bytes": manifest_bytes + base_bytes
                    + plan.detail_bytes, "vertices": vertices, "faces": faces,
                    "resolution": plan.resolution})
    return out


def _view(bundle: Path) -> tuple[np.ndarray, np.ndarray]:
    manifest = json.loads((bundle / "manifest.json").read_text())
    view = manifest.get("view") or {}
    up = np.asarray(view.get("up", (0.0, 1.0, 0.0)), dtype=float)
    front = np.asarray(view.get("front", (0.0, 0.0, 1.0)), dtype=float)
    return front, up


def _scan_mesh(scan) -> tuple[np.ndarray, np.ndarray | None]:
    faces = None if scan.faces is None else np.asarray(scan.faces, dtype=np.int64)
    return np.asarray(scan.points, dtype=float), faces


def score_object(name: str, path: Path, work: Path) -> dict:
    """Fit ``path`` with the default options and score every level it offers."""
    from fitter.fitting.io import load_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    scan = load_scan(path)
    points, scan_faces = _scan_mesh(scan)
    diag = diagonal(points)
    bundle = work / name.replace(" ", "-")
    start = time.perf_counter()
    fit_scan(scan, bundle, FitOptions(base=BASE))
    fit_s = time.perf_counter() - start
    manifest = json.loads((bundle / "manifest.json").read_text())
    tolerance = 1e-6 * diag
    scan_border = (boundary_length(points, scan_faces, tolerance)
                   if scan_faces is not None else None)
    scan_ends = None if scan_faces is None else border_edges(points, scan_faces, tolerance)[0]
    rows = []
    levels = drawn_levels(bundle)
    for level in levels:
        err = point_errors(points, level["vertices"], level["faces"], diag)
        back = reverse_errors(level["vertices"], level["faces"], points, scan_faces, diag)
        border = boundary_length(level["vertices"], level["faces"], tolerance, scan_ends,
                                 BORDER_REACH * diag)
        turn = (normal_errors(level["vertices"], level["faces"], points, scan_faces)
                if scan_faces is not None else None)
        rows.append({"level": level["level"], "bytes": level["bytes"],
                     "resolution": level["resolution"], "triangles": len(level["faces"]),
                     "all_points": err, "mesh_to_scan": back, "normals": turn,
                     "border": border})
    finest = levels[-1]
    iou = None
    if scan_faces is not None:
        picture, iou = render_views({"scan": (points, scan_faces),
                                     "tessera": (finest["vertices"], finest["faces"])},
                                    *_view(bundle))
        PICTURES.mkdir(parents=True, exist_ok=True)
        save_picture(picture, PICTURES / f"{bundle.name}.png", ["scan", "tessera (finest)"])
    draco = _draco_rows(points, scan_faces, diag, [r["bytes"] for r in rows])
    atlas = (manifest.get("base") or {}).get("kind") == "atlas"
    return {"object": name, "base": BASE, "points": int(len(points)), "diagonal": diag,
            "scan_faces": None if scan_faces is None else int(len(scan_faces)),
            "scan_border": scan_border, "fit_s": fit_s,
            "format_version": manifest.get("format_version"),
            "patches": (manifest.get("base") or {}).get("patches", 1),
            "layout": _chosen_layout(manifest), "trials": (manifest.get("fit") or {}).get("trials"),
            "pieces": manifest.get("pieces"),
            "levels": rows, "silhouette_iou": iou, "draco": draco,
            "pleats": pleat_stats(bundle) if atlas else None}


def _chosen_layout(manifest: dict) -> str | None:
    """The atlas layout the fit kept (``'plain'`` or ``'weighted'``, with ``' + splits'``
    when ``fit.refine_far_base`` split some of its triangles after the trials); ``None``
    for a single patch or a bundle that does not say."""
    fit = manifest.get("fit") or {}
    triangles = fit.get("triangles") or 0
    tried = [t for t in fit.get("trials") or [] if "layout" in t
             and (t.get("triangles") or 0) <= triangles]
    if not tried:
        return None
    kept = max(tried, key=lambda t: t["triangles"])
    return kept["layout"] + ("" if kept["triangles"] == triangles else " + splits")


def _draco_rows(points: np.ndarray, faces: np.ndarray | None, diag: float,
                budgets: list[int]) -> list[dict]:
    """Quadric decimation + Draco of the scan mesh: for each budget, the lowest RMS (all
    points) of the encodings at or under it, and how its surface turns from the scan's
    (:func:`normal_errors`). ``[]`` for a cloud or without the libraries."""
    if faces is None:
        return []
    try:
        from bench.bench_rate_distortion import decimated, draco_coded, draco_points
    except ImportError:
        return []
    try:
        encodings = draco_points(points, points, faces)
    except ImportError:
        return []
    out = []
    for budget in budgets:
        fits = [e for e in encodings if e["bytes"] <= budget]
        best = min(fits, key=lambda e: e["rms"]) if fits else None
        turn = None
        if best is not None:  # the same encoding again (both steps are deterministic)
            _, dv, df = draco_coded(*decimated(points, faces, best["target"]), best["bits"])
            turn = normal_errors(dv, df, points, faces)
        out.append({"budget": budget, "best": best, "normals": turn,
                    "rms_relative": None if best is None else best["rms"] / diag})
    return out


def _with_earlier(results: list[dict]) -> list[dict]:
    """``results`` with the earlier ``atlas.json``'s records of the objects not re-run now
    (``TESSERA_ATLAS_OBJECTS``), each keeping the ``date`` of the run that measured it."""
    path = RESULTS / f"{NAME}.json"
    if not path.exists():
        return results
    earlier = json.loads(path.read_text())
    measured = {r["object"] for r in results}
    kept = [{"date": earlier.get("date"), **r} for r in earlier.get("objects", [])
            if r.get("object") not in measured]
    now = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return [{"date": now, **r} for r in results] + kept


def _turn(ours: dict | None, draco: dict | None) -> str:
    """A table cell: the mean and p90 angle (:func:`normal_errors`), Draco's in brackets."""
    if ours is None:
        return "-"
    cell = f"{ours['mean']:.1f} / {ours['p90']:.1f}"
    return cell if draco is None else cell + f" ({draco['mean']:.1f} / {draco['p90']:.1f})"


def run() -> dict | None:
    objects = _objects()
    if not objects:
        print(f"atlas: no scans under {DATA}; skipped")
        return None
    results = []
    with tempfile.TemporaryDirectory(prefix="tessera-atlas-") as tmp:
        for name, path in objects.items():
            print(f"atlas: {name} ...", flush=True)
            try:
                results.append(score_object(name, path, Path(tmp)))
            except ScanError as exc:  # reported, and the other objects still measured
                print(f"atlas: {name}: {exc}")
                results.append({"object": name, "error": str(exc)})
    table = []
    for r in results:
        if "error" in r:
            table.append([r["object"], "-", "-", "-", "-", "-", "-", "-", "-", "-", "-",
                          r["error"][:60]])
            continue
        for level, draco in zip(r["levels"], r["draco"] or [None] * len(r["levels"]),
                                strict=True):
            best = None if draco is None else draco["best"]
            table.append([r["object"], r["patches"], level["level"], level["bytes"],
                          f"{100 * level['all_points']['within_0.5%']:.1f}",
                          f"{level['all_points']['rms']:.3g}",
                          "-" if best is None else f"{best['rms']:.3g}",
                          _turn(level.get("normals"), None if draco is None
                                else draco.get("normals")),
                          f"{100 * level['mesh_to_scan']['max_relative']:.2f}",
                          level["border"]["border_edges"],
                          "-" if r["scan_border"] is None else r["scan_border"]["border_edges"],
                          "-" if "off_share" not in level["border"]
                          else f"{100 * level['border']['off_share']:.1f}"])
    print_table("atlas: ALL scan points vs the drawn mesh, per level (default fit)",
                ["object", "patches", "level", "bytes", "% within 0.5%", "RMS all",
                 "Draco RMS", "normal turn deg, mean / p90 (Draco's)",
                 "max mesh->scan %diag", "border edges", "scan border",
                 "% border off scan's"], table)
    for r in results:  # folds: pleats of the base, level 0's area turned over against it
        if r.get("pleats"):
            p = r["pleats"]
            turned = ("no level 0" if p["l0_turned_share"] is None
                      else f"level 0 turned over on {100 * p['l0_turned_share']:.2f} % of its area")
            print(f"atlas: {r['object']}, pleats: {p['base_pairs_120']} folded triangle pairs "
                  f"in {p['base_pleated_patches']} base patches, {turned}")
    for r in results:  # where each finest level is farther than 1 % from its scan
        places = [] if "error" in r else r["levels"][-1]["mesh_to_scan"]["places"]
        if places:
            print(f"atlas: {r['object']}, finest level, places farther than 1 %: " + "; ".join(
                f"{100 * p['max_relative']:.2f} % (area {100 * p['far_share']:.3f} %, "
                f"facing {p['facing']:.2f})" for p in places))
    record = {"objects": _with_earlier(results)}
    write_results(NAME, record)
    return record
