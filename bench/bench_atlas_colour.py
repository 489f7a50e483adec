"""Atlas colour: the scan's colours against the colours a visitor is drawn, every point.

For each coloured object in ``../shared/data`` that fits as an atlas (the Laurana bust:
per-vertex RGB; the Bali mask: a 4096² UV texture), fit with default options, then per
detail level ``L`` (``-1`` the base): the mesh the browser draws at ``L``
(``client_py.atlas_mesh.tessellate_atlas`` with the tiles of levels ``0..L``) coloured per
vertex from the colour packs of its colour level, decoded from the bundle's WebP bytes
(``client_py.atlas_texture``), and for EVERY scan vertex its colour against the drawn
colour at its foot point on that mesh (``fitter.fitting.atlas.texture.colour_error``: mean
``|ΔRGB|`` per channel, RMS and P95 of the Euclidean ``ΔRGB``, 0..255). Bytes: the colour
packs of the level (what a visitor downloads for colour at ``L``). The same cells encoded
at other WebP qualities and not at all (the sampling's own error) show what the encoding
costs. The picture ``bench/results/atlas_colour/<object>.png``: the scan's own colours and
Tessera's drawn colours from the same cameras (unlit, so only colour differs).
The base is the fit's default (``--base smooth`` since session 31);
``TESSERA_ATLAS_BASE=patches`` (``bench.bench_atlas.BASE``) fits the patches base (``--base
patches``) into ``atlas_colour-patches.json`` and ``atlas_colour-patches/``.
"""

from __future__ import annotations

import io
import json
import tempfile
from pathlib import Path

import numpy as np

from bench import RESULTS, print_table, write_results
from bench.bench_atlas import BASE, DEFAULT_BASE
from bench.scoring import _camera, diagonal, view_directions
from client_py.mesh_arrays import mesh_arrays

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
OBJECTS = {"laurana-bust": DATA / "laurana-bust" / "laurana.ply",
           "bali-mask": DATA / "bali-mask" / "mask.obj"}
#: the results' name: another base than the default's goes to ``atlas_colour-<base>.json``
#: and its pictures to ``atlas_colour-<base>/`` (``atlas_colour-patches``), so the default
#: base's are kept
NAME = "atlas_colour" if BASE == DEFAULT_BASE else f"atlas_colour-{BASE}"
PICTURES = RESULTS / NAME
QUALITIES = (75, 82, 90, 95)


def _decode(data: bytes) -> tuple[int, int, bytes]:
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        rgb = im.convert("RGB")
        return rgb.width, rgb.height, rgb.tobytes()


def _drawn(atlas, resolution: int, tiles: dict, packs) -> tuple[np.ndarray, ...]:
    from client_py.atlas_mesh import tessellate_atlas
    from client_py.atlas_texture import atlas_vertex_colours, colours_by_patch

    mesh = tessellate_atlas(atlas, resolution, tiles or None, kernel="numpy")
    rgb = atlas_vertex_colours(mesh.patches, mesh.uvs, colours_by_patch(packs, len(atlas.quads)))
    return (*mesh_arrays(mesh), np.frombuffer(rgb, np.uint8).reshape(-1, 3).astype(float))


def _packs_of(nodes, cells=None, files=None):
    """The ColourPacks of one colour level's manifest packs ``nodes`` (``atlas_colour``'s,
    with their cell and block), read as the client reads them (``colour_packs_of``): from
    the raw ``cells`` laid out unencoded, or from decoded ``files`` (the bundle's, or the
    same cells re-encoded at another quality)."""
    from client_py.bundle import colour_packs_of
    from fitter.fitting.atlas.texture import pack_image

    images = {}
    for node in nodes:
        if files is None:
            image = pack_image(cells[node["first"]:node["first"] + node["count"]],
                               node["cell"], node["block"])
            images[node["file"]] = (image.shape[1], image.shape[0], image.tobytes())
        else:
            images[node["file"]] = _decode(files[node["file"]])
    return colour_packs_of(nodes, images)


