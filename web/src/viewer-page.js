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
// All URLs come from the server's JSON config block.

import { ErrorMap } from "./error-map.js";
import { MeshWorkerClient } from "./mesh-worker-client.js";
import { $, startPage } from "./page.js";

const COARSE = 24; // first mesh: ~1k vertices, drawn within milliseconds of the patch
const MIN_RES = 48;
const MAX_RES = 384;

const { config, stats, showStage, showError } = startPage({
  manifest: "Reading the object's description…",
  runtime: "Starting the Python runtime (Pyodide)…",
  client_py: "Installing client_py…",
  patch: "Reading the NURBS patch…",
  tessellation: "Tessellating…",
}, { resolution: null, meshes: 0, tiles_loaded: 0, tile_bytes: 0, tile_tessellate_ms: 0, regions: 0 });

function formatBytes(n) {
  if (n < 1024) return `${n} B`;
  if (n < 1024 * 1024) return `${(n / 1024).toFixed(1)} KB`;
  return `${(n / 1024 / 1024).toFixed(1)} MB`;
}

function formatLength(value, units) {
  if (value === undefined || value === null || !Number.isFinite(value)) return "—";
  const digits = Math.abs(value) >= 10 ? 1 : Math.abs(value) >= 1 ? 2 : 3;
  return `${value.toFixed(digits)} ${units === "unknown" ? "" : units}`.trim();
}

function setFact(id, text) {
  const el = $(id);
  if (el) el.textContent = text;
}

/** Grid size that puts a vertex every ~3 device pixels across the object on screen. */
function viewResolution(viewer) {
  const pixels = viewer.projectedDiameter() / 3;
  return Math.min(MAX_RES, Math.max(MIN_RES, Math.round(pixels / 16) * 16));
}

async function loadManifest() {
  const response = await fetch(config.manifest_url);
  if (!response.ok) throw new Error(`cannot fetch the manifest (${config.manifest_url}): HTTP ${response.status}`);
  const text = await response.text();
  stats.bytes_downloaded += text.length;
  try {
    return JSON.parse(text);
  } catch (error) {
    throw new Error(`the manifest is not valid JSON: ${error.message}`);
  }
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
  const manifestPromise = loadManifest();
  manifestPromise.catch(() => {});
  const tileModule = import("./tile-layer.js");
  tileModule.catch(() => {});
  const { Viewer } = await import("./viewer.js");
  const { REGION_GRID } = await tileModule;
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
    const grid = REGION_GRID;
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
  $("download-ply").disabled = false;
  $("download-ply").addEventListener("click", async () => {
    const button = $("download-ply");
    button.disabled = true;
    try {
      const overlay = $("toggle-error").getAttribute("aria-pressed") === "true";
      let colors = null;
      if (overlay && errorMap) colors = errorMap.vertexColors(currentUvs, domain);
      const ply = await worker.ply(current, colors);
      const url = URL.createObjectURL(new Blob([ply.bytes], { type: "application/octet-stream" }));
      const link = document.createElement("a");
      link.href = url;
      link.download = config.ply_name;
      document.body.append(link);
      link.click();
      link.remove();
      setTimeout(() => URL.revokeObjectURL(url), 10000);
    } catch (error) {
      showError(`Download PLY failed: ${error.message}`);
    } finally {
      button.disabled = false;
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
