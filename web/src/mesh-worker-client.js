// MeshWorkerClient: the page's handle on mesh-worker.js — promises in, typed arrays out.
//
// Owns the Worker, turns its messages into promises, reports progress stages, and
// enforces the Pyodide load timeout: a runtime that never answers (a wrong MIME
// type makes loadPyodide hang silently) becomes a visible error, not a spinner forever.

export class MeshWorkerClient {
  /**
   * @param {string} workerUrl  URL of mesh-worker.js (from the server's page config)
   * @param {{onStage?: (stage: string, detail: object) => void,
   *          onProgress?: (loaded: number, total: number) => void}} [options]
   *   onProgress: runtime bytes fetched so far by the worker of the total it expects
   */
  constructor(workerUrl, { onStage = () => {}, onProgress = () => {} } = {}) {
    this.onStage = onStage;
    this.onProgress = onProgress;
    this.nextId = 1;
    this.pending = new Map();
    // Detail tiles the worker will hold once it has handled every request posted so far
    // (updated when a "tile"/"drop" request is posted: the worker runs requests in order).
    this.held = new Set();
    this.packs = new Set(); // of those, an atlas's detail packs (addPack)
    this.colourPacks = new Set(); // an atlas's decoded colour packs the worker holds
    // called with the worker's Resource Timing entries when it fetched something (fetchTiles)
    this.onResources = () => {};
    this.worker = new Worker(workerUrl, { type: "module", name: "tessera-mesh-worker" });
    this.worker.onmessage = (event) => this._receive(event.data);
    this.worker.onerror = (event) => {
      event.preventDefault();
      this._failAll(`the mesh worker failed to start: ${event.message || "script error"}`);
    };
    this.worker.onmessageerror = () => this._failAll("the mesh worker sent an unreadable message");
  }

  /**
   * Load Pyodide, client_py and the patch. Resolves with the worker's "ready" message.
   * @param {{pyodideUrl: string, clientPyUrl: string, patchUrl: string}} urls
   * @param {number} timeoutS  seconds allowed for the Pyodide runtime to load
   */
  init(urls, timeoutS) {
    return new Promise((resolve, reject) => {
      const timer = setTimeout(() => {
        this.worker.terminate();
        reject(new Error(`the Python runtime (Pyodide) did not load within ${timeoutS} s; ` +
                         "check that the server sends .wasm as application/wasm"));
      }, timeoutS * 1000);
      this.pending.set(0, {
        resolve: (message) => { clearTimeout(timer); resolve(message); },
        reject: (error) => { clearTimeout(timer); reject(error); },
        runtimeLoaded: () => clearTimeout(timer),
      });
      this.worker.postMessage({ type: "init", ...urls });
    });
  }

  /** The worker's fetches so far, [{name, transferSize, encodedBodySize, decodedBodySize}]
   *  (its own Resource Timing entries: the page's timeline does not hold them). */
  async resources() {
    return (await this._request({ type: "resources" })).resources;
  }

  /** Tessellate on a resolution x resolution grid: {positions, normals, uvs, indices, tessellate_ms}. */
  tessellate(resolution) {
    return this._request({ type: "tessellate", resolution });
  }

  /** PLY bytes written by client_py.write_ply; `colors` an optional Uint8Array of RGB per vertex. */
  ply(resolution, colors = null) {
    return this._request({ type: "ply", resolution, colors }, colors ? [colors.buffer] : []);
  }

  /** The PLY levels the bundle offers (the worker keeps the manifest for plyLevel): resolves
   *  with {levels, max_resolution, spans_per_tile}, one entry of levels per detail level,
   *  {level, rms, detail_files, detail_bytes, texture_nodes, texture_bytes, resolution,
   *  region_resolution} (client_py.bundle.plan_level: the detail tiles of levels 0..L, the
   *  texture nodes its vertex colours come from, its grid over the whole object and that of
   *  a viewer's region at a level-L node, client_py.bundle.drawn_level_resolution and
   *  drawn_region_resolution);
   *  a malformed manifest rejects with the reason. */
  plan(manifest) {
    return this._request({ type: "plan", manifest: JSON.stringify(manifest) });
  }

  /** A patch bundle's detached pieces (after plan(): the manifest's pieces.file, fetched by
   *  the worker from `url` and kept for the PLYs): resolves with their mesh {positions,
   *  normals, uvs, indices, bytes, resources, tessellate_ms} in the scan frame. */
  async pieces(url) {
    const reply = await this._request({ type: "pieces", url });
    this.onResources(reply.resources); // the fetch counts in the visit's transfers
    return reply;
  }

