// What every object page shares: the server's JSON config block, the stats object of the
// testing contract (window.tessera.stats), the loading and error panels
// (templates/_status.html; on failure the message goes to document.body.dataset.error), the
// manifest, and the bundle at a detail level as a PLY (the viewer's "Download PLY" and the
// 3DHOP page's ?level=L): the level choice (levelOption) of the worker's plan (which detail
// and texture tiles a level needs: MeshWorkerClient.plan, client_py.bundle.plan_level), their
// fetching, the texture tiles decoded to RGB bytes (decodeTextureRgb) and the worker's
// tessellation with them (levelPly).

import { fetchBytes } from "./fetch-bytes.js";

export const $ = (id) => document.getElementById(id);

const FETCH_PARALLEL = 6; // tile fetches in flight at once for a PLY

export function startPage(stages, extraStats = {}) {
  const config = JSON.parse($("tessera-config").textContent);
  const stats = { vertices: 0, triangles: 0, tessellate_ms: null, pyodide_load_ms: null,
    first_frame_ms: null, bytes_downloaded: 0, kernel: null, ...extraStats };
  window.tessera = { config, stats };

  /** Show `stage`'s text in the loading panel, or `text` when given (progress within it). */
  function showStage(stage, text) {
    $("loading-text").textContent = typeof text === "string" ? text : stages[stage] || stage;
    document.body.dataset.stage = stage;
  }

  /** `loaded` of `total` bytes of the runtime fetched: the current stage's text with the
   *  percentage (document.body.dataset.loadPercent too, for tests). */
  function showProgress(loaded, total) {
    const stage = document.body.dataset.stage || "runtime";
    const percent = loadPercent(loaded, total);
    if (percent === null) return;
    document.body.dataset.loadPercent = String(percent);
    $("loading-text").textContent = withPercent(stages[stage] || stage, percent);
  }

  function showError(message) {
    document.body.dataset.error = message;
    $("loading").hidden = true;
    $("error").hidden = false;
    $("error-text").textContent = message;
  }

  return { config, stats, showStage, showProgress, showError };
}

/** Whole percent of `loaded` bytes of `total` (at most 100), or null without a total. */
export function loadPercent(loaded, total) {
  if (!(total > 0) || !Number.isFinite(loaded)) return null;
  return Math.min(100, Math.max(0, Math.floor((100 * loaded) / total)));
}

/** A stage's text with its percentage: "Starting the Python runtime (Pyodide)… 42 %". */
export function withPercent(text, percent) {
  return `${text} ${percent} %`;
}

/** The mesh worker's init request from the page's config (MeshWorkerClient.init): the
 *  runtime's URLs (the trimmed standard library, the lock file's info, the snapshot when the
 *  server has one), the bytes it will fetch (for the percentage) and the patch. */
export function workerInit(config) {
  return {
    pyodideUrl: config.pyodide_url, pyodideSnapshotUrl: config.pyodide_snapshot_url,
    pyodideStdlibUrl: config.pyodide_stdlib_url, pyodideLock: config.pyodide_lock,
    runtimeBytes: config.runtime_bytes, clientPyUrl: config.client_py_url,
    patchUrl: config.patch_url,
  };
}

/** "1 texture tile", "4 texture tiles". */
export function plural(n, word) {
  return `${n.toLocaleString("en")} ${word}${n === 1 ? "" : "s"}`;
}

export function formatBytes(n) {
  if (n < 1024) return `${n} B`;
  if (n < 1024 * 1024) return `${(n / 1024).toFixed(1)} KB`;
  return `${(n / 1024 / 1024).toFixed(1)} MB`;
}

/** Millimetres per metric unit (client_py's unit names, fitter.fitting.io.scan): a length
 *  under one of these units is shown in mm, so that a fit error of 0.0003 m reads "0.309 mm". */
const MM_PER_UNIT = { km: 1e6, m: 1e3, cm: 10 };

/**
 * A length with its unit for the panel and the legend: 1 decimal from 10, 2 from 1, else 3
 * significant digits (never rounded to "0.000"); below 1 km, m or cm it is given in mm; no
 * unit for "unknown"; a dash for no value.
 */
