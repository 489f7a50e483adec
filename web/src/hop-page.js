// The 3DHOP page: client_py writes the PLY in the browser (mesh worker), 3DHOP shows it.
//
// The PLY reaches 3DHOP as a blob: URL with mType "ply" (3DHOP's own loader, js/ply.js).
// Loaded state: 3DHOP's presenter reports its scene ready (presenter._isSceneReady(), set
// when every mesh of the scene has been parsed and uploaded); the page then sets
// document.body.dataset.ready = "1" after the next frame, as the viewer page does.
//
// Level of detail (?level=L, the #hop-level choice; default "base"): the base patch alone on a
// 192 x 192 grid (with the error map's colours under ?colors=error), or the bundle at detail
// level L as the viewer's "Download PLY" makes it (page.js levelPly, on the worker's plan:
// client_py.bundle.plan_level): every detail tile of levels 0..L fetched, the whole patch
// tessellated with them on the level's grid, min(1025, 2 spans 2^L + 1)^2 vertices, with
// per-vertex colours from the texture tiles when the bundle has some. The
// loading panel says what is being fetched and made. Stats (window.tessera.stats) beyond
// page.js's: level (-1 base), resolution, ply_bytes, and at a level the ply_* of levelPly.
// window.tessera.plyUrl is the PLY 3DHOP was given.

import { ErrorMap } from "./error-map.js";
import { MeshWorkerClient } from "./mesh-worker-client.js";
import {
  $, atlasBaseChoice, levelOption, levelPly, loadManifest, loadPieces, startPage, workerInit,
} from "./page.js";

const RESOLUTION = 192; // 36,864 vertices: one 3DHOP chunk (its limit is 65,535 per chunk)
const FRAME_RESOLUTION = 64; // base grid the framing is computed from at a detail level
const { config, stats, showStage, showError } = startPage({
  manifest: "Reading the object's description…",
  runtime: "Starting the Python runtime (Pyodide)…",
  client_py: "Installing client_py…",
  patch: "Reading the NURBS patch…",
  ply: "Writing the PLY mesh…",
  hop: "Handing the mesh to 3DHOP…",
}, { ply_bytes: 0, level: -1, resolution: null });

// Dragging on the 3D view selects no text (a listener, not an inline attribute: the page's
// Content-Security-Policy runs no inline handlers).
$("3dhop").addEventListener("mousedown", (event) => event.preventDefault());

// 3DHOP's toolbar (init.js) calls this global.
window.actionsToolbar = (action) => {
  const presenter = window.presenter;
  if (!presenter) return;
  if (action === "home") presenter.resetTrackball();
  else if (action === "zoomin") presenter.zoomIn();
  else if (action === "zoomout") presenter.zoomOut();
  else if (action === "light" || action === "light_on") {
    presenter.enableLightTrackball(!presenter.isLightTrackballEnabled());
    window.lightSwitch();
  } else if (action === "full" || action === "full_on") window.fullscreenSwitch();
};

/** Column-major 4x4 rotation turning the mean normal towards 3DHOP's camera (+z) and the
 *  longest in-plane extent of the vertices horizontal (+x), as the three.js viewer frames it. */
