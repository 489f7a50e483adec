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
// sampled by client_py in the worker; page.js levelPly, on the worker's plan of each level:
// client_py.bundle.plan_level).
// Its stats: ply_level (-1 base), ply_bytes (the file's size), ply_vertices, ply_resolution,
// ply_ms (Python), ply_total_ms (fetch + tessellate + write), ply_tiles_fetched,
// ply_fetch_bytes (detail tiles), ply_textures, ply_texture_bytes (texture tiles fetched);
// document.body.dataset.plyBusy is "1" while a PLY is being made, and
// #ply-status (under the buttons) says what is being done, then the file written. "Open in
// 3DHOP" follows the level chosen (its ?level=L).
// All URLs come from the server's JSON config block.

import { BaseMesh, COARSE_RESOLUTION } from "./base-mesh.js";
import { ErrorMapControl } from "./error-map-control.js";
import { FactsPanel } from "./facts-panel.js";
import { MeshWorkerClient } from "./mesh-worker-client.js";
import {
  $, formatBytes, formatLength, levelOption, levelPly, loadManifest, startPage,
} from "./page.js";

const { config, stats, showStage, showError } = startPage({
  manifest: "Reading the object's description…",
  runtime: "Starting the Python runtime (Pyodide)…",
  client_py: "Installing client_py…",
  patch: "Reading the NURBS patch…",
  tessellation: "Tessellating…",
  ply: "Making the PLY…",
}, { resolution: null, meshes: 0, tiles_loaded: 0, tile_bytes: 0, tile_tessellate_ms: 0, regions: 0,
     ply_level: null, ply_bytes: 0 });

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

/** `promise`, marked handled now: it is awaited later, and an early failure must not be
 *  reported as unhandled before then (it still rejects where it is awaited). */
function awaitedLater(promise) {
  promise.catch(() => {});
  return promise;
}

const nextFrame = () => new Promise((resolve) => requestAnimationFrame(resolve));

/** The mesh worker, starting Pyodide, client_py and the base patch; `ready` resolves with
 *  its init reply {patch, patch_bytes, pyodide_load_ms, stages, kernel}. */
function startWorker() {
  const worker = new MeshWorkerClient(config.worker_url, { onStage: showStage });
  const ready = worker.init({
    pyodideUrl: config.pyodide_url, pyodideSnapshotUrl: config.pyodide_snapshot_url,
    clientPyUrl: config.client_py_url, patchUrl: config.patch_url,
  }, config.pyodide_timeout_s);
  return { worker, ready: awaitedLater(ready) };
}

/** Keep the object clear of the information panel: beside it on wide screens, above it on
 *  narrow ones (style.css moves the panel to the bottom below 700 px). */
function keepClearOfPanel(viewer, panel) {
  const insets = () => {
    const box = panel.getBoundingClientRect();
    if (window.innerWidth > 900) return { left: box.right };
    if (window.innerWidth <= 700) return { bottom: window.innerHeight - box.top };
    return {};
  };
  viewer.setInsets(insets());
  window.addEventListener("resize", () => viewer.setInsets(insets()));
}

/** The worker's init reply in the stats of the testing contract. */
function recordWorkerStats(ready) {
  stats.pyodide_load_ms = ready.pyodide_load_ms;
  stats.worker_stages = ready.stages;
  stats.kernel = ready.kernel;
  stats.bytes_downloaded += ready.patch_bytes;
}

/** The first mesh, coarse, on screen, then the page is ready (document.body.dataset.ready);
 *  resolves with the grid to refine to. */
async function showFirstMesh(base) {
  showStage("tessellation");
  const target = base.targetResolution();
  await base.show(Math.min(COARSE_RESOLUTION, target));
  await nextFrame();
  stats.first_frame_ms = performance.now();
  stats.coarse_resolution = base.resolution;
  document.body.dataset.ready = "1";
  $("loading").hidden = true;
  return target;
}

/** The base at the grid `target`, then document.body.dataset.refined. */
async function refineBase(base, target) {
  if (target !== base.resolution) await base.show(target);
  await nextFrame();
  stats.refined_ms = performance.now();
  document.body.dataset.refined = "1";
}

/**
 * The detail tiles over the base on screen: a TileLayer, refining as the camera moves. A
 * malformed tile tree (TileLayer's constructor throws) leaves the base alone and gives null;
 * that reason, or a tile failing later, goes to document.body.dataset.tileError and the
 * Detail fact.
 */
function startTiles(TileLayer, { viewer, worker, manifest, base, facts }) {
  const fail = (message) => {
    document.body.dataset.tileError = message;
    facts.set("fact-detail", message);
  };
  let tiles;
  try {
    tiles = new TileLayer({
      viewer, worker, manifest, manifestUrl: config.manifest_url, stats,
      onError: (message) => {
        console.error(message);
        fail(message);
      },
      onChange: () => facts.showTiles(stats),
    });
  } catch (error) {
    fail(error.message);
    return null;
  }
  if (!tiles.enabled) {
    facts.set("fact-detail", "none in this bundle");
    return tiles;
  }
  facts.showTiles(stats);
  tiles.setBase({ positions: viewer.mesh.geometry.getAttribute("position").array, uvs: base.uvs },
                base.domain);
  tiles.schedule(0);
  return tiles;
}

