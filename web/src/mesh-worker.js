// The mesh worker: Pyodide + client_py in a module Web Worker, so the page never blocks on Python.
//
// It only moves messages and buffers: it writes client_py's files into Pyodide's file system,
// imports client_py.session and, for each request, calls one method of its WorkerSession
// (the Python, linted and tested like the rest of client_py) and sends the result back.
//
// Protocol (every request carries an `id`; every reply echoes it):
//   page -> {type: "init", pyodideUrl, pyodideSnapshotUrl?, pyodideStdlibUrl?, pyodideLock?,
//            runtimeBytes?, clientPyUrl, patchUrl}
//   worker -> {type: "stage", stage: "runtime" | "client_py" | "patch", ...}   (progress)
//   worker -> {type: "progress", loaded, total}  bytes of the runtime fetched so far (body
//           bytes as decoded) of runtimeBytes' total, at most every 100 ms
//   worker -> {type: "ready", pyodide_load_ms, kernel, patch: {...}, resources}  (init done;
//           patch: WorkerSession.load_patch's facts; resources: resourceEntries())
//   page -> {type: "resources"} -> {type: "resources", resources}  (the worker's fetches so far)
//   page -> {type: "tessellate", resolution}  -> {type: "mesh", positions, normals, uvs, indices, ...}
//           (WorkerSession.tessellate_base)
//   page -> {type: "ply", resolution, colors?} -> {type: "ply", bytes, vertices, triangles}
//           (WorkerSession.base_ply: the base mesh, with the RGB per vertex `colors`)
//   page -> {type: "plan", manifest}  -> {type: "plan", levels, max_resolution, spans_per_tile}
//           (the manifest's JSON text, kept; WorkerSession.level_choices: per detail level its
//           detail_files, texture_nodes, their bytes, rms, grid and region grid,
//           client_py.bundle.plan_level)
//   page -> {type: "ply", level, fresh?: [{name, bytes}], textures?: [{level, i, j, width,
//            height, rgb}]}
//        -> {type: "ply", bytes, vertices, triangles, resolution, write_ms}  (level >= 0:
//           WorkerSession.level_ply, what `tessera tessellate BUNDLE --level L` writes: the
//           plan's tiles, held ones or `fresh` ones, decoded for this request only, and its
//           texture tiles as decoded RGB bytes, rows top to bottom)
//   An atlas bundle (manifest format_version 2: patchUrl names base.tsa) is loaded by
//   WorkerSession.load_atlas instead (ready.patch.kind === "atlas"); then, after "plan":
//   page -> {type: "atlasRefinement"} -> {type: "atlasRefinement", groups, base_error, levels,
//           resolutions}   (WorkerSession.atlas_refinement: per group its sphere, packs, errors)
//   page -> {type: "pack", name, bytes} -> {type: "pack", name, level, group, tiles}  (add_pack)
//   page -> {type: "dropPacks", names}  -> {type: "droppedPacks", names}          (drop_packs)
//   page -> {type: "atlasMesh", levels} -> {type: "atlasMesh", positions, normals, uvs,
//           indices, colors, tessellate_ms}  (atlas_mesh: one welded mesh, group g at
//           levels[g]; colors RGB per vertex from the colour packs held, or null)
//   page -> {type: "atlasParts", levels, groups: [group, ...]}
//        -> {type: "atlasParts", meshes: [{group, level, positions, normals, uvs, indices,
//           colors, tessellate_ms}, ...]}  (atlas_part_meshes(groups, levels), in order:
//           each group's triangles of atlasMesh(levels), bit for bit, so groups made at one
//           level vector meet without a crack; what the viewer draws; colors as atlasMesh's,
//           by the same rule; tessellate_ms: the call's time shared among them)
//   page -> {type: "atlasColour"} -> {type: "atlasColour", colour}  (atlas_colour_refinement)
//   page -> {type: "colourPack", name, width, height, rgb} -> {type: "colourPack", name, level,
//           first, count}  (add_colour_pack: a decoded texture/C/G.webp)
//   page -> {type: "dropColourPacks", names} -> {type: "droppedColourPacks", names}
//   page -> {type: "errorMap", bytes, palette} -> {type: "errorMap", patches, rows}
//           (set_error_map: the atlas's error_raster.bin and the RGB of its 256 codes colour
//           the meshes made from now on; bytes null: the colour packs again)
//   page -> {type: "ply", level >= -1, fresh?} -> as above (level_ply: the packs of 0..L);
//           meanwhile {type: "plyProgress", id, fraction} (the share of the atlas tessellated)
//   page -> {type: "pieces", url} -> {type: "pieces", positions, normals, uvs, indices, bytes,
//           resources}  (after "plan": the worker fetches the manifest's pieces.tsa at `url`,
//           WorkerSession.load_pieces keeps its mesh for the PLYs and it is sent to be drawn)
//   page -> {type: "tile", name, bytes}  -> {type: "tile", name, level, i, j}   (add_tile, kept)
//   page -> {type: "fetchTiles", tiles: [{name, url}, ...]}
//        -> {type: "fetchedTiles", tiles: [{name, bytes, level, i, j}, ...], resources}
//           (the worker fetches the tiles itself, then add_tile each, kept; resources: as in
//           "resources", the page's tally of what the visit transferred)
//   page -> {type: "drop", names}        -> {type: "dropped", names}            (drop_tiles)
//   page -> {type: "region", level, i, j, grid, names, skirtDepth}
//        -> {type: "region", positions, normals, uvs, indices, tessellate_ms}  (region_mesh:
//           node (level, i, j) with the named tiles, skirts on its inner borders, scan frame)
//   page -> {type: "regions", regions: [{level, i, j, grid, names, skirtDepth}, ...]}
//        -> {type: "regions", meshes: [{level, i, j, positions, normals, uvs, indices,
//           tessellate_ms}, ...]}  (region_mesh for each, in order, in one reply)
//   worker -> {type: "error", stage, message}   for any failure, with the reason
// Requests run one at a time, in the order they came, except that a base "tessellate" waits
// while other requests are queued (or arrive before it starts): the regions of a zoom are not
// held up by the base's re-tessellation that the same zoom asked for (nothing depends on it).
// Mesh arrays are copied once out of the WebAssembly heap (PyBuffer views die with the
// Python object) and then *transferred*, not copied again, to the page. Times (*_ms) are
// measured here around the Python call.