export function formatLength(value, units) {
  if (value === undefined || value === null || !Number.isFinite(value)) return "—";
  let unit = units === "unknown" ? "" : units;
  if (unit in MM_PER_UNIT && Math.abs(value) < 1) {
    value *= MM_PER_UNIT[unit];
    unit = "mm";
  }
  const size = Math.abs(value);
  const text = size >= 10 ? value.toFixed(1) : size >= 1 ? value.toFixed(2)
    : size === 0 ? "0" : value.toPrecision(3);
  return `${text} ${unit}`.trim();
}

/** The bundle's manifest.json, parsed; its size is added to stats.bytes_downloaded. */
export async function loadManifest(url, stats) {
  const bytes = await fetchBytes(url, "the manifest");
  stats.bytes_downloaded += bytes.length;
  const text = new TextDecoder().decode(bytes);
  try {
    return JSON.parse(text);
  } catch (error) {
    throw new Error(`the manifest is not valid JSON: ${error.message}`);
  }
}

/** An <option> for a level choice (an entry of MeshWorkerClient.plan's levels): its label
 *  gives the bytes to fetch (detail and texture tiles) and the RMS at that level, its title
 *  the files and the grid. */
export function levelOption(choice, units) {
  const option = document.createElement("option");
  const textures = choice.texture_nodes.length;
  option.value = String(choice.level);
  option.textContent = `level ${choice.level} · ` +
    `${formatBytes(choice.detail_bytes + choice.texture_bytes)} · ` +
    `RMS ${formatLength(choice.rms, units)}` + (textures ? " · colour" : "");
  option.title = `base + ${plural(choice.detail_files.length, "detail tile")} of levels ` +
    `0–${choice.level} (${formatBytes(choice.detail_bytes)})` +
    (textures ? `, vertex colours from ${plural(textures, "texture tile")} ` +
      `(${formatBytes(choice.texture_bytes)})` : "") +
    `, tessellated on a ${choice.resolution} × ${choice.resolution} grid`;
  return option;
}

/** The base of an atlas bundle (manifest format_version 2) as a level choice (-1), like the
 *  entries of MeshWorkerClient.plan's levels: no packs, base.resolution samples per patch
 *  side (`refinement`: MeshWorkerClient.atlasRefinement's reply). Its PLY goes through
 *  levelPly like a detail level's: the worker writes the welded atlas at that resolution,
 *  coloured (with colour) from colour level 0, which level 0 of `levels` (the plan's) names
 *  too (client_py.atlas_texture.colour_level). */
export function atlasBaseChoice(refinement, levels = []) {
  const textures = levels.length ? levels[0].texture_nodes : [];
  return { level: -1, rms: null, detail_files: [], detail_bytes: 0, texture_nodes: textures,
           texture_bytes: textures.reduce((sum, node) => sum + (node.bytes || 0), 0),
           resolution: refinement.resolutions[0] };
}

/** Run `task(item)` over `items`, at most `limit` at a time; rejects with the first failure
 *  (no new task starts after it). */
export async function forEachLimited(items, limit, task) {
  let next = 0;
  let failed = false;
  const run = async () => {
    while (!failed && next < items.length) {
      const item = items[next++];
      try {
        await task(item);
      } catch (error) {
        failed = true;
        throw error;
      }
    }
  };
  await Promise.all(Array.from({ length: Math.min(limit, items.length) }, run));
}

/** A texture tile's image (WebP or PNG bytes) decoded to 8-bit RGB as client_py's TextureImage
 *  holds it: {level, i, j, width, height, rgb: Uint8Array of 3 width height bytes}, rows top
 *  (y = 0, v = v1) to bottom, as stored (docs/format.md, "Texture tiles"; no flip, no colour
 *  management: the file's bytes are the colours). `node` is its manifest node. */
export async function decodeTextureRgb(bytes, node) {
  let bitmap;
  try {
    bitmap = await createImageBitmap(new Blob([bytes]), {
      colorSpaceConversion: "none", premultiplyAlpha: "none" });
  } catch (error) {
    throw new Error(`texture tile ${node.file} is not a decodable image: ${error.message}`);
  }
  const { width, height } = bitmap;
  const canvas = new OffscreenCanvas(width, height);
  const context = canvas.getContext("2d", { willReadFrequently: true });
  context.drawImage(bitmap, 0, 0);
  bitmap.close();
  const rgba = context.getImageData(0, 0, width, height).data;
  const rgb = new Uint8Array(3 * width * height);
  for (let k = 0, m = 0; m < rgb.length; k += 4, m += 3) {
    rgb[m] = rgba[k];
    rgb[m + 1] = rgba[k + 1];
    rgb[m + 2] = rgba[k + 2];
  }
  return { level: node.level, i: node.i, j: node.j, file: node.file, width, height, rgb };
}