def _splat_colour(points, colours, frame, centre, half, size):
    """Z-buffered colour splats of ``points`` seen along ``-frame[2]`` (unlit)."""
    local = (points - centre) @ frame.T
    px = ((local[:, 0] / half + 1) * 0.5 * size).astype(np.int64)
    py = ((1 - local[:, 1] / half) * 0.5 * size).astype(np.int64)
    inside = (px >= 0) & (px < size) & (py >= 0) & (py < size)
    pixel = py[inside] * size + px[inside]
    depth, rgb = local[inside, 2], colours[inside]
    order = np.lexsort((-depth, pixel))
    pixel, rgb = pixel[order], rgb[order]
    first = np.ones(len(pixel), bool)
    first[1:] = pixel[1:] != pixel[:-1]
    image = np.full((size * size, 3), 255.0)
    image[pixel[first]] = rgb[first]
    return image.reshape(size, size, 3)


def _surface_colour_samples(vertices, faces, colours, count, seed=1):
    rng = np.random.default_rng(seed)
    tri = vertices[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(faces), count, p=area / area.sum())
    w = rng.dirichlet([1, 1, 1], count)
    points = np.einsum("nk,nkc->nc", w, tri[pick])
    rgb = np.einsum("nk,nkc->nc", w, colours[faces[pick]])
    return points, rgb


def picture(scan_mesh, drawn_mesh, front, up, path, size=320, samples=1_500_000,
            face=False):
    """Scan (top row) and Tessera (bottom row) from the front, a 3/4 view and the side;
    ``face``: zoomed on the top fifth along ``up`` (a bust's face), 3x the samples."""
    from PIL import Image, ImageDraw

    samples *= 3 if face else 1
    sampled = [_surface_colour_samples(*m, samples) for m in (scan_mesh, drawn_mesh)]
    reference = scan_mesh[0]
    centre = 0.5 * (reference.max(axis=0) + reference.min(axis=0))
    half = 0.55 * diagonal(reference)
    if face:
        height = reference @ up
        top = reference[height > height.max() - 0.3 * (height.max() - height.min())]
        centre = 0.5 * (top.max(axis=0) + top.min(axis=0))
        half = 0.35 * diagonal(top)
    views = view_directions(front, up)
    three_quarter = views["front"][0] + views["left"][0]
    cameras = [views["front"], (three_quarter / np.linalg.norm(three_quarter), up),
               views["right"]]
    rows = []
    for points, rgb in sampled:
        rows.append(np.concatenate([_splat_colour(points, rgb, _camera(d, u), centre, half,
                                                  size) for d, u in cameras], axis=1))
    image = Image.fromarray(np.clip(np.concatenate(rows), 0, 255).astype(np.uint8))
    draw = ImageDraw.Draw(image)
    for k, label in enumerate(["scan's colours", "Tessera's drawn colours (finest level)"]):
        draw.text((6, k * size + 6), label, fill=(200, 30, 30))
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path)


