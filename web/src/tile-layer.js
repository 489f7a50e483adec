// TileLayer: detail and texture tiles superimposed on the base as the camera moves.
//
// After each camera change (debounced) it asks the TileTree for the regions the view needs,
// fetches the tiles they need and nothing else (`.tsd` bytes go to the worker, which decodes
// and keeps them; texture images are decoded by the browser into three.js textures), has the
// worker tessellate each new region (client_py.tessellate_region with the region's tiles,
// plus skirts hanging behind its inner borders, 2 x its remaining error deep, so no crack
// shows next to a coarser or finer neighbour) and swaps all new regions in at once: until then the old regions and the base
// stay on screen, so no frame shows a hole. Regions and tiles no longer needed are disposed
// (geometries, textures, the worker's decoded tiles). Tile URLs are the manifest's file names
// resolved against the manifest's own URL (a bundle is one directory).
//
// Stats (window.tessera.stats): tiles_loaded (tiles held now, detail + texture), tile_bytes
// (bytes of tile files fetched, cumulative), tile_tessellate_ms (Python time of the regions
// the last update tessellated), regions (regions shown), tiles_fetched (cumulative),
// tile_updates (updates done), tiles_busy (an update is running or due).
//
// Each region is tessellated on the tree's regionGrid (R = 2 spans_per_tile + 1, tile-tree.js).

import * as THREE from "three";
import { fetchBytes } from "./fetch-bytes.js";
import { TileTree } from "./tile-tree.js";

export class TileLayer {
  /**
   * @param {{viewer: import("./viewer.js").Viewer, worker: import("./mesh-worker-client.js").MeshWorkerClient,
   *          manifest: object, manifestUrl: string, stats: object, onError: (message: string) => void,
   *          onChange?: () => void}} options
   */
  constructor({ viewer, worker, manifest, manifestUrl, stats, onError, onChange = () => {} }) {
    this.viewer = viewer;
    this.worker = worker;
    this.tree = new TileTree(manifest.tiles || null, manifest.transform || null);
    this.baseUrl = new URL(manifestUrl, window.location.href);
    this.stats = stats;
    this.onError = onError;
    this.onChange = onChange;
    this.detailTiles = new Set(); // file names the worker holds
    this.textures = new Map(); // file name -> THREE.Texture
    this.regions = new Map(); // "k/i/j" -> THREE.Mesh shown (or ready to be)
    this.running = null;
    this.dirty = false;
    this.failed = false;
    this.timer = null;
    Object.assign(stats, { tiles_loaded: 0, tile_bytes: 0, tile_tessellate_ms: 0, regions: 0,
                           tiles_fetched: 0, tile_updates: 0, tiles_busy: false });
  }

  get enabled() {
    return !this.tree.empty && !this.failed;
  }

  /** Vertices per side of every region's grid (TileTree.regionGrid), null without tiles. */
  get regionGrid() {
    return this.tree.regionGrid;
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
    const leaves = this.tree.select(viewer.camera, viewer.renderer.domElement.height);
    const wanted = new Map();
    const detailNames = new Set();
    const textureNames = new Set();
    for (const leaf of leaves) {
      const id = `${leaf.level}/${leaf.i}/${leaf.j}`;
      const chain = this.tree.detailChain(leaf.level, leaf.i, leaf.j);
      const texture = this.tree.textureNode(leaf.level, leaf.i, leaf.j);
      wanted.set(id, { ...leaf, chain, texture });
      for (const node of chain) detailNames.add(node.file);
      if (texture) textureNames.add(texture.file);
    }
    const baseTexture = this.tree.textureNode(0, 0, 0);
    if (baseTexture) textureNames.add(baseTexture.file);

    // fetch what is missing, all at once; decode detail tiles in the worker (in order)
    const newDetail = [...detailNames].filter((name) => !this.detailTiles.has(name));
    const newTexture = [...textureNames].filter((name) => !this.textures.has(name));
    const [detailBytes, textureImages] = await Promise.all([
      Promise.all(newDetail.map((name) => this._fetch(name))),
      Promise.all(newTexture.map((name) => this._fetch(name).then((bytes) => decodeTexture(bytes, name)))),
    ]);
    for (let n = 0; n < newDetail.length; n++) {
      await this.worker.addTile(newDetail[n], detailBytes[n]);
      this.detailTiles.add(newDetail[n]);
    }
    newTexture.forEach((name, n) => this.textures.set(name, textureImages[n]));

    // tessellate the new regions; the old ones stay on screen meanwhile
    let ms = 0;
    let made = 0;
    const next = new Map();
    for (const [id, leaf] of wanted) {
      let mesh = this.regions.get(id);
      if (!mesh) {
        const data = await this.worker.region(leaf.level, leaf.i, leaf.j, this.regionGrid,
                                              leaf.chain.map((node) => node.file),
                                              2 * this.tree.detailError(leaf.level, leaf.i, leaf.j));
        ms += data.tessellate_ms;
        made += 1;
        const texture = leaf.texture ? this.textures.get(leaf.texture.file) : null;
        mesh = viewer.makeRegionMesh(data, texture,
                                     leaf.texture ? TileTree.rect(leaf.texture.level, leaf.texture.i, leaf.texture.j) : null);
      }
      next.set(id, mesh);
    }
    const cells = 2 ** Math.max(this.tree.maxLevel, 0);
    viewer.setBaseTexture(baseTexture ? this.textures.get(baseTexture.file) : null);
    viewer.setRegions(next, { cells, rects: [...wanted.values()].map((l) => TileTree.rect(l.level, l.i, l.j)) });
    this.regions = next;

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
    if (made) stats.tile_tessellate_ms = ms;
    stats.tile_updates += 1;
    this.onChange();
  }

  async _fetch(name) {
    const bytes = await fetchBytes(new URL(name, this.baseUrl).href, name);
    this.stats.tile_bytes += bytes.length;
    this.stats.bytes_downloaded += bytes.length;
    this.stats.tiles_fetched += 1;
    return bytes;
  }
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