  /** PLY of the whole patch at detail level choice.level (an entry of plan().levels), on its
   *  grid, as `tessera tessellate BUNDLE --level L` writes it: its detail_files that the
   *  worker holds (see holds()) are used as they are, the others must be in `fresh` (a Map
   *  name -> bytes, transferred). `textures`: its texture_nodes decoded, {level, i, j, width,
   *  height, rgb} (rgb a Uint8Array of rows top to bottom, transferred; see page.js
   *  decodeTextureRgb). Resolves with {bytes, vertices, triangles, resolution, write_ms}.
   *  Tiles the worker does not hold at the moment of the call and `fresh` lacks reject at
   *  once (the caller fetches them). `onProgress(fraction)`: the share of an atlas's
   *  tessellation done, as the worker reports it. */
  plyLevel(choice, fresh = new Map(), textures = [], onProgress = () => {}) {
    const missing = choice.detail_files.filter((name) => !this.held.has(name) && !fresh.has(name));
    if (missing.length) {
      return Promise.reject(new Error(`detail tiles not fetched: ${missing.join(", ")}`));
    }
    const sent = [...fresh].map(([name, bytes]) => ({ name, bytes }));
    const images = textures.map(({ level: k, i, j, file, width, height, rgb }) =>
      ({ level: k, i, j, file, width, height, rgb }));
    return this._request({ type: "ply", level: choice.level, fresh: sent, textures: images },
                         [...sent.map((tile) => tile.bytes.buffer),
                          ...images.map((image) => image.rgb.buffer)], onProgress);
  }

  /** Whether the worker will hold detail tile `name` when it reaches the next request. */
  holds(name) {
    return this.held.has(name);
  }

  /** Hand a detail tile's bytes (a bundle's `.tsd` file `name`) to the worker, which decodes
   *  and keeps it: resolves with {name, level, i, j}; a bad file rejects with its reason. */
  addTile(name, bytes) {
    const copy = bytes.slice(); // the caller keeps its bytes (the copy is transferred)
    this.held.add(name);
    return this._request({ type: "tile", name, bytes: copy }, [copy.buffer]).catch((error) => {
      this.held.delete(name); // not decoded: not kept
      throw error;
    });
  }

  /** Have the worker fetch detail tiles itself ([{name, url}]: a bundle's `.tsd` files) and
   *  keep each decoded, off the page's thread: resolves with [{name, bytes, level, i, j}]; a
   *  tile that cannot be fetched or decoded rejects with its reason. The worker's Resource
   *  Timing entries then go to `onResources(entries)`. Requests sent after this one find the
   *  tiles held. */
  fetchTiles(tiles) {
    for (const { name } of tiles) this.held.add(name);
    return this._request({ type: "fetchTiles", tiles }).then((reply) => {
      this.onResources(reply.resources);
      return reply.tiles;
    }, (error) => {
      for (const { name } of tiles) this.held.delete(name);
      throw error;
    });
  }

  /** Forget tiles the worker holds (names as given to addTile or fetchTiles). */
  dropTiles(names) {
    for (const name of names) this.held.delete(name);
    return this._request({ type: "drop", names });
  }

  /** Mesh of quadtree node (level, i, j) with the named tiles applied, grid x grid vertices
   *  plus skirts hanging `skirtDepth` (scan units) below the lowest coarser level, in the scan
   *  frame: {positions, normals, uvs, indices, tessellate_ms}. */
  region(level, i, j, grid, names, skirtDepth) {
    return this._request({ type: "region", level, i, j, grid, names, skirtDepth });
  }

  /** Meshes of several quadtree nodes, as region() makes each, in one request: `regions`
   *  = [{level, i, j, grid, names, skirtDepth}]; resolves with their meshes in that order. */
  async regionBatch(regions) {
    return (await this._request({ type: "regions", regions })).meshes;
  }

  /** An atlas bundle's refinement table (after plan()): {groups: [{first, count, center,
   *  radius, packs, bytes, errors}], base_error, levels, resolutions}
   *  (client_py.session.WorkerSession.atlas_refinement). */
  atlasRefinement() {
    return this._request({ type: "atlasRefinement" });
  }

