// The mesh worker: Pyodide + client_py in a module Web Worker, so the page never blocks on Python.
//
// Protocol (every request carries an `id`; every reply echoes it):
//   page -> {type: "init", pyodideUrl, pyodideSnapshotUrl?, clientPyUrl, patchUrl}
//   worker -> {type: "stage", stage: "runtime" | "client_py" | "patch", ...}   (progress)
//   worker -> {type: "ready", pyodide_load_ms, kernel, patch: {...}}           (init done)
//   page -> {type: "tessellate", resolution}  -> {type: "mesh", positions, normals, uvs, indices, ...}
//   page -> {type: "ply", resolution, colors?} -> {type: "ply", bytes, vertices, triangles}
//                                                  (client_py.write_ply of the base mesh)
//   page -> {type: "ply", resolution, level, names, fresh?: [{name, bytes}],
//            textures?: [{level, i, j, width, height, rgb}]}
//        -> {type: "ply", bytes, vertices, triangles, write_ms}  (level >= 0: the whole domain
//           at detail level `level`, tessellate_region over (0, 0, 1, 1) with the named tiles,
//           scan frame; each name is a tile the worker holds or one of `fresh`, decoded for this
//           request only; vertex colours sampled from the texture tiles when some are sent:
//           client_py.layers.TextureImage of the RGB bytes, rows top to bottom)
//   page -> {type: "tile", name, bytes}  -> {type: "tile", name, level, i, j}   (read_detail_tile, kept)
//   page -> {type: "drop", names}        -> {type: "dropped", names}            (forget tiles)
//   page -> {type: "region", level, i, j, grid, names, skirtDepth}
//        -> {type: "region", positions, normals, uvs, indices, tessellate_ms}  (tessellate_region
//           over node (level, i, j) with the named tiles, skirts on its inner borders, scan frame)
//   worker -> {type: "error", stage, message}   for any failure, with the reason
// Mesh arrays are copied once out of the WebAssembly heap (PyBuffer views die with the
// Python object) and then *transferred*, not copied again, to the page.

import { fetchBytes } from "./fetch-bytes.js";

const PY_ROOT = "/home/pyodide/tessera";

