// The viewer page: wires the mesh worker, the three.js Viewer and the page's controls.
//
// Testing contract: document.body.dataset.ready === "1" once the first mesh is drawn;
// document.body.dataset.error holds the message on failure; window.tessera.stats =
// {vertices, triangles, tessellate_ms, pyodide_load_ms, first_frame_ms, bytes_downloaded,
//  kernel, resolution, tiles_loaded, tile_bytes, tile_tessellate_ms, regions, ...}
// (vertices/triangles: the base mesh; tile stats: web/src/tile-layer.js; pieces_triangles: a
// patch's detached pieces drawn beside it, manifest.pieces). Detail tiles load on
// zoom (web/src/tile-tree.js); window.tessera.zoomTo(u, v, distance) frames the surface point
// at normalised (u, v) from `distance` scan units along its normal and resolves once the
// tiles for that view are on screen; window.tessera.tilesIdle() resolves when no tile update
// is due; window.tessera.view() gives the camera's projection and view matrices (column-major)
// and window.tessera.regionMeshes() the regions on screen ({level, i, j, grid, positions, uvs}
// of their grid vertices, skirts left out), for tests. A tile that fails to load sets document.body.dataset.tileError (the base stays);
// pieces that fail to load set document.body.dataset.piecesError (the patch stays).
// "Download PLY" and its level choice: web/src/ply-download.js (its stats and
// document.body.dataset.plyBusy are described there). The page's parts: BaseMesh
// (base-mesh.js), FactsPanel (facts-panel.js), ErrorMapControl (error-map-control.js),
// TileLayer (tile-layer.js), PlyDownload (ply-download.js).
// All URLs come from the server's JSON config block.
// An atlas bundle (manifest format_version 2) is drawn by AtlasLayer (atlas-layer.js): one
// welded mesh refined by group on zoom; window.tessera.atlasView(position, target) puts the
// camera there (scan frame) and resolves with the stats once the groups it wants are shown;
// window.tessera.atlasIdle() resolves when no atlas update is due.

import { BaseMesh, COARSE_RESOLUTION } from "./base-mesh.js";
import { ErrorMapControl } from "./error-map-control.js";
import { FactsPanel } from "./facts-panel.js";
import { MeshWorkerClient } from "./mesh-worker-client.js";
import { $, atlasBaseChoice, loadManifest, loadPieces, startPage, workerInit } from "./page.js";
import { PlyDownload } from "./ply-download.js";
import { TransferTally } from "./transfer-tally.js";

const { config, stats, showStage, showProgress, showError } = startPage({
  manifest: "Reading the object's description…",
  runtime: "Starting the Python runtime (Pyodide)…",
  client_py: "Installing client_py…",
  patch: "Reading the NURBS patch…",
  tessellation: "Tessellating…",
  ply: "Making the PLY…",
}, { resolution: null, meshes: 0, tiles_loaded: 0, tile_bytes: 0, tile_tessellate_ms: 0, regions: 0,
     ply_level: null, ply_bytes: 0 });

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
  const worker = new MeshWorkerClient(config.worker_url,
                                      { onStage: showStage, onProgress: showProgress });
  const ready = worker.init(workerInit(config), config.pyodide_timeout_s);
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

/** What this visit transferred, shown in the panel and kept as stats.transfer: the worker's
 *  fetches (its init reply's `resources`, added once) and the page's, read again at each call
 *  (tiles keep arriving). */
function showTransfers(tally, facts) {
  tally.add("page", [...performance.getEntriesByType("navigation"),
                     ...performance.getEntriesByType("resource")]);
  stats.transfer = tally.summary();
  facts.showTransfer(stats.transfer);
}

/** The first mesh, coarse, on screen, then the page is ready (document.body.dataset.ready). */
async function showFirstMesh(base) {
  showStage("tessellation");
  await base.show(Math.min(COARSE_RESOLUTION, base.targetResolution()));
  await nextFrame();
  stats.first_frame_ms = performance.now();
  stats.coarse_resolution = base.resolution;
  document.body.dataset.ready = "1";
  $("loading").hidden = true;
}

