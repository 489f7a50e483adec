// TileLayer: detail and texture tiles superimposed on the base as the camera moves.
//
// After each camera change (debounced) it asks the TileTree for the regions the view needs,
// fetches the tiles they need and nothing else (the worker fetches the `.tsd` files itself,
// decodes and keeps them, and the region requests follow at once behind that request; texture
// images are fetched here and decoded by the browser into three.js textures), has the worker
// tessellate each new region (client_py.tessellate_region
// with the region's tiles, plus skirts hanging behind its inner borders, 2 x its remaining
// error deep, so no crack shows next to a coarser or finer neighbour) and swaps all new
// regions in at once: until then the old regions and the base stay on screen, so no frame
// shows a hole. Regions and tiles no longer needed are disposed (geometries, textures, the
// worker's decoded tiles). Tile URLs are the manifest's file names resolved against the
// manifest's own URL (a bundle is one directory).
//
// Fast zoom (issue 14): the new regions go to the worker in batches of REGION_BATCH, most
// projected error first (then nearest the view's centre), two batches in flight so the worker
// never waits for the page; when the camera moves on before they are done, no further batch
// is sent and the update starts again for the new view (the regions made so far are kept).
// The meshes the worker made are kept (REGION_CACHE of them, least recently used dropped), so
// a region seen again — zooming out and back in, orbiting — is not tessellated again. An
// update that changes nothing on screen draws nothing (a draw costs up to a second under a
// software rasteriser), and an update resolves once its regions are drawn.
//
// Stats (window.tessera.stats): tiles_loaded (tiles held now, detail + texture), tile_bytes
// (bytes of tile files fetched, cumulative), tile_tessellate_ms (Python time of the regions
// the last refinement tessellated: an update that changed the regions shown; 0 when all came
// from the cache), tile_refine_ms (wall time of that refinement, from its start to its
// regions drawn), regions (regions shown), regions_cached (shown from the cache in the last
// refinement), tiles_fetched (cumulative), tile_updates (updates done), tiles_busy (an update
// is running or due), tile_timing (the last refinement's split: select_ms, fetch_ms (tiles
// fetched and handed to the worker), regions_ms (the worker's batches), python_ms, build_ms
// (three.js geometries), swap_ms (swap and draw), total_ms, made, cached, stale (batches
// not sent: the camera moved on), at (performance.now() when drawn)); fetch_ms ends when the
// worker holds the new tiles, and regions_ms is what is left of the worker's batches after it.
//
// A region at a level-k node is tessellated on the tree's regionGrid(k) (tile-tree.js: the
// worker's plan of the manifest, levels[k].region_resolution, client_py's one rule).

import * as THREE from "three";
import { fetchBytes } from "./fetch-bytes.js";
import { TileTree } from "./tile-tree.js";

/** Regions per worker request: large enough that messages cost little, small enough that a
 *  camera moving on wastes little work. */
export const REGION_BATCH = 4;
/** Region meshes kept after they leave the screen (a 33² region with skirts is ~60 KB; the
 *  coarse levels' regions are finer, about 3.7 MB for the default bundle's one 257² level-0
 *  region, so a whole level's regions weigh about the same at every level). */
export const REGION_CACHE = 96;

export class TileLayer {
  /**
   * @param {{viewer: import("./viewer.js").Viewer, worker: import("./mesh-worker-client.js").MeshWorkerClient,
   *          manifest: object, manifestUrl: string, regionGrids: number[]|null, stats: object,
   *          onError: (message: string) => void, onChange?: () => void}} options
   *   regionGrids: vertices per region side at levels 0, 1, .. (the worker's plan:
   *   levels[k].region_resolution)
   */
  constructor({ viewer, worker, manifest, manifestUrl, regionGrids, stats, onError, onChange = () => {} }) {
    this.viewer = viewer;
    this.worker = worker;
    this.tree = new TileTree(manifest.tiles || null, manifest.transform || null, regionGrids || null);
    this.baseUrl = new URL(manifestUrl, window.location.href);
    this.stats = stats;
    this.onError = onError;
    this.onChange = onChange;
    this.detailTiles = new Set(); // file names the worker holds
    this.textures = new Map(); // file name -> THREE.Texture
    this.regions = new Map(); // "k/i/j" -> THREE.Mesh shown (or ready to be)
    this.shownKeys = new Map(); // "k/i/j" -> cache key of the mesh shown
    this.cache = new Map(); // cache key -> the worker's mesh data, least recently used first
    this.running = null;
    this.dirty = false;
    this.failed = false;
    this.timer = null;
    Object.assign(stats, { tiles_loaded: 0, tile_bytes: 0, tile_tessellate_ms: 0,
                           tile_refine_ms: 0, regions: 0, regions_cached: 0, tiles_fetched: 0,
                           tile_updates: 0, tiles_busy: false });
  }

  get enabled() {
    return !this.tree.empty && !this.failed;
  }

  /** Vertices per side of a level-`level` region's grid (TileTree.regionGrid), null without
   *  tiles. */
  regionGrid(level) {
    return this.tree.regionGrid(level);
  }