// Python side of the worker: thin wrappers over client_py, holding the loaded surface.
const PY_GLUE = `
import sys, time
if ${JSON.stringify(PY_ROOT)} not in sys.path:
    sys.path.insert(0, ${JSON.stringify(PY_ROOT)})
from array import array
from dataclasses import replace
from client_py import read_detail_tile, read_patch, tessellate_grid, tessellate_region, write_ply
from client_py import _kernel
from client_py.layers import TextureImage, tile_rect, transform_mesh

_surface = None
_patch = None  # the patch in its own frame: detail displaces along *its* normal
_tiles = {}  # bundle file name -> DetailTile, the detail tiles the page has handed over
_source = None
_last = (None, None)  # (resolution, mesh): "Download PLY" reuses the mesh on screen

def tessera_load(js_bytes, source):
    global _surface, _patch, _source, _last
    surface = read_patch(js_bytes.to_bytes())
    _patch = surface
    _tiles.clear()
    (u0, u1), (v0, v1) = surface.domain
    info = {
        "degree": list(surface.degree), "shape": list(surface.shape),
        "rational": surface.is_rational, "domain": [u0, u1, v0, v1],
        "trimmed": surface.trim is not None, "units": surface.metadata.get("units", "unknown"),
    }
    _surface = surface.to_scan_frame()
    _source = source
    _last = (None, None)
    lo, hi = _surface.bounding_box()
    info["bbox"] = [list(lo), list(hi)]
    return info

def tessera_tessellate(resolution):
    global _last
    t0 = time.perf_counter()
    mesh = tessellate_grid(_surface, resolution, resolution)
    _last = (resolution, mesh)
    return mesh, (time.perf_counter() - t0) * 1000.0

def tessera_ply(resolution, js_colors):
    t0 = time.perf_counter()
    mesh = _last[1] if _last[0] == resolution else tessellate_grid(_surface, resolution, resolution)
    if js_colors is not None:
        mesh = replace(mesh, colors=array("B", js_colors.to_bytes()))
    comments = [f"source {_source}", f"units {_surface.metadata.get('units', 'unknown')}",
                f"tessellated by client_py in the browser, {resolution}x{resolution} grid"]
    data = write_ply(mesh, binary=True, comments=comments)
    return data, mesh.vertex_count, mesh.triangle_count, (time.perf_counter() - t0) * 1000.0

def tessera_ply_level(level, resolution, names, fresh_names, fresh_bytes, texture_nodes,
                      texture_rgb):
    """PLY of the whole domain at detail level 'level': the base patch plus the named
    detail tiles (those of levels 0..level; held ones, or fresh ones sent with the request,
    which are decoded here and not kept), on a resolution x resolution grid, in the scan
    frame, with per-vertex colours sampled from the texture tiles given as
    [level, i, j, width, height] and their RGB bytes (rows top to bottom): what
    'tessera tessellate OUTDIR --level L' writes (client_py.tessellate_bundle).
    (No backquotes in here: this Python lives in a JavaScript template literal.)"""
    t0 = time.perf_counter()
    fresh = {}
    for name, data in zip(fresh_names, fresh_bytes, strict=True):
        try:
            fresh[name] = read_detail_tile(data.to_bytes())
        except ValueError as exc:
            raise ValueError(f"detail tile {name}: {exc}") from None
    tiles = []
    for name in names:
        tile = fresh[name] if name in fresh else _tiles.get(name)
        if tile is None:
            raise ValueError(f"detail tile {name} was neither handed over nor sent")
        if tile.level > level:
            raise ValueError(f"detail tile {name} is of level {tile.level}, finer than {level}")
        tiles.append(tile)
    textures = []
    for node, rgb in zip(texture_nodes, texture_rgb, strict=True):
        k, i, j, width, height = node
        try:
            textures.append(TextureImage(k, i, j, width, height, rgb.to_bytes()))
        except ValueError as exc:
            raise ValueError(f"texture tile {k}/{i}_{j}: {exc}") from None
    mesh = tessellate_region(_patch, (0.0, 0.0, 1.0, 1.0), resolution, resolution, tiles,
                             textures=textures)
    matrix = _patch.metadata.get("transform")
    if matrix is not None:
        mesh = transform_mesh(mesh, matrix)
    comments = [f"source {_source}", f"units {_surface.metadata.get('units', 'unknown')}",
                f"detail level {level}: base patch + {len(tiles)} detail tiles of levels 0..{level}",
                f"tessellated by client_py in the browser, {resolution}x{resolution} grid"]
    if textures:
        levels = sorted({t.level for t in textures})
        comments.append(f"vertex colours sampled from {len(textures)} texture tiles of levels "
                        + ", ".join(str(k) for k in levels))
    data = write_ply(mesh, binary=True, comments=comments)
    return data, mesh.vertex_count, mesh.triangle_count, (time.perf_counter() - t0) * 1000.0

def tessera_add_tile(name, js_bytes):
    tile = read_detail_tile(js_bytes.to_bytes())
    _tiles[name] = tile
    return [tile.level, tile.i, tile.j]

def tessera_drop_tiles(names):
    for name in names:
        _tiles.pop(name, None)

def _skirt(mesh, rect, n, tiles, depth):
    """Hang skirts (in the patch frame) from a region's borders inside the domain.

    A wall under each border, from the region's own edge S + P_k n down to
    S + (min_l P_l - depth) n, with P_l = sum_{k' <= l} D_k' the partial sums of levels
    l = -1 .. k (P_-1 = 0: the base). A coarser neighbour shows some P_l there (tiles of one
    level agree on their borders), a finer one lies within about 2 x the region's remaining
    error (depth) of P_k; whichever edge is higher, its wall hangs past the other, so no
    crack shows from the front. The walls never rise above the edge they hang from (no fins).
    Borders on the domain's outer edge get none (nothing to meet), trimmed-out cells neither.
    """
    u0, v0, u1, v1 = rect
    us = [u0 + (u1 - u0) * a / (n - 1) for a in range(n)]
    vs = [v0 + (v1 - v0) * b / (n - 1) for b in range(n)]
    (a0, a1), (b0, b1) = _patch.domain
    backend = _kernel.backend()
    tiles = sorted(tiles, key=lambda t: t.level)
    trim = _patch.trim
    half_u, half_v = 0.5 * (u1 - u0) / (n - 1), 0.5 * (v1 - v0) / (n - 1)
    # (side's u list, v list, grid index of its s-th vertex, inward cell centre of segment s)
    sides = []
    if u0 > 0.0:
        sides.append(([u0], vs, lambda s: s, lambda s: (u0 + half_u, vs[s] + half_v)))
    if u1 < 1.0:
        sides.append(([u1], vs, lambda s: (n - 1) * n + s, lambda s: (u1 - half_u, vs[s] + half_v)))
    if v0 > 0.0:
        sides.append((us, [v0], lambda s: s * n, lambda s: (us[s] + half_u, v0 + half_v)))
    if v1 < 1.0:
        sides.append((us, [v1], lambda s: s * n + n - 1, lambda s: (us[s] + half_u, v1 - half_v)))
    pos, nrm, uv, idx = mesh.positions, mesh.normals, mesh.uvs, mesh.indices
    for su, sv, vertex, inward in sides:
        points, normals, _ = backend.evaluate_grid(
            _patch, [a0 + (a1 - a0) * u for u in su], [b0 + (b1 - b0) * v for v in sv], "d")
        fields = [t.evaluate_grid(su, sv) for t in tiles]
        first = len(pos) // 3
        for s in range(n):
            partial = lo = 0.0
            for f in fields:
                partial += f[s]
                lo = min(lo, partial)
            lo, hi = lo - depth, partial
            p, q = points[3 * s : 3 * s + 3], normals[3 * s : 3 * s + 3]
            pos.extend(array("f", (p[0] + lo * q[0], p[1] + lo * q[1], p[2] + lo * q[2],
                                   p[0] + hi * q[0], p[1] + hi * q[1], p[2] + hi * q[2])))
            k = vertex(s)
            nrm.extend(nrm[3 * k : 3 * k + 3] * 2)
            uv.extend(uv[2 * k : 2 * k + 2] * 2)
        for s in range(n - 1):
            if trim is not None and not trim.covers(*inward(s)):
                continue
            a, b = first + 2 * s, first + 2 * s + 2
            idx.extend(array("I", (a, b, b + 1, a, b + 1, a + 1)))
    return mesh

def tessera_region(level, i, j, grid, names, skirt_depth):
    t0 = time.perf_counter()
    tiles = [_tiles[name] for name in names]
    for tile in tiles:
        if tile.level > level or tile.i != i >> (level - tile.level) \
                or tile.j != j >> (level - tile.level):
            raise ValueError(f"tile {tile.level}/{tile.i}_{tile.j} does not cover region "
                             f"{level}/{i}_{j}")
    rect = tile_rect(level, i, j)
    mesh = _skirt(tessellate_region(_patch, rect, grid, grid, tiles), rect, grid, tiles,
                  skirt_depth)
    matrix = _patch.metadata.get("transform")
    if matrix is not None:
        mesh = transform_mesh(mesh, matrix)
    return mesh, (time.perf_counter() - t0) * 1000.0
`;

