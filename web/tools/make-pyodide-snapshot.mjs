// Make a Pyodide memory snapshot with client_py.session (the mesh worker's Python) already
// imported (run by the server, in node).
//
//   node make-pyodide-snapshot.mjs PYODIDE_DIR SOURCES_JSON OUT_FILE
//
// A snapshot restores the Python interpreter's memory instead of initialising it: the
// browser's loadPyodide({_loadSnapshot}) then takes about a second instead of several.
// SOURCES_JSON is the server's /client_py/sources.json document. The snapshot is only valid
// for this Pyodide build and these client_py sources; the server keys its file name on both.
// _makeSnapshot/_loadSnapshot are Pyodide's experimental snapshot API (pyodide.d.ts).

import { readFileSync, writeFileSync } from "node:fs";
import { pathToFileURL } from "node:url";

const PY_ROOT = "/home/pyodide/tessera"; // the worker's path for client_py (mesh-worker.js)

const [pyodideDir, sourcesPath, outPath] = process.argv.slice(2);
if (!outPath) {
  console.error("usage: node make-pyodide-snapshot.mjs PYODIDE_DIR SOURCES_JSON OUT_FILE");
  process.exit(2);
}
const indexURL = pyodideDir.endsWith("/") ? pyodideDir : `${pyodideDir}/`;
const { loadPyodide } = await import(pathToFileURL(`${indexURL}pyodide.mjs`).href);
const pyodide = await loadPyodide({ indexURL, _makeSnapshot: true });
const sources = JSON.parse(readFileSync(sourcesPath, "utf8"));
for (const [name, text] of Object.entries(sources.files)) {
  const path = `${PY_ROOT}/${sources.package}/${name}`;
  pyodide.FS.mkdirTree(path.slice(0, path.lastIndexOf("/")));
  pyodide.FS.writeFile(path, text);
}
// client_py.session imports the rest of client_py: the worker's first pyimport finds it all
// in sys.modules (mesh-worker.js adds PY_ROOT to sys.path only when it is not there).
const sys = pyodide.pyimport("sys");
sys.path.insert(0, PY_ROOT);
sys.destroy();
pyodide.pyimport("client_py.session").destroy();
// The worker restoring this snapshot does not fetch python_stdlib.zip (mesh-worker.js hands
// Pyodide an empty archive): every module client_py needs is imported above, and an import
// of anything else fails at once with ModuleNotFoundError instead of reading a missing zip.
pyodide.runPython(`
import sys
for _entry in [p for p in sys.path if p.endswith(".zip")]:
    sys.path.remove(_entry)
    sys.path_importer_cache.pop(_entry, None)
del _entry
`);
const snapshot = pyodide.makeMemorySnapshot();
writeFileSync(outPath, snapshot);
console.log(`${outPath}: ${snapshot.length} bytes`);
