// The viewer page: wires the mesh worker, the three.js Viewer and the page's controls.
//
// Testing contract: document.body.dataset.ready === "1" once the first mesh is drawn;
// document.body.dataset.error holds the message on failure; window.tessera.stats =
// {vertices, triangles, tessellate_ms, pyodide_load_ms, first_frame_ms, bytes_downloaded,
//  kernel, resolution, tiles_loaded, tile_bytes, tile_tessellate_ms, regions, ...}
// (vertices/triangles: the base mesh; tile stats: web/src/tile-layer.js). Detail tiles load on
// zoom (web/src/tile-tree.js); window.tessera.zoomTo(u, v, distance) frames the surface point
// at normalised (u, v) from `distance` scan units along its normal and resolves once the
// tiles for that view are on screen; window.tessera.tilesIdle() resolves when no tile update
// is due; window.tessera.view() gives the camera's projection and view matrices (column-major)
// and window.tessera.regionMeshes() the regions on screen ({level, i, j, grid, positions, uvs}
// of their grid vertices, skirts left out), for tests. A tile that fails to load sets document.body.dataset.tileError (the base stays).
// "Download PLY" writes the level chosen next to it (#ply-level): "base", the mesh on screen
// (with the error map's colours when it is shown), or detail level L: every detail tile of
// levels 0..L is fetched (those the worker already holds are not) and the worker tessellates
// the whole patch with them on an R x R grid, R = min(1025, 2 spans_per_tile 2^L + 1) (two
// vertices per knot span of the level's tiles), as `tessera tessellate OUTDIR --level L`;
// a bundle with texture tiles gives the vertices colours sampled from them (decoded here,
// sampled by client_py in the worker; page.js levelPly and textureNodes).
// Its stats: ply_level (-1 base), ply_bytes (the file's size), ply_vertices, ply_resolution,
// ply_ms (Python), ply_total_ms (fetch + tessellate + write), ply_tiles_fetched,
// ply_fetch_bytes (detail tiles), ply_textures, ply_texture_bytes (texture tiles fetched);
// document.body.dataset.plyBusy is "1" while a PLY is being made, and
// #ply-status (under the buttons) says what is being done, then the file written. "Open in
// 3DHOP" follows the level chosen (its ?level=L).
// All URLs come from the server's JSON config block.

import { ErrorMap } from "./error-map.js";
import { MeshWorkerClient } from "./mesh-worker-client.js";
import {
  $, formatBytes, formatLength, levelOption, levelPly, loadManifest, PLY_MAX_RES, plyLevels,
  startPage,
} from "./page.js";

const COARSE = 24; // first mesh: ~1k vertices, drawn within milliseconds of the patch
const MIN_RES = 48;
const MAX_RES = 384;

const { config, stats, showStage, showError } = startPage({
  manifest: "Reading the object's description…",
  runtime: "Starting the Python runtime (Pyodide)…",
  client_py: "Installing client_py…",
  patch: "Reading the NURBS patch…",
  tessellation: "Tessellating…",
  ply: "Making the PLY…",
}, { resolution: null, meshes: 0, tiles_loaded: 0, tile_bytes: 0, tile_tessellate_ms: 0, regions: 0,
     ply_level: null, ply_bytes: 0 });

function setFact(id, text) {
  const el = $(id);
  if (el) el.textContent = text;
}

/** Grid size that puts a vertex every ~3 device pixels across the object on screen. */
function viewResolution(viewer) {
  const pixels = viewer.projectedDiameter() / 3;
  return Math.min(MAX_RES, Math.max(MIN_RES, Math.round(pixels / 16) * 16));
}