import { fetchBytes } from "./fetch-bytes.js";

const PY_ROOT = "/home/pyodide/tessera";
// An empty zip archive (its end-of-central-directory record alone): what Pyodide mounts as
// the standard library when a snapshot is restored (the snapshot imported all client_py
// needs and took the archive off sys.path: web/tools/make-pyodide-snapshot.mjs).
const EMPTY_ZIP = "data:application/zip;base64,UEsFBgAAAAAAAAAAAAAAAAAAAAAAAA==";
const PROGRESS_EVERY_MS = 100;

let pyodide = null;
let atlasLoaded = false; // the session holds an atlas (base.tsa), not a patch
let session = null; // client_py.session.WorkerSession, once the patch is loaded
const pending = []; // requests not yet started, in arrival order
let pumping = false;

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

/** A copy of a Python buffer (array.array, bytes) as a standalone typed array. */
function copyBuffer(proxy) {
  const view = proxy.getBuffer();
  try {
    return view.data.slice();
  } finally {
    view.release();
    proxy.destroy();
  }
}

/** `value` (an array, a Map) as a Python object for one call: `use(py)`, then freed. */
function withPy(value, use) {
  const py = pyodide.toPy(value);
  try {
    return use(py);
  } finally {
    if (py && typeof py.destroy === "function") py.destroy();
  }
}

/** A Python dict or list (a proxy) as plain JavaScript objects; the proxy is freed. */
function toPlain(proxy) {
  try {
    return proxy.toJs({ dict_converter: Object.fromEntries });
  } finally {
    proxy.destroy();
  }
}

/** This worker's fetches as the Resource Timing API saw them: [{name, transferSize,
 *  encodedBodySize, decodedBodySize}] (transferSize 0: from the browser's cache). The page
 *  cannot see them: each global has its own performance timeline. */