  /** Hand an atlas detail pack (`detail/K/G.tsdp` of the manifest) to the worker, which
   *  decodes and keeps it: resolves with {name, level, group, tiles}; a bad pack rejects. */
  addPack(name, bytes) {
    const copy = bytes.slice();
    this.held.add(name);
    this.packs.add(name);
    return this._request({ type: "pack", name, bytes: copy }, [copy.buffer]).catch((error) => {
      this.held.delete(name);
      this.packs.delete(name);
      throw error;
    });
  }

  /** The packs the worker will hold (names as given to addPack). */
  heldPacks() {
    return new Set(this.packs);
  }

  /** Forget packs the worker holds. */
  dropPacks(names) {
    for (const name of names) {
      this.held.delete(name);
      this.packs.delete(name);
    }
    return this._request({ type: "dropPacks", names });
  }

  /** An atlas bundle's colour (after plan()), or null without colour: {levels, texel,
   *  group_packs, packs} (client_py.session.WorkerSession.atlas_colour_refinement). */
  async atlasColour() {
    return (await this._request({ type: "atlasColour" })).colour;
  }

  /** Hand a decoded colour pack (`texture/C/G.webp` of the manifest: {width, height, rgb},
   *  rgb transferred) to the worker, which keeps it for the vertex colours of atlasMesh
   *  and atlasParts. */
  addColourPack(name, { width, height, rgb }) {
    this.colourPacks.add(name);
    return this._request({ type: "colourPack", name, width, height, rgb }, [rgb.buffer])
      .catch((error) => {
        this.colourPacks.delete(name);
        throw error;
      });
  }

  /** Colour the atlas meshes made from now on by its error map (`bytes`: the bundle's
   *  error_raster.bin, `palette`: 768 bytes, RGB of each code), or by the colour packs again
   *  (`bytes` null). */
  setErrorMap(bytes, palette = null) {
    return this._request({ type: "errorMap", bytes, palette });
  }

  /** Forget colour packs the worker holds. */
  dropColourPacks(names) {
    for (const name of names) this.colourPacks.delete(name);
    return this._request({ type: "dropColourPacks", names });
  }

  /** The whole atlas as one welded mesh, group g at detail level levels[g] (-1: the base):
   *  {positions, normals, uvs, indices, colors, tessellate_ms} (colors: RGB per vertex when
   *  the worker holds every group's colour pack, else null). */
  atlasMesh(levels) {
    return this._request({ type: "atlasMesh", levels });
  }

  /** Meshes of the atlas's `groups` with group g at detail level levels[g] (-1: the base):
   *  resolves with [{group, level, positions, normals, uvs, indices, colors, tessellate_ms}]
   *  in that order (WorkerSession.atlas_part_meshes: each group's triangles of
   *  atlasMesh(levels), so groups made at one level vector meet without a crack; a group's
   *  mesh depends on its own and its neighbours' levels; colors as atlasMesh's, from the
   *  colour packs the worker holds). */
  async atlasParts(levels, groups) {
    return (await this._request({ type: "atlasParts", levels, groups })).meshes;
  }

  terminate() {
    this.worker.terminate();
    this._failAll("the mesh worker was stopped");
  }

  _request(message, transfer = [], onProgress = null) {
    const id = this.nextId++;
    return new Promise((resolve, reject) => {
      this.pending.set(id, { resolve, reject, onProgress });
      this.worker.postMessage({ ...message, id }, transfer);
    });
  }

  _receive(message) {
    if (message.type === "plyProgress") {
      this.pending.get(message.id)?.onProgress?.(message.fraction);
      return;
    }
    if (message.type === "progress") {
      this.onProgress(message.loaded, message.total);
      return;
    }
    if (message.type === "stage") {
      if (message.stage !== "runtime") this.pending.get(0)?.runtimeLoaded?.();
      this.onStage(message.stage, message);
      return;
    }
    const id = message.type === "ready" || (message.type === "error" && message.id === undefined)
      ? 0 : message.id;
    const entry = this.pending.get(id);
    if (!entry) return;
    this.pending.delete(id);
    if (message.type === "error") {
      const error = new Error(message.message);
      error.stage = message.stage;
      entry.reject(error);
    } else {
      entry.resolve(message);
    }
  }

  _failAll(text) {
    for (const entry of this.pending.values()) entry.reject(new Error(text));
    this.pending.clear();
  }
}