/**
 * The testing contract's functions on window.tessera (see the top of this file). `tiles()`
 * gives the TileLayer (null before it starts, or without one); `tilesStarted` resolves once
 * that is settled.
 */
function exposeTestHooks({ viewer, base, tiles, tilesStarted }) {
  window.tessera.tessellate = (resolution) => base.show(resolution);
  window.tessera.tilesIdle = async () => {
    await tilesStarted;
    if (tiles()) await tiles().idle();
    return { ...stats };
  };
  window.tessera.view = () => ({
    projection: Array.from(viewer.camera.projectionMatrix.elements),
    view: Array.from(viewer.camera.matrixWorldInverse.elements),
  });
  window.tessera.regionMeshes = () => {
    const layer = tiles();
    if (!layer) return [];
    const grid = layer.regionGrid;
    return [...layer.regions].map(([id, mesh]) => {
      const [level, i, j] = id.split("/").map(Number);
      const st = mesh.geometry.getAttribute("uv").array;
      const uvs = [];
      for (let k = 0; k < grid * grid; k++) uvs.push(st[2 * k + 1], st[2 * k]);
      return { level, i, j, grid, uvs,
               positions: Array.from(mesh.geometry.getAttribute("position").array.subarray(0, 3 * grid * grid)) };
    });
  };
  window.tessera.zoomTo = async (u, v, distance) => {
    await tilesStarted;
    viewer.lookAtSurface(u, v, distance, base.uvs, base.domain);
    const layer = tiles();
    if (layer) {
      await layer.update();
      await layer.idle();
    }
    return { ...stats };
  };
}

async function main() {
  // Start the worker (Pyodide: seconds) before three.js is even fetched: they load in parallel.
  const { worker, ready: readyPromise } = startWorker();
  const manifestPromise = awaitedLater(loadManifest(config.manifest_url, stats));
  const tileModule = awaitedLater(import("./tile-layer.js"));
  const { Viewer } = await import("./viewer.js");
  const viewer = new Viewer($("view"));
  keepClearOfPanel(viewer, document.querySelector(".panel"));
  const facts = new FactsPanel();
  let tiles = null; // TileLayer once the manifest and the first mesh are in
  let settleTiles;
  const tilesStarted = new Promise((resolve) => { settleTiles = resolve; });
  const base = new BaseMesh({
    viewer, worker, stats, fixedResolution: config.resolution || null,
    onShown: (mesh) => {
      facts.showMesh(stats);
      if (tiles) {
        tiles.setBase(mesh, base.domain);
        tiles.schedule(0);
      }
    },
  });
  exposeTestHooks({ viewer, base, tiles: () => tiles, tilesStarted });
  // the camera moved: new regions; a zoom gesture ended: maybe a finer or coarser base grid
  viewer.controls.addEventListener("change", () => tiles && tiles.schedule());
  base.followZoom(showError);

  const ready = await readyPromise;
  const manifest = await manifestPromise;
  recordWorkerStats(ready);
  base.domain = ready.patch.domain;
  facts.describe(manifest, ready, stats);
  const target = await showFirstMesh(base);

  const { TileLayer } = await tileModule;
  tiles = startTiles(TileLayer, { viewer, worker, manifest, base, facts });
  settleTiles();
  const errorMap = new ErrorMapControl(manifest, viewer);
  $("fit-view").addEventListener("click", () => viewer.fitView());

  // The PLY's level of detail: "base" (the mesh on screen) or a detail level of the bundle.
  const select = $("ply-level");
  let levels = [];
  let plan = null; // the worker's plan of the levels (MeshWorkerClient.plan)
  try {
    plan = await worker.plan(manifest);
    levels = plan.levels;
  } catch (error) {
    select.title = error.message; // stays hidden: the base PLY alone
    console.warn(error.message);
  }
  const units = manifest.units || ready.patch.units || "unknown";
  for (const choice of levels) select.append(levelOption(choice, units));
  if (levels.length) {
    select.title = "Level of detail of the PLY. base: the mesh on screen (with the error map's " +
      "colours when it is shown). level L: the base with every detail tile of levels 0..L " +
      "(their total size is shown; tiles already loaded are not fetched again), the RMS " +
      "distance to the scan at that level, tessellated over the whole object on an R × R " +
      `grid, R = min(${plan.max_resolution}, 2 × ${plan.spans_per_tile} spans per tile × 2^L + 1): ` +
      "two vertices " +
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
        const colors = errorMap.vertexColors(base.uvs, base.domain);
        ply = await worker.ply(base.resolution, colors);
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

  await refineBase(base, target);
}

main().catch((error) => {
  console.error(error);
  showError(error.message || String(error));
});