function resourceEntries() {
  return performance.getEntriesByType("resource").map((entry) => ({
    name: entry.name, transferSize: entry.transferSize, encodedBodySize: entry.encodedBodySize,
    decodedBodySize: entry.decodedBodySize }));
}

/** Count the body bytes of every fetch this worker makes (Pyodide's own included) against
 *  `total`, posting {type: "progress"} as they arrive. The response keeps its status and
 *  headers (streaming WebAssembly compilation needs its Content-Type). */
function countFetchedBytes(total) {
  const realFetch = self.fetch.bind(self);
  let loaded = 0;
  let lastPost = 0;
  const report = (force) => {
    const now = performance.now();
    if (force || now - lastPost >= PROGRESS_EVERY_MS) {
      lastPost = now;
      post({ type: "progress", loaded, total });
    }
  };
  self.fetch = async (input, options) => {
    const response = await realFetch(input, options);
    if (!response.body || String(response.url).startsWith("data:")) return response;
    const counter = new TransformStream({
      transform(chunk, controller) {
        loaded += chunk.byteLength;
        report(false);
        controller.enqueue(chunk);
      },
      flush() { report(true); },
    });
    return new Response(response.body.pipeThrough(counter), {
      status: response.status, statusText: response.statusText, headers: response.headers });
  };
}