/** Offer `bytes` as a download named `name`. */
function saveFile(bytes, name) {
  const url = URL.createObjectURL(new Blob([bytes], { type: "application/octet-stream" }));
  const link = document.createElement("a");
  link.href = url;
  link.download = name;
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

/** Progress and outcome of a PLY export, in the panel's status line under its buttons (the
 *  loading panel's grey text would sit on the object). */
function showPlyStatus(text) {
  const line = $("ply-status");
  line.textContent = text;
  line.hidden = !text;
}

function describe(manifest, ready) {
  const units = manifest.units || ready.patch.units || "unknown";
  const s = manifest.stats || {};
  setFact("fact-units", units);
  setFact("fact-bundle", formatBytes(stats.bytes_downloaded));
  setFact("fact-patch", formatBytes(ready.patch_bytes));
  setFact("fact-grid", `${ready.patch.shape.join(" × ")} control points, degree ${ready.patch.degree.join(", ")}` +
    (ready.patch.rational ? ", rational" : ""));
  setFact("fact-rms", formatLength(s.rms, units));
  setFact("fact-max", formatLength(s.max, units));
  if (manifest.provenance && manifest.provenance.points) {
    setFact("fact-source", `${manifest.provenance.points.toLocaleString("en")} scan points` +
      (manifest.provenance.bytes ? `, ${formatBytes(manifest.provenance.bytes)}` : ""));
  }
}

function showTileFacts() {
  if (stats.tile_updates === undefined) return;
  setFact("fact-detail", stats.regions
    ? `${stats.regions} regions, ${stats.tiles_loaded} tiles (${formatBytes(stats.tile_bytes)} fetched), ` +
      `${stats.tile_tessellate_ms.toFixed(0)} ms`
    : `base only (${stats.tile_bytes ? formatBytes(stats.tile_bytes) + " of tiles fetched" : "zoom in for detail"})`);
}

function showMeshFacts() {
  setFact("fact-mesh", `${stats.vertices.toLocaleString("en")} vertices, ` +
    `${stats.triangles.toLocaleString("en")} triangles`);
  setFact("fact-time", `${stats.tessellate_ms.toFixed(0)} ms in Python (${stats.kernel} kernel)`);
}

async function main() {
  // Start the worker (Pyodide: seconds) before three.js is even fetched: they load in parallel.
  const worker = new MeshWorkerClient(config.worker_url, { onStage: showStage });
  const readyPromise = worker.init({
    pyodideUrl: config.pyodide_url, pyodideSnapshotUrl: config.pyodide_snapshot_url,
    clientPyUrl: config.client_py_url, patchUrl: config.patch_url,
  }, config.pyodide_timeout_s);
  readyPromise.catch(() => {}); // awaited below; this only keeps an early failure "handled"
  const manifestPromise = loadManifest(config.manifest_url, stats);
  manifestPromise.catch(() => {});
  const tileModule = import("./tile-layer.js");
  tileModule.catch(() => {});
  const { Viewer } = await import("./viewer.js");
  const viewer = new Viewer($("view"));
  const panel = document.querySelector(".panel");
  // Keep the object clear of the information panel: beside it on wide screens, above it on
  // narrow ones (style.css moves the panel to the bottom below 700 px).
  const insets = () => {
    const box = panel.getBoundingClientRect();
    if (window.innerWidth > 900) return { left: box.right };
    if (window.innerWidth <= 700) return { bottom: window.innerHeight - box.top };
    return {};
  };
  viewer.setInsets(insets());
  window.addEventListener("resize", () => viewer.setInsets(insets()));
  let domain = null;
  let errorMap = null;
  let current = 0;
  let currentUvs = null;
  let pending = null;
  let tiles = null; // TileLayer once the manifest and the first mesh are in
  let resolveTiles;
  const tilesReady = new Promise((resolve) => { resolveTiles = resolve; });
  window.tessera.tilesIdle = async () => {
    await tilesReady;
    if (tiles) await tiles.idle();
    return { ...stats };
  };
  window.tessera.view = () => ({
    projection: Array.from(viewer.camera.projectionMatrix.elements),
    view: Array.from(viewer.camera.matrixWorldInverse.elements),
  });
  window.tessera.regionMeshes = () => [...(tiles ? tiles.regions : new Map())].map(([id, mesh]) => {
    const [level, i, j] = id.split("/").map(Number);
    const grid = tiles.regionGrid;
    const st = mesh.geometry.getAttribute("uv").array;
    const uvs = [];
    for (let k = 0; k < grid * grid; k++) uvs.push(st[2 * k + 1], st[2 * k]);
    return { level, i, j, grid, uvs,
             positions: Array.from(mesh.geometry.getAttribute("position").array.subarray(0, 3 * grid * grid)) };
  });
  window.tessera.zoomTo = async (u, v, distance) => {
    await tilesReady;
    viewer.lookAtSurface(u, v, distance, currentUvs, domain);
    if (tiles) {
      await tiles.update();
      await tiles.idle();
    }
    return { ...stats };
  };

  async function showResolution(resolution) {
    const t0 = performance.now();
    const mesh = await worker.tessellate(resolution);
    viewer.setMesh(mesh, domain);
    current = resolution;
    currentUvs = mesh.uvs; // same vertex order as the worker's PLY of this grid
    stats.resolution = resolution;
    stats.vertices = mesh.positions.length / 3;
    stats.triangles = mesh.indices.length / 3;
    stats.tessellate_ms = mesh.tessellate_ms;
    stats.round_trip_ms = performance.now() - t0;
    stats.meshes += 1;
    showMeshFacts();
    if (tiles) {
      tiles.setBase(mesh, domain);
      tiles.schedule(0);
    }
    return { ...stats };
  }
  window.tessera.tessellate = (resolution) => showResolution(resolution);

  // Zooming in asks for a finer grid, zooming out for a coarser one (after the gesture ends).
  viewer.controls.addEventListener("change", () => tiles && tiles.schedule());
  viewer.controls.addEventListener("end", () => {
    if (config.resolution || !domain) return;
    const wanted = viewResolution(viewer);
    if (wanted === current || Math.abs(Math.log(wanted / current)) < Math.log(1.4)) return;
    clearTimeout(pending);
    pending = setTimeout(() => showResolution(wanted).catch((e) => showError(e.message)), 150);
  });

  const ready = await readyPromise;
  const manifest = await manifestPromise;
  stats.pyodide_load_ms = ready.pyodide_load_ms;
  stats.worker_stages = ready.stages;
  stats.kernel = ready.kernel;
  stats.bytes_downloaded += ready.patch_bytes;
  domain = ready.patch.domain;
  describe(manifest, ready);

  showStage("tessellation");
  const target = config.resolution || viewResolution(viewer);
  await showResolution(Math.min(COARSE, target));
  await new Promise((resolve) => requestAnimationFrame(resolve));
  stats.first_frame_ms = performance.now();
  stats.coarse_resolution = current;
  document.body.dataset.ready = "1";
  $("loading").hidden = true;

  const { TileLayer } = await tileModule;
  try {
    tiles = new TileLayer({
      viewer, worker, manifest, manifestUrl: config.manifest_url, stats,
      onError: (message) => {
        console.error(message);
        document.body.dataset.tileError = message;
        setFact("fact-detail", message);
      },
      onChange: showTileFacts,
    });
  } catch (error) { // a malformed tile tree: the base alone, said so
    document.body.dataset.tileError = error.message;
    setFact("fact-detail", error.message);
  }
  if (tiles && tiles.enabled) {
    showTileFacts();
    tiles.setBase({ positions: viewer.mesh.geometry.getAttribute("position").array, uvs: currentUvs }, domain);
    tiles.schedule(0);
  } else if (tiles) {
    setFact("fact-detail", "none in this bundle");
  }
  resolveTiles();

  if (manifest.error_grid) {
    try {
      errorMap = new ErrorMap(manifest.error_grid, manifest.units || "");
      $("legend-bar").style.background = errorMap.cssGradient();
      $("legend-max").textContent = formatLength(errorMap.max, manifest.units || "");
      $("toggle-error").disabled = false;
    } catch (error) {
      $("toggle-error").title = error.message;
    }
  }
  $("toggle-error").addEventListener("click", () => {
    const on = $("toggle-error").getAttribute("aria-pressed") !== "true";
    $("toggle-error").setAttribute("aria-pressed", String(on));
    viewer.setErrorOverlay(on ? { rgba: errorMap.rgba(), cols: errorMap.cols, rows: errorMap.rows } : null);
    $("legend").hidden = !on;
  });
  $("fit-view").addEventListener("click", () => viewer.fitView());

  // The PLY's level of detail: "base" (the mesh on screen) or a detail level of the bundle.
  const select = $("ply-level");
  let levels = [];
  try {
    levels = plyLevels(manifest);
  } catch (error) {
    select.title = error.message; // stays hidden: the base PLY alone
    console.warn(error.message);
  }
  const units = manifest.units || ready.patch.units || "unknown";
  for (const choice of levels) select.append(levelOption(choice, units));
  if (levels.length) {
    const spans = manifest.tiles.detail.spans_per_tile;
    select.title = "Level of detail of the PLY. base: the mesh on screen (with the error map's " +
      "colours when it is shown). level L: the base with every detail tile of levels 0..L " +
      "(their total size is shown; tiles already loaded are not fetched again), the RMS " +
      "distance to the scan at that level, tessellated over the whole object on an R × R " +
      `grid, R = min(${PLY_MAX_RES}, 2 × ${spans} spans per tile × 2^L + 1): two vertices ` +
      "per knot span of the level's tiles" + (manifest.tiles.texture
        ? "; with the object's colours sampled from its texture tiles (size included)." : ".");
    select.hidden = false;
    select.disabled = false;
    // "Open in 3DHOP" shows the level chosen here (the 3DHOP page's ?level=L)
    const hopLink = config.hop_url &&
      [...document.querySelectorAll(".actions a")].find((a) => a.getAttribute("href") === config.hop_url);
    if (hopLink) {
      select.addEventListener("change", () => {
        const url = new URL(config.hop_url, window.location.href);
        if (Number(select.value) >= 0) url.searchParams.set("level", select.value);
        hopLink.href = url.href;
      });
    }
  }

  $("download-ply").disabled = false;
  $("download-ply").addEventListener("click", async () => {
    const button = $("download-ply");
    const level = Number(select.value);
    button.disabled = true;
    select.disabled = true;
    document.body.dataset.plyBusy = "1";
    document.body.dataset.stage = "ply";
    showPlyStatus(level < 0 ? "Writing the PLY…" : "");
    try {
      let ply;
      let name = config.ply_name;
      if (level < 0) {
        const t0 = performance.now();
        const overlay = $("toggle-error").getAttribute("aria-pressed") === "true";
        let colors = null;
        if (overlay && errorMap) colors = errorMap.vertexColors(currentUvs, domain);
        ply = await worker.ply(current, colors);
        stats.ply_total_ms = performance.now() - t0;
        Object.assign(stats, { ply_tiles_fetched: 0, ply_fetch_bytes: 0, ply_textures: 0,
                               ply_texture_bytes: 0 });
      } else {
        const choice = levels.find((c) => c.level === level);
        ply = await levelPly(worker, choice, { manifestUrl: config.manifest_url, stats,
                                               onProgress: showPlyStatus });
        name = `${config.ply_name.replace(/\.ply$/i, "")}_level${level}.ply`;
      }
      Object.assign(stats, { ply_level: level, ply_bytes: ply.bytes.length, ply_vertices: ply.vertices,
                             ply_resolution: ply.resolution, ply_ms: ply.write_ms });
      saveFile(ply.bytes, name);
      showPlyStatus(`${name}: ${formatBytes(ply.bytes.length)}, ` +
        `${ply.vertices.toLocaleString("en")} vertices (${ply.resolution}² grid), ` +
        `${(stats.ply_total_ms / 1000).toFixed(1)} s`);
    } catch (error) {
      showPlyStatus("");
      showError(`Download PLY${level >= 0 ? ` (level ${level})` : ""} failed: ${error.message}`);
    } finally {
      delete document.body.dataset.plyBusy;
      button.disabled = false;
      select.disabled = !levels.length;
    }
  });

  if (target !== current) await showResolution(target);
  await new Promise((resolve) => requestAnimationFrame(resolve));
  stats.refined_ms = performance.now();
  document.body.dataset.refined = "1";
}

main().catch((error) => {
  console.error(error);
  showError(error.message || String(error));
});
