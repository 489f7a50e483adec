// Run a Python script against client_py inside Pyodide under node.
//
// Usage: node tests/pyodide_runner.mjs SCRIPT.py [INPUT.json]
//
// Loads Pyodide from the npm package in web/node_modules (no network: only the
// core that ships in the package, so no numpy and no pytest), writes
// client_py/*.py into Pyodide's file system, and runs SCRIPT with two globals:
// INPUT (the parsed INPUT.json, or None) and RESULT (None). After the script, the
// runner prints one JSON line on stdout:
//   {"result": RESULT, "python": sys.version, "load_seconds": s, "run_seconds": s}
// Everything the script prints goes to stderr, so stdout stays machine-readable.
// CLIENT_PY_DIR=/path/to/client_py runs another copy of the package (before/after timings).
// A Python exception prints its traceback on stderr and exits with status 1.
// Used by tests/test_pyodide.py and bench/bench_tessellate.py.

import { readdirSync, readFileSync } from "node:fs";
import { dirname, join, resolve } from "node:path";
import { fileURLToPath, pathToFileURL } from "node:url";

const root = resolve(dirname(fileURLToPath(import.meta.url)), "..");
const [script, inputPath] = process.argv.slice(2);
if (!script) {
  process.stderr.write("usage: node tests/pyodide_runner.mjs SCRIPT.py [INPUT.json]\n");
  process.exit(2);
}

const pyodidePath = join(root, "web", "node_modules", "pyodide", "pyodide.mjs");
const { loadPyodide } = await import(pathToFileURL(pyodidePath).href);

const loadStart = performance.now();
const pyodide = await loadPyodide({
  stdout: (line) => process.stderr.write(line + "\n"),
  stderr: (line) => process.stderr.write(line + "\n"),
});
const loadSeconds = (performance.now() - loadStart) / 1000;

// client_py as a package in the working directory (on sys.path).
const home = "/home/pyodide";
const clientDir = process.env.CLIENT_PY_DIR || join(root, "client_py");
pyodide.FS.mkdirTree(`${home}/client_py`);
for (const name of readdirSync(clientDir)) {
  if (name.endsWith(".py")) {
    pyodide.FS.writeFile(`${home}/client_py/${name}`, readFileSync(join(clientDir, name)));
  }
}

const input = inputPath ? readFileSync(inputPath, "utf8") : "null";
pyodide.globals.set("INPUT_JSON", input);
const source = readFileSync(script, "utf8");
const runStart = performance.now();
let output;
try {
  pyodide.runPython(
    "import json, os, sys\n" +
      `os.chdir(${JSON.stringify(home)})\n` +
      "sys.path.insert(0, os.getcwd())\n" +
      "INPUT = json.loads(INPUT_JSON)\n" +
      "RESULT = None\n",
  );
  pyodide.runPython(source, { filename: script });
  output = pyodide.runPython(
    "json.dumps({'result': RESULT, 'python': sys.version})",
  );
} catch (err) {
  process.stderr.write(String(err && err.message ? err.message : err) + "\n");
  process.exit(1);
}
const record = JSON.parse(output);
record.load_seconds = loadSeconds;
record.run_seconds = (performance.now() - runStart) / 1000;
process.stdout.write(JSON.stringify(record) + "\n");