  /** New base mesh on screen: recompute the nodes' bounding boxes from it. */
  setBase(mesh, domain) {
    if (!this.enabled) return;
    // the refined surface lies within about base.max (the scan's max deviation) of the base
    this.tree.setBounds(mesh.positions, mesh.uvs, domain, this.tree.baseError);
  }

  /** Re-select soon (camera moved); several calls within `delayMs` make one update. */
  schedule(delayMs = 120) {
    if (!this.enabled) return;
    this.stats.tiles_busy = true;
    clearTimeout(this.timer);
    this.timer = setTimeout(() => this.update(), delayMs);
  }

  /** Bring the regions up to date with the camera; resolves when nothing is left to do. */
  async update() {
    if (!this.enabled) return;
    clearTimeout(this.timer);
    this.stats.tiles_busy = true;
    if (this.running) {
      this.dirty = true;
      return this.running;
    }
    this.running = (async () => {
      try {
        do {
          this.dirty = false;
          await this._update();
        } while (this.dirty && !this.failed);
      } catch (error) {
        this.failed = true;
        this.onError(`detail tiles: ${error.message}`);
      } finally {
        this.running = null;
        this.stats.tiles_busy = false;
      }
    })();
    return this.running;
  }

  /** Resolves once no update is running or scheduled. */
  async idle() {
    while (this.stats.tiles_busy && !this.failed) {
      await (this.running || new Promise((resolve) => setTimeout(resolve, 30)));
    }
  }

  async _update() {
    const viewer = this.viewer;
    const t0 = performance.now();
    const leaves = this.tree.select(viewer.camera, viewer.renderer.domElement.height);
    const tSelected = performance.now();
    const wanted = new Map();
    const detailNames = new Set();
    const textureNames = new Set();
    for (const leaf of leaves) {
      const id = `${leaf.level}/${leaf.i}/${leaf.j}`;
      const chain = this.tree.detailChain(leaf.level, leaf.i, leaf.j);
      const texture = this.tree.textureNode(leaf.level, leaf.i, leaf.j);
      const skirtDepth = 2 * this.tree.detailError(leaf.level, leaf.i, leaf.j);
      const names = chain.map((node) => node.file);
      const grid = this.regionGrid(leaf.level);
      const key = `${id}|${grid}|${skirtDepth}|${names.join(",")}`;
      wanted.set(id, { ...leaf, chain, names, skirtDepth, grid, key, texture });
      for (const name of names) detailNames.add(name);
      if (texture) textureNames.add(texture.file);
    }
    const baseTexture = this.tree.textureNode(0, 0, 0);
    if (baseTexture) textureNames.add(baseTexture.file);

    // fetch what is missing, all at once: the detail tiles by the worker itself, off this
    // thread (a draw here, up to a second under a software rasteriser, does not hold them
    // up), the texture images here
    const newDetail = [...detailNames].filter((name) => !this.detailTiles.has(name));
    const newTexture = [...textureNames].filter((name) => !this.textures.has(name));
    const detailFetched = newDetail.length
      ? this.worker.fetchTiles(newDetail.map((name) => ({ name, url: new URL(name, this.baseUrl).href })))
      : Promise.resolve([]);
    const texturesFetched = Promise.all(newTexture.map(async (name) => {
      const texture = await decodeTexture(await this._fetch(name), name);
      this.textures.set(name, texture);
    }));

    // the regions not on screen: from the cache, or made by the worker, most needed first;
    // sent now, behind the tiles they need (the worker runs requests in order)
    const missing = [...wanted.values()].filter((leaf) =>
      this.shownKeys.get(`${leaf.level}/${leaf.i}/${leaf.j}`) !== leaf.key && !this.cache.has(leaf.key));
    const making = this._makeRegions(prioritised(missing));
    making.catch(() => {}); // a tile's own failure below is the one reported
    const [fetchedTiles] = await Promise.all([detailFetched, texturesFetched]);
    for (const tile of fetchedTiles) {
      this.detailTiles.add(tile.name);
      this._count(tile.bytes);
    }
    const tFetched = performance.now();
    const made = await making;
    if (made.stale) return; // the camera moved on: update() runs again for the new view
    const tMade = performance.now();

    const next = new Map();
    const nextKeys = new Map();
    let cached = 0;
    let buildMs = 0;
    for (const [id, leaf] of wanted) {
      let mesh = this.regions.get(id);
      if (!mesh || this.shownKeys.get(id) !== leaf.key) {
        const data = this._cached(leaf.key);
        if (!made.keys.has(leaf.key)) cached += 1;
        const texture = leaf.texture ? this.textures.get(leaf.texture.file) : null;
        const tBuild = performance.now();
        mesh = viewer.makeRegionMesh(data, texture, leaf.texture
          ? TileTree.rect(leaf.texture.level, leaf.texture.i, leaf.texture.j) : null);
        buildMs += performance.now() - tBuild;
      }
      next.set(id, mesh);
      nextKeys.set(id, leaf.key);
    }
    const changed = next.size !== this.regions.size ||
      [...next].some(([id, mesh]) => this.regions.get(id) !== mesh);
    const shownTexture = baseTexture ? this.textures.get(baseTexture.file) : null;
    if (viewer.baseTexture !== shownTexture) viewer.setBaseTexture(shownTexture);
    if (changed) {
      const cells = 2 ** Math.max(this.tree.maxLevel, 0);
      viewer.setRegions(next, { cells, rects: [...wanted.values()].map((l) => TileTree.rect(l.level, l.i, l.j)) });
    }
    this.regions = next;
    this.shownKeys = nextKeys;
    if (changed) await viewer.whenDrawn();
    const tSwapped = performance.now();

    // unload what no region needs any more
    const stale = [...this.detailTiles].filter((name) => !detailNames.has(name));
    if (stale.length) {
      await this.worker.dropTiles(stale);
      for (const name of stale) this.detailTiles.delete(name);
    }
    for (const [name, texture] of this.textures) {
      if (!textureNames.has(name)) {
        texture.dispose();
        this.textures.delete(name);
      }
    }
    const stats = this.stats;
    stats.tiles_loaded = this.detailTiles.size + this.textures.size;
    stats.regions = next.size;
    if (changed) {
      Object.assign(stats, {
        tile_tessellate_ms: made.ms, tile_refine_ms: tSwapped - t0, regions_cached: cached,
        tile_timing: { select_ms: tSelected - t0, fetch_ms: tFetched - tSelected,
                       regions_ms: tMade - tFetched, python_ms: made.ms, build_ms: buildMs,
                       swap_ms: tSwapped - tMade - buildMs, total_ms: tSwapped - t0,
                       made: made.keys.size, cached, stale: 0, at: tSwapped },
      });
    }
    stats.tile_updates += 1;
    this.onChange();
  }