async function init({ pyodideUrl, pyodideSnapshotUrl, pyodideStdlibUrl, pyodideLock, runtimeBytes,
                      clientPyUrl, patchUrl }) {
  let stage = "runtime";
  try {
    post({ type: "stage", stage });
    const t0 = performance.now();
    if (runtimeBytes) {
      const wanted = ["pyodide.asm.wasm", "sources.json",
                      pyodideSnapshotUrl ? "snapshot" : "python_stdlib.zip"];
      countFetchedBytes(wanted.reduce((sum, name) => sum + (runtimeBytes[name] || 0), 0));
    }
    const { loadPyodide } = await import(`${pyodideUrl}pyodide.mjs`);
    const tImported = performance.now();
    const options = { indexURL: pyodideUrl };
    // the lock file's info alone: the worker loads no packages (pyodide-lock.json is 119 KB)
    if (pyodideLock) options.lockFileContents = pyodideLock;
    if (pyodideSnapshotUrl) {
      // Interpreter memory with client_py imported, made by the server (fitter/server/snapshot.py).
      options._loadSnapshot = fetchBytes(pyodideSnapshotUrl, "the Pyodide snapshot");
      options.stdLibURL = EMPTY_ZIP;
    } else if (pyodideStdlibUrl) {
      options.stdLibURL = pyodideStdlibUrl; // trimmed to what client_py can import
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
    const sys = pyodide.pyimport("sys");
    if (!sys.path.has(PY_ROOT)) sys.path.insert(0, PY_ROOT); // a snapshot has it already
    sys.destroy();
    const sessionModule = pyodide.pyimport("client_py.session");
    const created = sessionModule.WorkerSession();
    sessionModule.destroy();
    stages.client_py_ms = performance.now() - t0 - pyodideLoadMs;
    const kernel = created.kernel;

    stage = "patch";
    post({ type: "stage", stage });
    const tPatch = performance.now();
    const bytes = await fetchBytes(patchUrl, "the base patch");
    const source = patchUrl.split("/").pop();
    atlasLoaded = source.endsWith(".tsa");
    const patch = toPlain(atlasLoaded ? created.load_atlas(bytes, source)
                                      : created.load_patch(bytes, source));
    session = created;
    stages.patch_ms = performance.now() - tPatch;
    post({ type: "ready", pyodide_load_ms: pyodideLoadMs, kernel, patch, patch_bytes: bytes.length,
           client_py_version: sources.version, stages, resources: resourceEntries() });
  } catch (error) {
    post({ type: "error", stage, message: reason(error) });
  }
}

/** A Mesh of the session as standalone typed arrays (the proxy is freed), with `fields`. */
function meshArrays(mesh, ms, fields) {
  try {
    const positions = copyBuffer(mesh.positions);
    const normals = copyBuffer(mesh.normals);
    const uvs = copyBuffer(mesh.uvs);
    const indices = copyBuffer(mesh.indices);
    // RGB per vertex (an atlas coloured from its colour packs), else none
    const colors = mesh.colors === null || mesh.colors === undefined ? null : copyBuffer(mesh.colors);
    return { ...fields, positions, normals, uvs, indices, colors, tessellate_ms: ms };
  } finally {
    mesh.destroy();
  }
}

const buffersOf = (m) => [m.positions.buffer, m.normals.buffer, m.uvs.buffer, m.indices.buffer,
                          ...(m.colors ? [m.colors.buffer] : [])];

/** Post a Mesh of the session as transferable typed arrays, with `fields` added. */
function postMesh(mesh, ms, fields) {
  const message = meshArrays(mesh, ms, fields);
  post(message, buffersOf(message));
}

/** Post a PlyFile of the session (its bytes transferred). */
function postPly(ply, ms, id) {
  try {
    const bytes = copyBuffer(ply.data);
    post({ type: "ply", id, level: ply.level, resolution: ply.resolution, bytes,
           vertices: ply.vertex_count, triangles: ply.triangle_count, write_ms: ms },
         [bytes.buffer]);
  } finally {
    ply.destroy();
  }
}

function tessellate({ id, resolution }) {
  const t0 = performance.now();
  const mesh = session.tessellate_base(resolution);
  postMesh(mesh, performance.now() - t0, { type: "mesh", id, resolution });
}

function plan({ id, manifest }) {
  session.read_manifest(manifest);
  post({ type: "plan", id, ...toPlain(session.level_choices()) });
}

function ply({ id, resolution, colors, level, fresh, textures }) {
  const t0 = performance.now();
  if (Number.isInteger(level) && (level >= 0 || atlasLoaded)) {
    const tiles = new Map((fresh || []).map((tile) => [tile.name, tile.bytes]));
    // the share of the tessellation done, posted as it goes (an atlas: seconds of Python)
    const progress = (fraction) => post({ type: "plyProgress", id, fraction });
    const result = withPy(tiles, (pyTiles) => withPy(textures || [], (pyTextures) =>
      session.level_ply(level, pyTiles, pyTextures, progress)));
    postPly(result, performance.now() - t0, id);
  } else {
    postPly(session.base_ply(resolution, colors || undefined), // undefined -> None
            performance.now() - t0, id);
  }
}

async function pieces({ id, url }) {
  const bytes = await fetchBytes(url, "the detached pieces");
  const t0 = performance.now();
  const mesh = session.load_pieces(bytes);
  postMesh(mesh, performance.now() - t0, { type: "pieces", id, bytes: bytes.length,
                                          resources: resourceEntries() });
}

function tile({ id, name, bytes }) {
  const [level, i, j] = toPlain(session.add_tile(name, bytes));
  post({ type: "tile", id, name, level, i, j });
}

/** Fetch detail tiles here, off the page's thread (a draw there does not hold them up), and
 *  keep each decoded (add_tile); the region requests the page sends behind this one find
 *  them held. Replies with their sizes and this worker's Resource Timing entries. */
async function fetchTiles({ id, tiles }) {
  const fetched = await Promise.all(tiles.map(async ({ name, url }) =>
    ({ name, bytes: await fetchBytes(url, name) })));
  const added = fetched.map(({ name, bytes }) => {
    const [level, i, j] = toPlain(session.add_tile(name, bytes));
    return { name, bytes: bytes.length, level, i, j };
  });
  post({ type: "fetchedTiles", id, tiles: added, resources: resourceEntries() });
}

function drop({ id, names }) {
  withPy(names, (list) => session.drop_tiles(list));
  post({ type: "dropped", id, names });
}

function region({ id, level, i, j, grid, names, skirtDepth }) {
  const t0 = performance.now();
  const mesh = withPy(names, (list) => session.region_mesh(level, i, j, grid, list, skirtDepth));
  postMesh(mesh, performance.now() - t0, { type: "region", id, level, i, j });
}

function regions({ id, regions: wanted }) {
  const meshes = wanted.map(({ level, i, j, grid, names, skirtDepth }) => {
    const t0 = performance.now();
    const mesh = withPy(names, (list) => session.region_mesh(level, i, j, grid, list, skirtDepth));
    return meshArrays(mesh, performance.now() - t0, { level, i, j });
  });
  post({ type: "regions", id, meshes }, meshes.flatMap(buffersOf));
}

function atlasRefinement({ id }) {
  post({ type: "atlasRefinement", id, ...toPlain(session.atlas_refinement()) });
}

function pack({ id, name, bytes }) {
  post({ type: "pack", id, name, ...toPlain(session.add_pack(name, bytes)) });
}

function dropPacks({ id, names }) {
  withPy(names, (list) => session.drop_packs(list));
  post({ type: "droppedPacks", id, names });
}

function atlasParts({ id, levels, groups }) {
  const t0 = performance.now();
  const made = withPy(levels, (levelList) => withPy(groups, (groupList) =>
    session.atlas_part_meshes(groupList, levelList)));
  const ms = (performance.now() - t0) / Math.max(groups.length, 1); // one call: its time shared
  let meshes;
  try {
    meshes = groups.map((group, k) => meshArrays(made.get(k), ms, { group, level: levels[group] }));
  } finally {
    made.destroy();
  }
  post({ type: "atlasParts", id, meshes }, meshes.flatMap(buffersOf));
}

function atlasMesh({ id, levels }) {
  const t0 = performance.now();
  const mesh = withPy(levels, (list) => session.atlas_mesh(list));
  postMesh(mesh, performance.now() - t0, { type: "atlasMesh", id, levels });
}

function atlasColour({ id }) {
  const colour = session.atlas_colour_refinement(); // None (no colour) arrives as undefined
  post({ type: "atlasColour", id, colour: colour ? toPlain(colour) : null });
}

function colourPack({ id, name, width, height, rgb }) {
  post({ type: "colourPack", id, name, ...toPlain(session.add_colour_pack(name, width, height, rgb)) });
}

function dropColourPacks({ id, names }) {
  withPy(names, (list) => session.drop_colour_packs(list));
  post({ type: "droppedColourPacks", id, names });
}

function errorMap({ id, bytes, palette }) {
  // undefined, not null, arrives in Python as None (null is a JsNull)
  post({ type: "errorMap", id,
         ...toPlain(session.set_error_map(bytes ?? undefined, palette ?? undefined)) });
}

function resources({ id }) {
  post({ type: "resources", id, resources: resourceEntries() });
}

const handlers = { init, tessellate, plan, ply, pieces, tile, fetchTiles, drop, region, regions,
                   resources };

async function run(request) {
  const handler = handlers[request.type];
  if (!handler) {
    post({ type: "error", id: request.id, stage: "request", message: `unknown request ${request.type}` });
    return;
  }
  if (request.type !== "init" && request.type !== "resources" && !session) {
    post({ type: "error", id: request.id, stage: request.type, message: "the patch is not loaded" });
    return;
  }
  try {
    await handler(request);
  } catch (error) {
    post({ type: "error", id: request.id, stage: request.type, message: reason(error) });
  }
}

const yieldChannel = new MessageChannel();

/** Resolves after the messages that reached the worker so far have been taken in (a task
 *  through a MessageChannel: setTimeout(0) would be clamped to 4 ms when nested). */
function takeInMessages() {
  return new Promise((resolve) => {
    yieldChannel.port1.onmessage = () => resolve();
    yieldChannel.port2.postMessage(null);
  });
}

/** Run the pending requests one at a time (Python is single-threaded anyway): the oldest
 *  that is not a base "tessellate", else the oldest. Before starting a base, the worker takes
 *  in the messages that came meanwhile, so a region batch sent since goes first. */
async function pump() {
  if (pumping) return;
  pumping = true;
  try {
    while (pending.length) {
      if (pending.every((request) => request.type === "tessellate")) await takeInMessages();
      const at = Math.max(pending.findIndex((request) => request.type !== "tessellate"), 0);
      await run(pending.splice(at, 1)[0]);
    }
  } finally {
    pumping = false;
  }
}

self.onmessage = (event) => {
  pending.push(event.data);
  pump();
};

Object.assign(handlers, { atlasRefinement, pack, dropPacks, atlasMesh, atlasParts, atlasColour,
                          colourPack, dropColourPacks, errorMap }); // an atlas bundle's