/** The base at the grid the view wants once the first detail regions are in (a backdrop's
 *  when they cover the view), then document.body.dataset.refined. */
async function refineBase(base, tiles) {
  if (tiles && tiles.enabled) await tiles.idle();
  const target = base.targetResolution();
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
function startTiles(TileLayer, { viewer, worker, manifest, planned, base, facts, transfers }) {
  const fail = (message) => {
    document.body.dataset.tileError = message;
    facts.set("fact-detail", message);
  };
  let tiles;
  try {
    // each level's region grid: the worker's plan (client_py's one rule of a level's grid)
    const regionGrids = planned.plan ? planned.plan.levels.map((l) => l.region_resolution) : null;
    tiles = new TileLayer({
      viewer, worker, manifest, manifestUrl: config.manifest_url, regionGrids, stats,
      onError: (message) => {
        console.error(message);
        fail(message);
      },
      onChange: () => {
        facts.showTiles(stats);
        showTransfers(transfers, facts);
      },
    });
  } catch (error) {
    fail(planned.error || error.message); // a manifest the worker cannot plan: its reason
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
  window.tessera.camera = () => ({
    up: viewer.camera.up.toArray(), position: viewer.camera.position.toArray(),
    target: viewer.controls.target.toArray(),
  });
  window.tessera.regionMeshes = () => {
    const layer = tiles();
    if (!layer) return [];
    return [...layer.regions].map(([id, mesh]) => {
      const [level, i, j] = id.split("/").map(Number);
      const grid = layer.regionGrid(level);
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

/** The worker's plan of the manifest's levels (MeshWorkerClient.plan): {plan} or, for a
 *  manifest it cannot plan, {error} (the reason). */
async function planLevels(worker, manifest) {
  try {
    return { plan: await worker.plan(manifest) };
  } catch (error) {
    return { error: error.message };
  }
}

/** The PLY levels of the bundle, as `planned` (planLevels), offered by `download`; a
 *  manifest the worker cannot plan leaves the base PLY alone, said so. */
function offerPly(download, planned, manifest, ready) {
  if (!planned.plan) {
    download.offerBaseOnly(planned.error);
    return;
  }
  const plan = planned.plan;
  download.offerLevels(plan, manifest.units || ready.patch.units || "unknown",
                       Boolean(manifest.tiles && manifest.tiles.texture));
}

/** An atlas bundle: the base of every group, then refinement by group as the camera moves
 *  (AtlasLayer), "Download PLY" of every level. */
async function showAtlas({ viewer, worker, manifest, ready, facts, transfers }) {
  facts.describeAtlas(manifest, ready, stats);
  viewer.setObjectView(manifest.view || null);
  showStage("tessellation");
  const plan = await worker.plan(manifest); // the worker keeps the manifest for what follows
  const refinement = await worker.atlasRefinement();
  const { AtlasLayer } = await import("./atlas-layer.js");
  const layer = new AtlasLayer({
    viewer, worker, refinement, manifestUrl: config.manifest_url, stats,
    onError: (message) => {
      console.error(message);
      document.body.dataset.tileError = message;
      facts.set("fact-detail", message);
    },
    onChange: () => {
      facts.showMesh(stats);
      facts.showAtlas(stats, refinement.groups.length);
      showTransfers(transfers, facts);
    },
  });
  await layer.show(refinement.groups.map(() => -1));
  // the error map: per patch cells of the fit error, coloured per vertex by the worker
  const errorMap = new ErrorMapControl(manifest, viewer, { show: (map) => layer.showErrorMap(map) });
  if (!errorMap.errorMap && !$("toggle-error").title) {
    $("toggle-error").title = "No error map in this atlas bundle (fitted before error_raster): " +
      "its fit error is in the panel";
  }
  facts.showMesh(stats);
  if (layer.enabled) facts.showAtlas(stats, refinement.groups.length);
  else facts.set("fact-detail", "none in this bundle");
  await nextFrame();
  stats.first_frame_ms = performance.now();
  stats.atlas_patches = ready.patch.patches;
  document.body.dataset.ready = "1";
  $("loading").hidden = true;
  showTransfers(transfers, facts);
  viewer.controls.addEventListener("change", () => layer.schedule());
  $("fit-view").addEventListener("click", () => viewer.fitView());
  $("front-view").addEventListener("click", () => viewer.showFront());
  window.tessera.atlasIdle = async () => {
    await layer.idle();
    return { ...stats };
  };
  window.tessera.atlasView = async (position, target) => {
    viewer.camera.position.set(...position);
    viewer.controls.target.set(...target);
    viewer.controls.update();
    viewer.render();
    await layer.update();
    await layer.idle();
    return { ...stats };
  };
  const download = new PlyDownload({ worker, base: null, errorMap: null, config, stats,
                                     onError: showError });
  download.offerAtlasLevels(plan, manifest.units || ready.patch.units || "unknown",
                            atlasBaseChoice(refinement, plan.levels));
  document.body.dataset.refined = "1";
}

async function main() {
  performance.setResourceTimingBufferSize(5000); // every tile of a long visit (default: 250)
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
    onShown: (mesh, { following }) => {
      facts.showMesh(stats);
      if (tiles) {
        tiles.setBase(mesh, base.domain);
        // the coarse first base's boxes were rough: choose again; a zoom's finer base only
        // sharpens them a little, and the regions it has are already drawn
        if (!following) tiles.schedule(0);
      }
    },
    waitFor: () => (tiles ? tiles.idle() : Promise.resolve()),
    backdrop: () => Boolean(tiles && tiles.enabled && stats.regions > 0),
  });
  exposeTestHooks({ viewer, base, tiles: () => tiles, tilesStarted });
  // the camera moved: new regions; a zoom gesture ended: maybe a finer or coarser base grid
  viewer.controls.addEventListener("change", () => tiles && tiles.schedule());
  base.followZoom(showError);

  const ready = await readyPromise;
  const manifest = await manifestPromise;
  recordWorkerStats(ready);
  if (ready.patch.kind === "atlas") {
    const transfers = new TransferTally(config.manifest_url, window.location.href);
    transfers.add("worker", ready.resources || []);
    settleTiles();
    await showAtlas({ viewer, worker, manifest, ready, facts, transfers });
    return;
  }
  base.domain = ready.patch.domain;
  facts.describe(manifest, ready, stats);
  viewer.setObjectView(manifest.view || null); // older bundles have none: the fallback framing
  const transfers = new TransferTally(config.manifest_url, window.location.href);
  transfers.add("worker", ready.resources || []);
  worker.onResources = (entries) => transfers.add("worker", entries); // tiles it fetched
  await showFirstMesh(base);
  showTransfers(transfers, facts);

  const { TileLayer } = await tileModule;
  const planned = await planLevels(worker, manifest); // the worker keeps the manifest
  if (planned.plan) {
    try {
      const pieces = await loadPieces(worker, manifest, { manifestUrl: config.manifest_url, stats });
      if (pieces) {
        viewer.setPieces(pieces);
        stats.pieces_triangles = pieces.indices.length / 3;
      }
    } catch (error) { // a missing or bad pieces.tsa: the patch stays, the reason is kept
      document.body.dataset.piecesError = error.message;
    }
  }
  tiles = startTiles(TileLayer, { viewer, worker, manifest, planned, base, facts, transfers });
  settleTiles();
  const errorMap = new ErrorMapControl(manifest, viewer, {
    baseUrl: new URL(config.manifest_url, window.location.href) });
  $("fit-view").addEventListener("click", () => viewer.fitView());
  $("front-view").addEventListener("click", () => viewer.showFront());

  offerPly(new PlyDownload({ worker, base, errorMap, config, stats, onError: showError }),
           planned, manifest, ready);
  await refineBase(base, tiles);
  showTransfers(transfers, facts);
}

main().catch((error) => {
  console.error(error);
  showError(error.message || String(error));
});
