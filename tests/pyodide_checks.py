"""client_py checks that run inside Pyodide (and, for the comparison, in CPython).

Pyodide's npm package has no pytest and no numpy offline, so this is a plain
script, standard library only. ``tests/pyodide_runner.mjs`` runs it with the
global ``INPUT`` (reference values computed in CPython with scipy, written as
JSON by ``tests/test_pyodide.py``) and reads back ``RESULT``:

    {"kernel": ..., "checks": {name: error message or None},
     "digests": {name: sha256 of bytes client_py produced}}

The digests (tessellated arrays, PLY and .tsp bytes, all from the pure-Python
kernel) are compared with the same script's digests in CPython: the browser
must produce the very same bytes. The worker's session (``client_py.session``)
is driven here as mesh-worker.js drives it: patch, manifest, tiles, a region
with skirts, the level plan and a level PLY.
"""

from __future__ import annotations

import hashlib
import json
import math
import time

from client_py import (
    DetailTile,
    NurbsSurface,
    PatchFormatError,
    TextureImage,
    TrimMask,
    hang_skirts,
    plan_level,
    read_detail_tile,
    read_patch,
    tessellate_grid,
    tessellate_region,
    write_detail_tile,
    write_level_ply,
    write_patch,
    write_ply,
)
from client_py._kernel import KERNEL_NAME
from client_py.atlas import AtlasSurface
from client_py.atlas_format import canonical_atlas, read_atlas, write_atlas
from client_py.atlas_mesh import tessellate_atlas
from client_py.control_mesh import read_control_codes, read_control_header, write_control_mesh
from client_py.layers import tile_rect, transform_mesh
from client_py.session import WorkerSession


def _surface(spec: dict) -> NurbsSurface:
    trim = TrimMask(spec["trim"]) if spec.get("trim") else None
    return NurbsSurface(tuple(spec["degree"]), tuple(spec["knots"]), spec["control_points"],
                        spec["weights"], trim=trim, metadata=spec.get("metadata"))


def _max_diff(a, b) -> float:
    return max(abs(x - y) for pa, pb in zip(a, b, strict=True)
               for x, y in zip(pa, pb, strict=True))


def _sha(data) -> str:
    return hashlib.sha256(bytes(data)).hexdigest()


def _check(checks: dict, name: str, func) -> None:
    """Record ``None`` when ``func`` passes, else the failure (any exception) as text."""
    try:
        func()
        checks[name] = None
    except Exception as exc:  # noqa: BLE001 - every failure is reported, by name
        checks[name] = f"{type(exc).__name__}: {exc}"


