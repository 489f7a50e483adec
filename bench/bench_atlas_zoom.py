"""What a visitor sees zoomed into a real atlas: each object of ``../shared/data`` that the
default fit makes an atlas of (``bench_atlas.OBJECTS``; ``TESSERA_ATLAS_OBJECTS`` picks some)
is fitted with the default options, served by the Flask app and opened in the viewer
(headless Chromium, 1000 x 700), then looked at from close to three of its detail groups
in turn (the one farthest along the bundle's ``view.front``, the highest along ``view.up``
and the one nearest the middle of the object), from ``DISTANCE`` times the group's radius
in front of it (``window.tessera.atlasView``).

Per view: the level the viewer drew that group at and the deepest level on screen, the
groups refined, the packs' bytes fetched so far, the refinement's batches, the time from
its choice to its first batch drawn (``atlas_first_batch_ms``: the nearest detail), the
worker's Python time over all its batches and the time to the whole view refined (wall time
of ``atlasView``, SwiftShader's draws included), and a picture of the
canvas (``bench/results/atlas_zoom/<object>-<view>.png``). A group that stays at the base
(level -1) in a close view is the failure this benchmark exists for: the viewer's budget
of drawn vertices then holds no refinement. Writes ``bench/results/atlas_zoom.json``.
"""

from __future__ import annotations

import io
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench import RESULTS, ROOT, print_table, write_results
from bench.bench_atlas import _objects

DISTANCE = 1.5  # the camera this many group radii in front of the group's centre
PICTURES = RESULTS / "atlas_zoom"
PICTURE_WIDTH = 500  # pixels: the canvas's pictures halved


def _views(manifest: dict) -> dict[str, int]:
    """The three groups looked at: ``front``, ``top`` and ``middle``."""
    groups = manifest["tiles"]["detail"]["groups"]
    centres = np.array([g["center"] for g in groups])
    front, up = np.array(manifest["view"]["front"]), np.array(manifest["view"]["up"])
    middle = 0.5 * (centres.min(axis=0) + centres.max(axis=0))
    return {"front": int(np.argmax(centres @ front)), "top": int(np.argmax(centres @ up)),
            "middle": int(np.argmin(np.linalg.norm(centres - middle, axis=1)))}


def _look(page, manifest: dict, group: int) -> dict:
    g = manifest["tiles"]["detail"]["groups"][group]
    centre = np.array(g["center"])
    position = centre + DISTANCE * g["radius"] * np.array(manifest["view"]["front"])
    clock = time.perf_counter()
    stats = page.evaluate("([p, t]) => window.tessera.atlasView(p, t)",
                          [position.tolist(), centre.tolist()])
    levels = stats["atlas_levels"]
    return {"group": group, "level": levels[group], "deepest": max(levels),
            "levels": len(manifest["tiles"]["detail"]["levels"]),
            "refined": sum(k >= 0 for k in levels), "groups": len(levels),
            "pack_bytes": stats["atlas_pack_bytes"], "vertices": stats["vertices"],
            "batches": stats.get("atlas_batches"),  # 0: the levels shown already (no update)
            "first_batch_ms": round(stats.get("atlas_first_batch_ms") or 0),
            "python_ms": round(stats.get("atlas_update_python_ms") or 0),
            "wall_s": round(time.perf_counter() - clock, 1)}


def _picture(png: bytes, path: Path) -> None:
    """``png`` scaled to :data:`PICTURE_WIDTH` pixels wide, saved at ``path``."""
    from PIL import Image

    image = Image.open(io.BytesIO(png)).convert("RGB")
    height = round(image.height * PICTURE_WIDTH / image.width)
    image.resize((PICTURE_WIDTH, height), Image.LANCZOS).save(path, optimize=True)


def _object(browser, name: str, path: Path, root: Path) -> dict:
    from live import open_viewer, serve_collection

    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    folder = root / name.replace(" ", "-")
    fit_scan(path, folder, FitOptions())
    manifest = json.loads((folder / "manifest.json").read_text())
    if manifest.get("format_version") != 2:
        return {"object": name, "skipped": "a single patch (its tiles are not groups)"}
    out = {"object": name, "patches": manifest["base"]["patches"], "views": {}}
    with serve_collection(root) as live, \
            open_viewer(browser, f"{live.url}/objects/{folder.name}/", 300_000) as page:
        for view, group in _views(manifest).items():
            out["views"][view] = _look(page, manifest, group)
            _picture(page.locator("canvas").screenshot(), PICTURES / f"{folder.name}-{view}.png")
        out["errors"] = list(page.errors)
    return out


def run() -> dict | None:
    sys.path.insert(0, str(ROOT / "tests"))
    from live import CHROMIUM_PATH, chromium_launch_args

    objects = _objects()
    if not objects or not Path(CHROMIUM_PATH).exists():
        print(f"atlas_zoom: skipped (scans: {len(objects)}; {CHROMIUM_PATH} "
              f"{'present' if Path(CHROMIUM_PATH).exists() else 'missing'})")
        return None
    from playwright.sync_api import sync_playwright

    PICTURES.mkdir(parents=True, exist_ok=True)
    results = []
    with tempfile.TemporaryDirectory(prefix="tessera-atlas-zoom-") as tmp, \
            sync_playwright() as pw:
        browser = pw.chromium.launch(**chromium_launch_args())
        try:
            for name, path in objects.items():
                print(f"atlas_zoom: {name} ...", flush=True)
                results.append(_object(browser, name, path, Path(tmp)))
        finally:
            browser.close()
    rows = [[r["object"], r["patches"], view, v["group"], f"{v['level']} / {v['levels'] - 1}",
             v["deepest"], f"{v['refined']} / {v['groups']}", v["pack_bytes"], v["batches"],
             v["first_batch_ms"], v["python_ms"], v["wall_s"], len(r["errors"])]
            for r in results if "views" in r for view, v in r["views"].items()]
    print_table("atlas_zoom: a close view of a group, in the viewer (default fit)",
                ["object", "patches", "view", "group", "its level / finest", "deepest shown",
                 "groups refined", "pack bytes", "batches", "first batch ms", "Python ms",
                 "whole s", "errors"], rows)
    return write_results("atlas_zoom", {"distance_radii": DISTANCE, "objects": results})