def score_object(name: str, path: Path, work: Path) -> dict:
    from client_py.atlas_format import read_atlas
    from client_py.bundle import atlas_colour, atlas_level_detail, atlas_tiles
    from fitter.fitting.atlas.texture import (
        coarser_cells,
        colour_error,
        encode_levels,
        sample_cells,
        scan_vertex_colours,
    )
    from fitter.fitting.io import load_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    scan = load_scan(path)
    bundle = fit_scan(scan, work / name, FitOptions(base=BASE)).path
    manifest = json.loads((bundle / "manifest.json").read_text())
    if manifest.get("format_version") != 2:
        return {"object": name, "skipped": "fitted as a single patch, not an atlas"}
    colour = atlas_colour(manifest)
    spec = atlas_tiles(manifest)
    atlas, _ = read_atlas((bundle / "base.tsa").read_bytes())
    groups = manifest["tiles"]["detail"]["groups"]
    files = {p["file"]: (bundle / p["file"]).read_bytes() for p in colour.packs}
    read = lambda n: (bundle / n).read_bytes()  # noqa: E731
    levels = len(spec.levels)
    finest_tiles = atlas_level_detail(manifest, read, levels - 1)
    top_cell = colour.levels[-1]["cell"]
    raw = coarser_cells(sample_cells(scan, atlas, finest_tiles, top_cell), len(colour.levels))
    by_quality = {}
    for quality in QUALITIES:
        q_files, _, q_rows = encode_levels(raw, groups, 1.0, quality)
        by_quality[quality] = (q_files, [r["bytes_total"] for r in q_rows])
    rows = []
    for level in range(-1, levels):
        c = min(max(level, 0), len(colour.levels) - 1)
        cell = colour.levels[c]["cell"]
        tiles = atlas_level_detail(manifest, read, level) if level >= 0 else {}
        row = {"level": level, "colour_level": c, "cell": cell,
               "bytes": colour.levels[c]["bytes_total"]}
        nodes = [p for p in colour.packs if p["level"] == c]
        for label, packs in [("bundle", _packs_of(nodes, files=files)),
                             ("unencoded", _packs_of(nodes, cells=raw[c])),
                             *[(f"q{q}", _packs_of(nodes, files=by_quality[q][0]))
                               for q in QUALITIES]]:
            vertices, faces, rgb = _drawn(atlas, spec.resolution(level), tiles, packs)
            row[label] = colour_error(scan, vertices, faces, rgb)
        for q in QUALITIES:
            row[f"q{q}"]["bytes"] = by_quality[q][1][c]
        rows.append(row)
        if level == levels - 1:
            scan_rgb = scan_vertex_colours(scan)
            bundle_packs = _packs_of(nodes, files=files)
            vertices, faces, rgb = _drawn(atlas, spec.resolution(level), tiles, bundle_packs)
            view = manifest["view"]
            for face in (False, True):
                picture((np.asarray(scan.points, float), np.asarray(scan.faces), scan_rgb),
                        (vertices, faces, rgb), np.asarray(view["front"]),
                        np.asarray(view["up"]),
                        PICTURES / f"{name}{'-face' if face else ''}.png", face=face)
    return {"object": name, "base": BASE, "points": int(len(scan.points)),
            "patches": spec.patches,
            "groups": len(groups), "colour_levels": len(colour.levels),
            "source": manifest["tiles"]["texture"]["source"],
            "packs": [{"file": p["file"], "bytes": p["bytes"], "patches": p["count"],
                       "size": f"{p['width']}x{p['height']}"} for p in colour.packs],
            "manifest_error": manifest["tiles"]["texture"]["error"], "levels": rows}


def run() -> dict | None:
    present = {n: p for n, p in OBJECTS.items() if p.is_file()}
    if not present:
        print("no coloured object in ../shared/data: skipped")
        return None
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, path in present.items():
            results.append(score_object(name, path, Path(tmp)))
    table = []
    for r in results:
        for row in r.get("levels", []):
            b = row["bundle"]
            table.append([r["object"], row["level"], row["colour_level"], row["cell"],
                          f"{row['bytes']:,}", f"{b['mean_abs']:.2f}", f"{b['rms']:.2f}",
                          f"{b['p95']:.1f}", f"{row['unencoded']['mean_abs']:.2f}",
                          " / ".join(f"{row[f'q{q}']['mean_abs']:.2f}@{row[f'q{q}']['bytes']:,}"
                                     for q in QUALITIES)])
    print_table("Atlas colour: every scan vertex against the drawn colour at its foot point",
                ["object", "level", "colour level", "texels/patch side", "colour bytes",
                 "mean |dRGB|", "RMS dRGB", "P95 dRGB", "unencoded mean |dRGB|",
                 "mean |dRGB| @ bytes, WebP q" + "/".join(map(str, QUALITIES))], table)
    record = {"objects": results}
    write_results(NAME, record)
    return record