/** A patch bundle's detached pieces (manifest.pieces.file, docs/format.md "Pieces"), fetched
 *  by the worker after plan() and kept for every PLY it writes: resolves with their mesh
 *  (MeshWorkerClient.pieces), or null when the bundle draws none; adds their bytes to
 *  stats.bytes_downloaded. */
export async function loadPieces(worker, manifest, { manifestUrl, stats }) {
  if (!manifest.pieces || !manifest.pieces.file) return null;
  const url = new URL(manifest.pieces.file, new URL(manifestUrl, window.location.href));
  const mesh = await worker.pieces(url.href);
  stats.bytes_downloaded += mesh.bytes;
  return mesh;
}

/**
 * The PLY of the bundle at detail level choice.level (an entry of MeshWorkerClient.plan's
 * levels): the detail tiles the worker does not hold are fetched, the texture tiles fetched
 * and decoded to RGB, then the worker tessellates the whole patch with them
 * (MeshWorkerClient.plyLevel).
 * Resolves with the worker's reply {bytes, vertices, triangles, resolution, write_ms}.
 * Sets stats.ply_tiles_fetched, ply_fetch_bytes (detail tiles), ply_textures,
 * ply_texture_bytes, ply_total_ms and adds what it fetched to bytes_downloaded;
 * onProgress(text) is told what is being done. A tile that cannot be fetched or decoded
 * rejects with its name and the reason.
 */
export async function levelPly(worker, choice, { manifestUrl, stats, onProgress = () => {} }) {
  const t0 = performance.now();
  const baseUrl = new URL(manifestUrl, window.location.href);
  const fresh = new Map(); // name -> bytes fetched for this PLY
  const images = [];
  let fetched = 0;
  let textureBytes = 0;
  const total = choice.detail_files.length;
  const textures = choice.texture_nodes;
  const lacking = () => choice.detail_files.filter((name) => !fresh.has(name) && !worker.holds(name));
  const progress = () => {
    const done = total - lacking().length + images.length;
    const percent = Math.floor((100 * done) / Math.max(1, total + textures.length));
    onProgress(`Fetching the detail tiles of levels 0–${choice.level}: ${percent} % (` +
      `${total - lacking().length} of ${total}` +
      (textures.length ? `, texture tiles: ${images.length} of ${textures.length}` : "") +
      `, ${formatBytes(fetched + textureBytes)} fetched)…`);
  };
  const fetchTiles = (names) => forEachLimited(names, FETCH_PARALLEL, async (name) => {
    const bytes = await fetchBytes(new URL(name, baseUrl).href, `detail tile ${name}`);
    fresh.set(name, bytes);
    fetched += bytes.length;
    stats.bytes_downloaded += bytes.length;
    progress();
  });
  const fetchTextures = () => forEachLimited(textures, FETCH_PARALLEL, async (node) => {
    const bytes = await fetchBytes(new URL(node.file, baseUrl).href, `texture tile ${node.file}`);
    textureBytes += bytes.length;
    stats.bytes_downloaded += bytes.length;
    images.push(await decodeTextureRgb(bytes, node));
    progress();
  });
  progress();
  await Promise.all([fetchTiles(lacking()), fetchTextures()]);
  // the viewer's tile layer may drop a tile meanwhile (the camera moved): fetch until none lacks
  for (let missing = lacking(); missing.length; missing = lacking()) await fetchTiles(missing);
  Object.assign(stats, { ply_progress: [], ply_tiles_fetched: fresh.size, ply_fetch_bytes: fetched,
                         ply_textures: images.length, ply_texture_bytes: textureBytes });
  const tessellating = (fraction) => onProgress(
    `Tessellating level ${choice.level} on a ${choice.resolution} × ` +
    `${choice.resolution} grid with ${plural(total, "detail tile")}` +
    (images.length ? ` and ${plural(images.length, "texture tile")}` : "") +
    `: ${Math.floor(100 * fraction)} %…`);
  tessellating(0);
  // no await since the last check: the worker will hold every name not in `fresh`
  const ply = await worker.plyLevel(choice, fresh, images, (fraction) => {
    stats.ply_progress = [...(stats.ply_progress || []), fraction];
    tessellating(fraction);
  });
  stats.ply_total_ms = performance.now() - t0;
  return ply;
}