let pyodide = null;
let glue = null;
let queue = Promise.resolve();

function post(message, transfer = []) {
  self.postMessage(message, transfer);
}

/** The last line of a Python traceback ("PatchFormatError: invalid ..."), else the message. */
function reason(error) {
  const text = String(error && error.message ? error.message : error).trim();
  if (error && error.type) {
    const lines = text.split("\n").filter((line) => line.trim());
    const last = lines[lines.length - 1] || text;
    return last.replace(/^[\w.]+: /, `${error.type}: `);
  }
  return text;
}

/** A copy of a Python buffer (array.array) as a standalone typed array. */
function copyBuffer(proxy) {
  const view = proxy.getBuffer();
  try {
    return view.data.slice();
  } finally {
    view.release();
    proxy.destroy();
  }
}


async function init({ pyodideUrl, pyodideSnapshotUrl, clientPyUrl, patchUrl }) {
  let stage = "runtime";
  try {
    post({ type: "stage", stage });
    const t0 = performance.now();
    const { loadPyodide } = await import(`${pyodideUrl}pyodide.mjs`);
    const tImported = performance.now();
    const options = { indexURL: pyodideUrl };
    if (pyodideSnapshotUrl) {
      // Interpreter memory with client_py imported, made by the server (fitter/server/snapshot.py).
      options._loadSnapshot = fetchBytes(pyodideSnapshotUrl, "the Pyodide snapshot");
    }
    pyodide = await loadPyodide(options);
    const pyodideLoadMs = performance.now() - t0;
    const stages = { import_ms: tImported - t0, load_pyodide_ms: pyodideLoadMs - (tImported - t0),
                     snapshot: Boolean(pyodideSnapshotUrl) };

    stage = "client_py";
    post({ type: "stage", stage, pyodide_load_ms: pyodideLoadMs });
    const response = await fetch(clientPyUrl);
    if (!response.ok) throw new Error(`cannot fetch client_py (${clientPyUrl}): HTTP ${response.status}`);
    const sources = await response.json();
    for (const [name, text] of Object.entries(sources.files)) {
      const path = `${PY_ROOT}/${sources.package}/${name}`;
      pyodide.FS.mkdirTree(path.slice(0, path.lastIndexOf("/")));
      pyodide.FS.writeFile(path, text);
    }
    pyodide.runPython(PY_GLUE);
    stages.client_py_ms = performance.now() - t0 - pyodideLoadMs;
    glue = {
      load: pyodide.globals.get("tessera_load"),
      tessellate: pyodide.globals.get("tessera_tessellate"),
      ply: pyodide.globals.get("tessera_ply"),
      plyLevel: pyodide.globals.get("tessera_ply_level"),
      addTile: pyodide.globals.get("tessera_add_tile"),
      dropTiles: pyodide.globals.get("tessera_drop_tiles"),
      region: pyodide.globals.get("tessera_region"),
    };
    const kernel = pyodide.runPython("_kernel.KERNEL_NAME");

    stage = "patch";
    post({ type: "stage", stage });
    const tPatch = performance.now();
    const bytes = await fetchBytes(patchUrl, "the base patch");
    const infoProxy = glue.load(bytes, patchUrl.split("/").pop());
    const patch = infoProxy.toJs({ dict_converter: Object.fromEntries });
    infoProxy.destroy();
    stages.patch_ms = performance.now() - tPatch;
    post({ type: "ready", pyodide_load_ms: pyodideLoadMs, kernel, patch, patch_bytes: bytes.length,
           client_py_version: sources.version, stages });
  } catch (error) {
    post({ type: "error", stage, message: reason(error) });
  }
}