def _truncations_refused(read, data: bytes, steps: int, error: type, name: str) -> None:
    """``read`` of about ``steps`` evenly spaced truncations of ``data`` each raises
    ``error``."""
    for cut in range(0, len(data), max(1, len(data) // steps)):
        try:
            read(data[:cut])
        except error:
            continue
        raise AssertionError(f"{name} truncated to {cut} bytes was accepted")


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise AssertionError(message)


def _lcg_values(count: int, seed: int, spread: int) -> list[int]:
    """Deterministic pseudo-random integers in ``-spread..spread`` (no ``random`` module
    state to share between interpreters), mostly small as detail coefficients are."""
    out, x = [], seed
    for _ in range(count):
        x = (1103515245 * x + 12345) % 2**31
        out.append((x % (2 * spread + 1) - spread) // (1 + (x >> 20) % 4))
    return out


def _control_mesh_checks(checks: dict, digests: dict, timings: dict) -> None:
    """A smooth base's control mesh (``.tsa`` versions 5 and 6): CPython's bytes and codes,
    read back, truncations refused; both versions' pure-Python decoding timed. The mesh: a
    40 x 40 height field of integers (no libm: the same floats in every interpreter)."""
    n = 40
    heights = _lcg_values(n * n, 11, 60)
    points = [(4.0 * i + h % 3, 3.5 * j, h / 4 + (i - 20) ** 2 / 8)
              for i in range(n) for j in range(n) for h in (heights[i * n + j],)]
    triangles = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            triangles += [(a, b, c), (a, c, d)]
    files = {version: write_control_mesh(points, triangles, 11, {"units": "mm"},
                                         version=version) for version in (5, 6)}

    def both_versions_read_back():
        decoded = {}
        for version, data in files.items():
            digests[f"control_mesh.v{version}"] = _sha(data)
            _require(read_control_header(data)["version"] == version, "version")
            clock = time.perf_counter()
            decoded[version] = read_control_codes(data)
            timings[f"control mesh v{version} read ({n * n} points)"] = \
                time.perf_counter() - clock
            _truncations_refused(read_control_codes, data, 41, PatchFormatError,
                                 f"v{version}")
        _require(decoded[5] == decoded[6], "versions 5 and 6 decode to different meshes")
        _require(len(files[6]) < len(files[5]), "version 6 is not the smaller")
        digests["control_mesh.decoded"] = _sha(repr(decoded[6]).encode())

    _check(checks, "control mesh: .tsa v5 and v6 read back alike; truncations refused",
           both_versions_read_back)


def _detail_checks(checks: dict, digests: dict) -> None:
    """Detail tiles (range-coded .tsd) and region tessellation give CPython's bytes."""
    mask = TrimMask([[(r * 7 + c * 3) % 5 != 0 for c in range(8)] for r in range(8)])
    tiles = [DetailTile(1, i, j, 2, 6, 0.015625, tuple(_lcg_values(64, 11 * i + j + 1, 40)),
                        mask if (i, j) == (1, 0) else None) for i in range(2) for j in range(2)]
    blobs = [write_detail_tile(t) for t in tiles]
    for k, data in enumerate(blobs):
        digests[f"tile{k}.tsd"] = _sha(data)

    def tile_round_trip():
        for tile, data in zip(tiles, blobs, strict=True):
            _require(read_detail_tile(data) == tile, f"tile {tile.i}_{tile.j} changed")
            for cut in range(0, len(data), 5):
                try:
                    read_detail_tile(data[:cut])
                except PatchFormatError:
                    continue
                raise AssertionError(f"tile truncated to {cut} bytes was accepted")

    _check(checks, "detail tiles round trip; truncations raise PatchFormatError",
           tile_round_trip)
    U = [0, 0, 0, 0.5, 1, 1, 1]
    grid = [[[i / 3, j / 3, 0.1 * ((i * j) % 3)] for j in range(4)] for i in range(4)]
    trim = TrimMask([[not (2 <= r <= 4 and 1 <= c <= 5) for c in range(8)] for r in range(8)])
    base = NurbsSurface((2, 2), (U, U), grid, trim=trim)
    mesh = tessellate_region(base, (0.25, 0.0, 1.0, 0.75), 23, 19, tiles, kernel="python")
    for name in ("positions", "normals", "uvs", "indices"):
        digests[f"region.{name}"] = _sha(memoryview(getattr(mesh, name)).cast("B"))


def _session_checks(checks: dict, digests: dict) -> None:
    """The worker's session, driven as mesh-worker.js drives it, on a bundle made here."""
    U = [0, 0, 0, 0.5, 1, 1, 1]
    grid = [[[i / 3, j / 3, 0.1 * ((i * j) % 3)] for j in range(4)] for i in range(4)]
    trim = TrimMask([[not (r >= 5 and c >= 4) for c in range(8)] for r in range(8)])
    transform = [[0, -2, 0, 250], [2, 0, 0, -40], [0, 0, 2, 1200], [0, 0, 0, 1]]
    base = NurbsSurface((2, 2), (U, U), grid, trim=trim,
                        metadata={"units": "mm", "transform": transform})
    spans, files, nodes = 3, {}, []
    for level in range(2):
        for i in range(1 << level):
            for j in range(1 << level):
                tile = DetailTile(level, i, j, 2, spans, 2.0**-7,
                                  tuple(_lcg_values(25, 5 + 7 * level + 3 * i + j, 30)))
                name = f"detail/{level}/{i}_{j}.tsd"
                files[name] = write_detail_tile(tile)
                nodes.append({"level": level, "i": i, "j": j, "file": name,
                              "bytes": len(files[name])})
    textures = [{"level": k, "i": i, "j": j, "width": 4, "height": 4,
                 "rgb": bytes((17 * m + 40 * k + 9 * i + 5 * j) % 256 for m in range(48))}
                for k, i, j in ((0, 0, 0), (1, 0, 0), (1, 1, 1))]
    manifest = {"units": "mm", "tiles": {
        "detail": {"spans_per_tile": spans, "levels": [{"level": 0, "rms": 0.2},
                                                       {"level": 1, "rms": 0.1}],
                   "nodes": nodes},
        "texture": {"nodes": [{"level": t["level"], "i": t["i"], "j": t["j"],
                               "file": f"texture/{t['level']}/{t['i']}_{t['j']}.webp",
                               "bytes": 100} for t in textures]}}}
    session = WorkerSession(kernel="python")
    session.load_patch(write_patch(base, bits=16), "base.tsp")
    session.read_manifest(json.dumps(manifest))
    patch = read_patch(write_patch(base, bits=16))

    def plan():
        offered = session.level_choices()
        _require(offered["max_resolution"] == 1025, "the grid's cap")
        choices = offered["levels"]
        _require([c["level"] for c in choices] == [0, 1], f"levels {choices}")
        for c in choices:
            want = [n["file"] for n in nodes if n["level"] <= c["level"]]
            _require(c["detail_files"] == want, f"level {c['level']}: {c['detail_files']}")
            _require(c["resolution"] == 2 * spans * 2 ** c["level"] + 1, "grid")
        _require(len(choices[1]["texture_nodes"]) == 3, "texture nodes of level 1")

    _check(checks, "session: the plan names the manifest's tiles and grid", plan)
    held = ["detail/0/0_0.tsd", "detail/1/1_0.tsd"]
    for name in held:
        session.add_tile(name, files[name])
    region = session.region_mesh(1, 1, 0, 7, held, 0.05)
    for name in ("positions", "normals", "uvs", "indices"):
        digests[f"session.region.{name}"] = _sha(memoryview(getattr(region, name)).cast("B"))

    def region_is_tessellate_region_plus_skirts():
        tiles = [read_detail_tile(files[name]) for name in held]
        rect = tile_rect(1, 1, 0)
        mesh = tessellate_region(patch, rect, 7, 7, tiles, "python")
        mesh = transform_mesh(hang_skirts(mesh, patch, rect, 7, tiles, 0.05, "python"),
                              transform, "python")
        for name in ("positions", "normals", "uvs", "indices"):
            _require(getattr(region, name) == getattr(mesh, name), f"region {name} differs")
        _require(region.vertex_count == 49 + 2 * 2 * 7, "two inner sides, 2 x 7 vertices each")

    _check(checks, "session: region mesh is tessellate_region + skirts, scan frame",
           region_is_tessellate_region_plus_skirts)

    # a rigid transform (a quarter turn about z and a shift): the region is made on the
    # scan-frame patch (issue 14), equal to the mapped patch-frame mesh to float32 rounding
    rigid = [[0, -1, 0, 250], [1, 0, 0, -40], [0, 0, 1, 1200], [0, 0, 0, 1]]
    placed = NurbsSurface((2, 2), (U, U), grid, trim=trim,
                          metadata={"units": "mm", "transform": rigid})
    fast = WorkerSession(kernel="python")
    fast.load_patch(write_patch(placed, bits=16), "base.tsp")
    for name in held:
        fast.add_tile(name, files[name])
    rigid_region = fast.region_mesh(1, 1, 0, 7, held, 0.05)
    for name in ("positions", "normals", "uvs", "indices"):
        digests[f"session.rigid_region.{name}"] = _sha(
            memoryview(getattr(rigid_region, name)).cast("B"))

    def rigid_region_is_the_mapped_mesh():
        placed_patch = read_patch(write_patch(placed, bits=16))
        tiles = [read_detail_tile(files[name]) for name in held]
        rect = tile_rect(1, 1, 0)
        mesh = tessellate_region(placed_patch, rect, 7, 7, tiles, "python")
        mesh = transform_mesh(hang_skirts(mesh, placed_patch, rect, 7, tiles, 0.05, "python"),
                              rigid, "python")
        _require(rigid_region.uvs == mesh.uvs and rigid_region.indices == mesh.indices,
                 "uvs or indices differ")
        def worst(a, b):
            return max(abs(x - y) for x, y in zip(a, b, strict=True))

        scale = max(abs(x) for x in mesh.positions)
        _require(worst(rigid_region.positions, mesh.positions) <= 1e-6 * scale, "positions")
        _require(worst(rigid_region.normals, mesh.normals) <= 1e-6, "normals")

    _check(checks, "session: a rigidly placed region made in the scan frame is the mapped mesh",
           rigid_region_is_the_mapped_mesh)
    fresh = {name: memoryview(data) for name, data in files.items() if name not in held}
    ply = session.level_ply(1, fresh, textures[::-1])
    digests["session.level_ply"] = _sha(ply.data)
    session.tessellate_base(9)
    digests["session.base_ply"] = _sha(session.base_ply(9, bytes(range(243))).data)

    def level_ply_is_write_level_ply():
        tiles = [read_detail_tile(files[n["file"]]) for n in nodes]
        images = [TextureImage(t["level"], t["i"], t["j"], 4, 4, t["rgb"]) for t in textures]
        data, _ = write_level_ply(patch, tiles, 1, plan_level(manifest, 1).resolution,
                                  "base.tsp", images, kernel="python")
        _require(ply.data == data, "the session's level PLY is not write_level_ply's")
        _require(b"comment detail level 1: base patch + 5 detail tiles" in ply.data, "header")

    _check(checks, "session: level PLY is write_level_ply of the plan",
           level_ply_is_write_level_ply)


def _atlas_checks(checks: dict, digests: dict, timings: dict, spec: dict) -> None:
    """The atlas (``.tsa`` bytes, the welded mesh) gives CPython's bytes, is closed and
    oriented, and lies on the reference evaluator; the pure-Python tessellation is timed."""
    atlas = canonical_atlas(AtlasSurface(**spec["atlas"]))  # the numbering .tsa v3 stores
    data = write_atlas(atlas, 12, {"units": "mm"})
    digests["atlas.tsa"] = _sha(data)

    def atlas_round_trip():
        back, meta = read_atlas(data)
        _require(meta == {"units": "mm"} and back.quads == atlas.quads, "layout changed")
        before = [*atlas.vertices, *atlas.edge_points, *atlas.face_points]
        after = [*back.vertices, *back.edge_points, *back.face_points]
        for axis in range(3):
            a, b = [p[axis] for p in before], [p[axis] for p in after]
            err = max(abs(x - y) for x, y in zip(a, b, strict=True))
            _require(err <= (max(a) - min(a)) / (2 * 4095) * (1 + 1e-9), f"axis {axis}: {err}")
        digests["atlas.tsa_decoded"] = _sha(repr((after, back.weights)).encode())
        _truncations_refused(read_atlas, data, 97, PatchFormatError, "atlas")

    _check(checks, "atlas: .tsa round trip; truncations raise PatchFormatError",
           atlas_round_trip)
    meshes = {"uniform": tessellate_atlas(atlas, 5, kernel="python"),
              "mixed": tessellate_atlas(atlas, spec["atlas_mixed"], kernel="python")}
    for key, mesh in meshes.items():
        for name in ("positions", "normals", "uvs", "indices", "patches"):
            digests[f"atlas.{key}.{name}"] = _sha(memoryview(getattr(mesh, name)).cast("B"))

    def closed_and_oriented():
        for key, mesh in meshes.items():
            directed: dict = {}
            idx = mesh.indices
            for t in range(0, len(idx), 3):
                a, b, c = idx[t : t + 3]
                for edge in ((a, b), (b, c), (c, a)):
                    directed[edge] = directed.get(edge, 0) + 1
            _require(all(n == 1 for n in directed.values()), f"{key}: an edge runs twice")
            _require(all((b, a) in directed for a, b in directed), f"{key}: a boundary edge")

    _check(checks, "atlas: welded meshes are closed and consistently oriented",
           closed_and_oriented)

    def on_the_reference_evaluator():
        mesh = meshes["uniform"]
        for k in range(0, mesh.vertex_count, 7):
            f, (u, v) = mesh.patches[k], mesh.uvs[2 * k : 2 * k + 2]
            point = atlas.patch_surface(f).evaluate(u, v)
            got = mesh.positions[3 * k : 3 * k + 3]
            err = max(abs(x - y) for x, y in zip(point, got, strict=True))
            _require(err <= 1e-6, f"vertex {k} is {err} off its patch")

    _check(checks, "atlas: vertices lie on their patch (reference evaluator)",
           on_the_reference_evaluator)
    if "atlas_timed" in spec:
        timed = AtlasSurface(**spec["atlas_timed"])
        for r in (9, 17):
            start = time.perf_counter()
            tessellate_atlas(timed, r, kernel="python")
            timings[f"tessellate_atlas r={r}"] = time.perf_counter() - start
    _atlas_session_checks(checks, digests, timings, atlas, data,
                          AtlasSurface(**spec["atlas_timed"]) if "atlas_timed" in spec else None)
    _welded_pack_checks(checks, digests, atlas)


def _atlas_manifest(atlas: AtlasSurface, groups: int, spans: int, levels: int,
                    base_resolution: int, packs: dict) -> dict:
    """A version-2 manifest of ``atlas`` in ``groups`` equal contiguous groups (its last
    takes the rest), ``packs`` = ``{(level, group): bytes}``."""
    count = len(atlas.quads) // groups
    spans_of = [(g * count, count if g < groups - 1 else len(atlas.quads) - g * count)
                for g in range(groups)]
    return {"format": "tessera-bundle", "format_version": 2, "units": "mm",
            "base": {"file": "base.tsa", "kind": "atlas", "patches": len(atlas.quads),
                     "resolution": base_resolution},
            "tiles": {"version": 2, "texture": None, "detail": {
                "format": "tsdp", "format_version": 2, "tile_format_version": 2,
                "degree": 2, "spans_per_tile": spans, "base": {"rms": 0.1, "max": 0.3},
                "levels": [{"level": k, "rms": 0.1 / 2**k} for k in range(levels)],
                "groups": [{"first": f, "count": c, "center": [0, 0, 0], "radius": 1}
                           for f, c in spans_of],
                "packs": [{"level": k, "group": g, "bytes": len(b), "geometric_error": 0.1}
                          for (k, g), b in sorted(packs.items())]}}}


def _atlas_session_checks(checks: dict, digests: dict, timings: dict, atlas: AtlasSurface,
                          data: bytes, timed: AtlasSurface | None) -> None:
    """The worker's session on an atlas bundle (manifest version 2), driven as
    mesh-worker.js drives it: base.tsa, the manifest, packs, a mesh with groups at different
    levels (welded, closed), a level PLY; the re-tessellation the viewer asks for is timed."""
    from client_py.atlas_detail import pack_name, write_pack

    packs = {}
    for level in range(2):
        for g in range(len(atlas.quads)):
            tiles = [DetailTile(level, i, j, 2, 2, 0.002,
                                tuple(_lcg_values(16, 100 * level + 10 * g + 2 * i + j, 6)))
                     for i in range(1 << level) for j in range(1 << level)]
            packs[level, g] = write_pack(level, {g: tiles})
    manifest = _atlas_manifest(atlas, len(atlas.quads), 2, 2, 5, packs)
    session = WorkerSession(kernel="python")
    facts = session.load_atlas(memoryview(data), "base.tsa")
    session.read_manifest(json.dumps(manifest))
    refinement = session.atlas_refinement()
    for key in ((0, 0), (1, 0), (0, 3)):
        session.add_pack(pack_name(*key), memoryview(packs[key]))
    mixed = session.atlas_mesh([1, -1, -1, 0, -1, -1])
    for name in ("positions", "normals", "uvs", "indices", "patches"):
        digests[f"atlas_session.mixed.{name}"] = _sha(memoryview(getattr(mixed, name)).cast("B"))
    fresh = {pack_name(*key): memoryview(b) for key, b in packs.items()
             if not session.holds_pack(pack_name(*key))}
    ply = session.level_ply(1, fresh)
    digests["atlas_session.level_ply"] = _sha(ply.data)

    def refines_welded():
        _require(facts["kind"] == "atlas" and facts["patches"] == len(atlas.quads), "facts")
        _require(refinement["resolutions"] == [5, 5, 9], f"{refinement['resolutions']}")
        directed: dict = {}
        idx = mixed.indices
        for t in range(0, len(idx), 3):
            a, b, c = idx[t : t + 3]
            for edge in ((a, b), (b, c), (c, a)):
                directed[edge] = directed.get(edge, 0) + 1
        _require(all(n == 1 for n in directed.values()), "an edge runs twice")
        _require(all((b, a) in directed for a, b in directed), "a boundary edge")
        _require(ply.level == 1 and ply.resolution == 9, "level PLY")
        try:
            session.atlas_mesh([1, 1, -1, 0, -1, -1])
        except ValueError as exc:
            _require("detail/0/1.tsdp" in str(exc), str(exc))
        else:
            raise AssertionError("a group without its packs was drawn")

    _check(checks, "atlas session: groups at different levels, welded and closed; level PLY",
           refines_welded)
    if timed is not None:  # the viewer's re-tessellation: 6 groups of 100 patches
        session = WorkerSession(kernel="python")
        session.load_atlas(write_atlas(timed, 12), "base.tsa")
        session.read_manifest(json.dumps(_atlas_manifest(timed, 6, 4, 2, 9, {})))
        for levels in ([-1] * 6, [0, -1, -1, -1, -1, -1], [1, 1, -1, -1, -1, -1]):
            start = time.perf_counter()
            mesh = session.atlas_mesh(levels)
            timings[f"atlas_mesh {levels} ({mesh.vertex_count} vertices)"] = \
                time.perf_counter() - start


def _welded_pack_checks(checks: dict, digests: dict, atlas: AtlasSurface) -> None:
    """A welded pack (version 4: each shared border coefficient coded once) of every patch
    at level 1, its tiles cut from level grids whose border rings share one value per slot
    (``AtlasSurface.border_slots``): the same bytes and the same tiles back in both
    interpreters."""
    from client_py.atlas import ring_positions
    from client_py.atlas_detail import read_pack, write_pack

    n, size = 2 * 2 + 2, 2 + 2  # level 1, spans 2, degree 2
    slots: dict = {}
    tiles = {}
    for f in range(len(atlas.quads)):
        flat = _lcg_values(n * n, 7 + f, 6)
        grid = [flat[a * n : (a + 1) * n] for a in range(n)]
        for (a, b), slot in zip(ring_positions(n), atlas.border_slots(f, n), strict=True):
            grid[a][b] = slots.setdefault(slot, grid[a][b])
        tiles[f] = [DetailTile(1, i, j, 2, 2, 0.002, tuple(grid[2 * i + a][2 * j + b]
                                                          for a in range(size)
                                                          for b in range(size)))
                    for i in range(2) for j in range(2)]
    data = write_pack(1, tiles, atlas)
    digests["welded_pack"] = _sha(data)

    def round_trip():
        _require(data[4] == 4 and data[21] == 1, "a welded version 4 pack")
        _require(read_pack(data, atlas) == (1, tiles), "welded pack round trip")
        _require(len(data) < len(write_pack(1, tiles)), "welding saves bytes")

    _check(checks, "welded detail pack: round trip, fewer bytes", round_trip)


def run(spec: dict) -> dict:
    checks: dict = {}
    digests: dict = {}
    timings: dict = {}
    for k, case in enumerate(spec["cases"]):
        s = _surface(case["surface"])
        pts = case["params"]

        def evaluate(s=s, pts=pts, case=case):
            got = [s.evaluate(u, v) for u, v in pts]
            err = _max_diff(got, case["oracle_points"])
            _require(err <= 1e-10, f"evaluate differs from scipy by {err}")
            nrm = [s.normal(u, v) for u, v in pts]
            err = _max_diff(nrm, case["oracle_normals"])
            _require(err <= 1e-9, f"normal differs from scipy by {err}")

        _check(checks, f"case{k}: evaluate and normal match scipy", evaluate)
        nu, nv = case["grid"]
        mesh = tessellate_grid(s, nu, nv, kernel="python")
        for name in ("positions", "normals", "uvs", "indices"):
            digests[f"case{k}.{name}"] = _sha(memoryview(getattr(mesh, name)).cast("B"))

        def grid_positions(mesh=mesh, case=case):
            ref = case["oracle_grid"]
            got = [mesh.positions[3 * i : 3 * i + 3] for i in range(len(ref))]
            err = _max_diff(got, ref)
            scale = max(1.0, max(abs(c) for p in ref for c in p))
            _require(err <= 2.0**-23 * scale, f"grid positions differ from scipy by {err}")

        _check(checks, f"case{k}: tessellated grid matches scipy", grid_positions)
        digests[f"case{k}.ply_binary"] = _sha(write_ply(mesh, texture_file="t.png"))
        digests[f"case{k}.ply_ascii"] = _sha(write_ply(mesh, binary=False))
        data = write_patch(s, bits=case["bits"])
        digests[f"case{k}.tsp"] = _sha(data)

        def round_trip(s=s, data=data, case=case, k=k):
            r = read_patch(data)
            _require(r.knots == s.knots, "knots changed")
            _require(r.trim == s.trim and r.metadata == s.metadata, "trim or metadata changed")
            half_step = 1.0 / (2 * (2 ** case["bits"] - 1))
            for axis in range(3):
                a, b = s.flat_points[axis::3], r.flat_points[axis::3]
                err = max(abs(x - y) for x, y in zip(a, b, strict=True))
                _require(err <= half_step * (max(a) - min(a)) * (1 + 1e-9),
                         f"axis {axis} off by {err}")
            digests[f"case{k}.tsp_decoded"] = _sha(repr((r.flat_points, r.flat_weights)).encode())

        _check(checks, f"case{k}: patch round trip", round_trip)

        def corruption(data=data):
            for cut in range(len(data)):
                try:
                    read_patch(data[:cut])
                except PatchFormatError:
                    continue
                raise AssertionError(f"truncation to {cut} bytes was accepted")
            for offset in range(0, len(data), 7):
                flipped = bytearray(data)
                flipped[offset] ^= 0x41
                try:
                    read_patch(bytes(flipped))
                except PatchFormatError:
                    continue
                raise AssertionError(f"a change at byte {offset} was accepted")

        _check(checks, f"case{k}: truncated and changed files raise PatchFormatError", corruption)

    def quarter_circle():
        c = math.sqrt(0.5)
        s = NurbsSurface((2, 1), ([0, 0, 0, 1, 1, 1], [0, 0, 1, 1]),
                         [[[2, 0, 0], [2, 0, 1]], [[2, 2, 0], [2, 2, 1]], [[0, 2, 0], [0, 2, 1]]],
                         [[1, 1], [c, c], [1, 1]])
        mesh = tessellate_grid(s, 33, 2, kernel="python")
        for i in range(0, len(mesh.positions), 3):
            r = math.hypot(mesh.positions[i], mesh.positions[i + 1])
            _require(abs(r - 2.0) <= 4e-7, f"vertex {i // 3} at radius {r}")
        for u in (0.0, 0.1, 0.5, 0.77, 1.0):
            x, y, _ = s.evaluate(u, 0.5)
            _require(abs(math.hypot(x, y) - 2.0) <= 1e-12, f"radius at u={u}")

    _check(checks, "quarter cylinder is an exact circle", quarter_circle)

    def rejects_bad_input():
        U = [0, 0, 0, 1, 1, 1]
        grid = [[[i, j, 0] for j in range(3)] for i in range(3)]
        for kwargs, word in (({"knots": ([0, 0, 1, 1], U)}, "knots[0] (U) has 4 knots"),
                             ({"weights": [[1, 1, 1], [1, -1, 1], [1, 1, 1]]}, "weights[1][1]")):
            args = {"degree": (2, 2), "knots": (U, U), "control_points": grid} | kwargs
            try:
                NurbsSurface(**args)
            except ValueError as exc:
                _require(word in str(exc), f"message {exc!r} lacks {word!r}")
            else:
                raise AssertionError(f"{kwargs} was accepted")

    _check(checks, "invalid input raises ValueError naming it", rejects_bad_input)
    _detail_checks(checks, digests)
    _control_mesh_checks(checks, digests, timings)
    _session_checks(checks, digests)
    if "atlas" in spec:
        _atlas_checks(checks, digests, timings, spec)
    return {"kernel": KERNEL_NAME, "checks": checks, "digests": digests, "timings": timings}


if "INPUT" in globals() and INPUT is not None:  # noqa: F821 - set by pyodide_runner.mjs
    RESULT = run(INPUT)  # noqa: F821