  /**
   * Have the worker tessellate `leaves` (in this order), REGION_BATCH per request with two
   * requests in flight; the meshes go to the cache. Stops sending when the camera has moved
   * on (this.dirty): {stale: true}. Else {stale: false, keys (of the regions made), ms (their
   * Python time)}.
   */
  async _makeRegions(leaves) {
    const batches = [];
    for (let k = 0; k < leaves.length; k += REGION_BATCH) batches.push(leaves.slice(k, k + REGION_BATCH));
    const keys = new Set();
    let ms = 0;
    const send = (batch) => this.worker.regionBatch(batch.map((leaf) => ({
      level: leaf.level, i: leaf.i, j: leaf.j, grid: leaf.grid, names: leaf.names,
      skirtDepth: leaf.skirtDepth })));
    let inFlight = batches.length ? send(batches[0]) : null;
    for (let b = 0; b < batches.length; b++) {
      const following = b + 1 < batches.length && !this.dirty ? send(batches[b + 1]) : null;
      // awaited next round, unless this batch fails first: then its failure is the one reported
      if (following) following.catch(() => {});
      const meshes = await inFlight;
      batches[b].forEach((leaf, n) => {
        this._remember(leaf.key, meshes[n]);
        keys.add(leaf.key);
        ms += meshes[n].tessellate_ms;
      });
      if (!following) {
        if (b + 1 < batches.length) return { stale: true };
        break;
      }
      inFlight = following;
    }
    return { stale: false, keys, ms };
  }

  _remember(key, data) {
    this.cache.delete(key);
    this.cache.set(key, data);
    while (this.cache.size > REGION_CACHE) this.cache.delete(this.cache.keys().next().value);
  }

  _cached(key) {
    const data = this.cache.get(key);
    this._remember(key, data); // most recently used
    return data;
  }

  async _fetch(name) {
    const bytes = await fetchBytes(new URL(name, this.baseUrl).href, name);
    this._count(bytes.length);
    return bytes;
  }

  /** One tile file of `bytes` bytes fetched (here or by the worker). */
  _count(bytes) {
    this.stats.tile_bytes += bytes;
    this.stats.bytes_downloaded += bytes;
    this.stats.tiles_fetched += 1;
  }
}

/** `leaves` most projected error first, then nearest the centre of the view (normalised device
 *  coordinates of their boxes' centres): the order the worker makes them in. */
function prioritised(leaves) {
  return [...leaves].sort((a, b) => (b.sse - a.sse) || (a.centre - b.centre));
}

/** A texture tile's image as a three.js texture (uv channel 1, rows flipped at decode so
 *  t = 0 is the image's bottom row, v up as docs/format.md specifies). */
async function decodeTexture(bytes, name) {
  let bitmap;
  try {
    bitmap = await createImageBitmap(new Blob([bytes]), { imageOrientation: "flipY" });
  } catch (error) {
    throw new Error(`texture tile ${name} is not a decodable image: ${error.message}`);
  }
  const texture = new THREE.Texture(bitmap);
  texture.flipY = false; // ignored for ImageBitmap: flipped above
  texture.colorSpace = THREE.SRGBColorSpace;
  texture.channel = 1;
  texture.needsUpdate = true;
  return texture;
}
