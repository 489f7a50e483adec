// The mesh worker: Pyodide + client_py in a module Web Worker, so the page never blocks on Python.
//
// Protocol (every request carries an `id`; every reply echoes it):
//   page -> {type: "init", pyodideUrl, pyodideSnapshotUrl?, clientPyUrl, patchUrl}
//   worker -> {type: "stage", stage: "runtime" | "client_py" | "patch", ...}   (progress)
//   worker -> {type: "ready", pyodide_load_ms, kernel, patch: {...}}           (init done)
//   page -> {type: "tessellate", resolution}  -> {type: "mesh", positions, normals, uvs, indices, ...}
//   page -> {type: "ply", resolution, colors?} -> {type: "ply", bytes}          (client_py.write_ply)
//   worker -> {type: "error", stage, message}   for any failure, with the reason
// Mesh arrays are copied once out of the WebAssembly heap (PyBuffer views die with the
// Python object) and then *transferred*, not copied again, to the page.

const PY_ROOT = "/home/pyodide/tessera";

// Python side of the worker: thin wrappers over client_py, holding the loaded surface.
const PY_GLUE = `
import sys, time
if ${JSON.stringify(PY_ROOT)} not in sys.path:
    sys.path.insert(0, ${JSON.stringify(PY_ROOT)})
from array import array
from dataclasses import replace
from client_py import read_patch, tessellate_grid, write_ply
from client_py import _kernel

_surface = None
_source = None
_last = (None, None)  # (resolution, mesh): "Download PLY" reuses the mesh on screen

def tessera_load(js_bytes, source):
    global _surface, _source, _last
    surface = read_patch(js_bytes.to_bytes())
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
    return data, mesh.vertex_count, (time.perf_counter() - t0) * 1000.0
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

async function fetchBytes(url, what) {
  let response;
  try {
    response = await fetch(url);
  } catch (error) {
    throw new Error(`cannot fetch ${what} (${url}): ${error.message}`);
  }
  if (!response.ok) throw new Error(`cannot fetch ${what} (${url}): HTTP ${response.status}`);
  return new Uint8Array(await response.arrayBuffer());
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

function tessellate({ id, resolution }) {
  const result = glue.tessellate(resolution);
  try {
    const [mesh, ms] = result;
    const positions = copyBuffer(mesh.positions);
    const normals = copyBuffer(mesh.normals);
    const uvs = copyBuffer(mesh.uvs);
    const indices = copyBuffer(mesh.indices);
    mesh.destroy();
    post({ type: "mesh", id, resolution, positions, normals, uvs, indices, tessellate_ms: ms },
         [positions.buffer, normals.buffer, uvs.buffer, indices.buffer]);
  } finally {
    result.destroy();
  }
}

function ply({ id, resolution, colors }) {
  const result = glue.ply(resolution, colors || undefined); // undefined -> None (null is JsNull)
  try {
    const [data, vertices, ms] = result;
    const bytes = copyBuffer(data);
    post({ type: "ply", id, resolution, bytes, vertices, write_ms: ms }, [bytes.buffer]);
  } finally {
    result.destroy();
  }
}

const handlers = { init, tessellate, ply };

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