/** Post a (Mesh, ms) result of the glue as transferable typed arrays, with `fields` added. */
function postMesh(result, fields) {
  try {
    const [mesh, ms] = result;
    const positions = copyBuffer(mesh.positions);
    const normals = copyBuffer(mesh.normals);
    const uvs = copyBuffer(mesh.uvs);
    const indices = copyBuffer(mesh.indices);
    mesh.destroy();
    post({ ...fields, positions, normals, uvs, indices, tessellate_ms: ms },
         [positions.buffer, normals.buffer, uvs.buffer, indices.buffer]);
  } finally {
    result.destroy();
  }
}

function tessellate({ id, resolution }) {
  postMesh(glue.tessellate(resolution), { type: "mesh", id, resolution });
}

function tile({ id, name, bytes }) {
  const proxy = glue.addTile(name, bytes);
  const node = proxy.toJs();
  proxy.destroy();
  post({ type: "tile", id, name, level: node[0], i: node[1], j: node[2] });
}

function drop({ id, names }) {
  const list = pyodide.toPy(names);
  try {
    glue.dropTiles(list);
  } finally {
    list.destroy();
  }
  post({ type: "dropped", id, names });
}

function region({ id, level, i, j, grid, names, skirtDepth }) {
  const list = pyodide.toPy(names);
  try {
    postMesh(glue.region(level, i, j, grid, list, skirtDepth), { type: "region", id, level, i, j });
  } finally {
    list.destroy();
  }
}

function ply({ id, resolution, colors, level, names, fresh, textures }) {
  const atLevel = Number.isInteger(level) && level >= 0;
  const images = textures || [];
  const result = atLevel
    ? glue.plyLevel(level, resolution, names, (fresh || []).map((t) => t.name),
                    (fresh || []).map((t) => t.bytes),
                    images.map((t) => [t.level, t.i, t.j, t.width, t.height]),
                    images.map((t) => t.rgb))
    : glue.ply(resolution, colors || undefined); // undefined -> None (null is JsNull)
  try {
    const [data, vertices, triangles, ms] = result;
    const bytes = copyBuffer(data);
    post({ type: "ply", id, resolution, level: atLevel ? level : -1, bytes, vertices, triangles,
           write_ms: ms }, [bytes.buffer]);
  } finally {
    result.destroy();
  }
}

const handlers = { init, tessellate, ply, tile, drop, region };

self.onmessage = (event) => {
  const request = event.data;
  // Requests run one at a time, in order: Python is single-threaded anyway.
  queue = queue.then(async () => {
    const handler = handlers[request.type];
    if (!handler) {
      post({ type: "error", id: request.id, stage: "request", message: `unknown request ${request.type}` });
      return;
    }
    if (request.type !== "init" && !glue) {
      post({ type: "error", id: request.id, stage: request.type, message: "the patch is not loaded" });
      return;
    }
    try {
      await handler(request);
    } catch (error) {
      post({ type: "error", id: request.id, stage: request.type, message: reason(error) });
    }
  });
};