function facingMatrix(positions, normals, tilt = (20 * Math.PI) / 180) {
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (v) => { const l = Math.hypot(...v) || 1; return v.map((x) => x / l); };
  let f = [0, 0, 0];
  for (let k = 0; k < normals.length; k += 3) f = [f[0] + normals[k], f[1] + normals[k + 1], f[2] + normals[k + 2]];
  f = Math.hypot(...f) > 1e-9 ? norm(f) : [0, 0, 1];
  // In-plane principal axis: 2x2 covariance of the vertices in a basis (a, b) orthogonal to f.
  const a = norm(cross(Math.abs(f[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0], f));
  const b = cross(f, a);
  const n = positions.length / 3;
  const c = [0, 0, 0];
  for (let k = 0; k < positions.length; k += 3) for (let i = 0; i < 3; i++) c[i] += positions[k + i] / n;
  let saa = 0, sab = 0, sbb = 0;
  for (let k = 0; k < positions.length; k += 3) {
    const d = [positions[k] - c[0], positions[k + 1] - c[1], positions[k + 2] - c[2]];
    const pa = dot(d, a), pb = dot(d, b);
    saa += pa * pa; sab += pa * pb; sbb += pb * pb;
  }
  const angle = 0.5 * Math.atan2(2 * sab, saa - sbb);
  const right = norm(a.map((x, i) => Math.cos(angle) * x + Math.sin(angle) * b[i]));
  const up0 = cross(f, right);
  // Then tilt by `tilt` about x: the camera looks from a little above, like the three.js viewer.
  const ct = Math.cos(tilt), st = Math.sin(tilt);
  const up = up0.map((x, i) => ct * x - st * f[i]);
  const back = up0.map((x, i) => st * x + ct * f[i]);
  // Rows of the rotation are right, up, back; column-major storage puts row r, column c at [4c + r].
  return [right[0], up[0], back[0], 0, right[1], up[1], back[1], 0, right[2], up[2], back[2], 0,
          0, 0, 0, 1];
}

function waitForScene(presenter, timeoutMs) {
  return new Promise((resolve, reject) => {
    const start = performance.now();
    const poll = () => {
      if (presenter._isSceneReady()) resolve();
      else if (performance.now() - start > timeoutMs) reject(new Error(`3DHOP did not load the mesh within ${timeoutMs / 1000} s`));
      else setTimeout(poll, 20);
    };
    poll();
  });
}

/** The level asked for by ?level= ("base", "-1" or absent: -1, the base), or an Error. */
function requestedLevel() {
  const raw = new URLSearchParams(location.search).get("level");
  if (raw === null || raw === "" || raw === "base" || raw === "-1") return -1;
  if (!/^\d+$/.test(raw)) {
    throw new Error(`?level=${raw} is not a level of detail: use base or a level number (0, 1, …)`);
  }
  return Number(raw);
}

/** This page's URL with the query parameter `name` set to `value` (deleted when null). */
function withParam(name, value) {
  const url = new URL(location.href);
  if (value === null) url.searchParams.delete(name); else url.searchParams.set(name, value);
  return url;
}

async function main() {
  if (typeof Presenter === "undefined") throw new Error("3DHOP's scripts did not load (check TESSERA_3DHOP_DIR / TESSERA_3DHOP_URL)");
  const level = requestedLevel();
  const useColors = new URLSearchParams(location.search).get("colors") === "error";
  if (useColors && level >= 0) {
    throw new Error(`error colours (?colors=error) show the base's distance to the scan: they ` +
                    `cannot be combined with a detail level (?level=${level})`);
  }
  stats.level = level;
  window.init3dhop();
  const presenter = new Presenter("draw-canvas");
  window.presenter = presenter;

  const worker = new MeshWorkerClient(config.worker_url, { onStage: (stage) => showStage(stage) });
  const readyPromise = worker.init(workerInit(config), config.pyodide_timeout_s);
  readyPromise.catch(() => {}); // awaited below; this only keeps an early failure "handled"
  const manifest = await loadManifest(config.manifest_url, stats);
  const ready = await readyPromise;
  stats.pyodide_load_ms = ready.pyodide_load_ms;
  stats.kernel = ready.kernel;
  stats.bytes_downloaded += ready.patch_bytes;

  // The level choice: base, and one entry per detail level of the bundle (the worker's plan).
  const select = $("hop-level");
  let levels = [];
  let levelsError = null;
  try {
    levels = (await worker.plan(manifest)).levels;
  } catch (error) {
    levelsError = error;
  }
  // a patch's detached pieces: in every PLY the worker writes from now on
  if (!levelsError) {
    try {
      await loadPieces(worker, manifest, { manifestUrl: config.manifest_url, stats });
    } catch (error) { // a missing or bad pieces.tsa: the patch's PLYs, the reason kept
      document.body.dataset.piecesError = error.message;
    }
  }
  const units = manifest.units || "unknown";
  for (const choice of levels) select.append(levelOption(choice, units));
  select.value = String(level);
  select.disabled = !levels.length;
  select.title = levelsError ? levelsError.message : levels.length
    ? "Level of detail shown: the base patch alone, or the base with every detail tile of " +
      "levels 0..L (their size, and the RMS distance to the scan at that level, are shown)" +
      (manifest.tiles.texture ? ", coloured from the object's texture tiles" : "")
    : "this bundle has no detail tiles: the base patch alone";
  select.addEventListener("change", () => {
    const url = withParam("level", select.value === "-1" ? null : select.value);
    url.searchParams.delete("colors");
    location.assign(url);
  });
  const choice = level >= 0 ? levels.find((c) => c.level === level) : null;
  if (level >= 0 && !choice) {
    if (levelsError) throw new Error(`cannot show level ${level}: ${levelsError.message}`);
    throw new Error(levels.length
      ? `this bundle has no detail level ${level} (its levels are 0–${levels.length - 1})`
      : `this bundle has no detail tiles: ?level=${level} cannot be shown (only the base)`);
  }

  const colorsBox = $("hop-colors");
  colorsBox.checked = useColors;
  if (level >= 0) {
    colorsBox.disabled = true;
    colorsBox.parentElement.title = "The error map is the base's distance to the scan: " +
      "choose the base level to see it";
  }
  colorsBox.addEventListener("change", () => {
    const url = withParam("colors", colorsBox.checked ? "error" : null);
    url.searchParams.delete("level");
    location.assign(url);
  });

  let colors = null;
  let ply;
  let frame; // the base mesh the view is framed on
  const atlas = ready.patch.kind === "atlas"; // manifest format_version 2
  if (atlas && useColors) throw new Error("an atlas bundle has no error map to colour the mesh with");
  if (atlas) {
    // one welded PLY of every patch at the level (the base: the atlas alone), as "Download PLY"
    showStage("ply");
    const refinement = await worker.atlasRefinement();
    frame = await worker.atlasMesh(refinement.groups.map(() => -1));
    const chosen = choice || atlasBaseChoice(refinement, levels);
    ply = await levelPly(worker, chosen, {
      manifestUrl: config.manifest_url, stats, onProgress: (text) => showStage("ply", text) });
    stats.tessellate_ms = ply.write_ms;
    stats.resolution = ply.resolution;
    stats.ply_level = level;
    colors = chosen.texture_nodes.length ? true : null; // RGB per vertex from its colour packs
  } else if (!choice) {
    const resolution = config.resolution || RESOLUTION;
    showStage("ply");
    frame = await worker.tessellate(resolution);
    stats.tessellate_ms = frame.tessellate_ms;
    if (useColors) {
      const errorMap = ErrorMap.fromManifest(manifest);
      if (!errorMap) throw new Error("this bundle has no error data to colour the mesh with");
      await errorMap.load(new URL(config.manifest_url, window.location.href));
      colors = errorMap.vertexColors(frame.uvs, ready.patch.domain);
    }
    ply = await worker.ply(resolution, colors);
    stats.resolution = resolution;
  } else {
    showStage("ply");
    frame = await worker.tessellate(FRAME_RESOLUTION);
    ply = await levelPly(worker, choice, {
      manifestUrl: config.manifest_url, stats, onProgress: (text) => showStage("ply", text) });
    stats.tessellate_ms = ply.write_ms;
    stats.resolution = ply.resolution;
    stats.ply_level = level;
    colors = choice.texture_nodes.length ? true : null;
  }
  stats.vertices = ply.vertices;
  stats.triangles = ply.triangles;
  stats.ply_bytes = ply.bytes.length;
  const url = URL.createObjectURL(new Blob([ply.bytes], { type: "application/octet-stream" }));
  window.tessera.plyUrl = url;

  showStage("hop", `Handing the mesh to 3DHOP (${ply.vertices.toLocaleString("en")} vertices)…`);
  presenter.setScene({
    meshes: { tessera: { url, mType: "ply", transform: { matrix: facingMatrix(frame.positions, frame.normals) } } },
    // A stone-like solid colour, or -2,-2,-2 meaning "the vertex colours" when the mesh has
    // them (client_py writes texture_u/v only with a texture, which 3DHOP would sample).
    modelInstances: { object: { mesh: "tessera", useSolidColor: true,
                                color: colors ? [-2.0, -2.0, -2.0] : [0.86, 0.82, 0.75],
                                specularColor: [0.08, 0.08, 0.08, 32.0] } },
    trackball: {
      type: SphereTrackball,
      trackOptions: { startDistance: 2.4, minMaxDist: [0.4, 6.0] },
    },
    space: { cameraFOV: 40.0 },
  });
  // 3DHOP parses the PLY on the main thread: allow for a million-vertex level
  await waitForScene(presenter, 20000 + ply.vertices / 20);
  presenter.repaint();
  await new Promise((resolve) => requestAnimationFrame(() => requestAnimationFrame(resolve)));
  stats.first_frame_ms = performance.now();
  $("loading").hidden = true;
  document.body.dataset.ready = "1";
}

main().catch((error) => {
  showError(error.message || String(error));
});
