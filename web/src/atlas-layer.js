// AtlasLayer: an atlas bundle (manifest format_version 2) on screen — one mesh per GROUP of
// patches, each drawn at its own detail level, chosen by screen-space error as in OGC 3D
// Tiles (docs/format.md, "Bundle manifest, version 2 (atlas)").
//
// The worker's refinement table (WorkerSession.atlas_refinement, from the manifest) gives per
// group its bounding sphere (scan frame) and, per level k, its pack (detail/K/G.tsdp, or null:
// no tiles there) and geometric_error (the largest distance of its scan points after levels
// 0..k); the base's error is tiles.detail.base.max. With d the distance from the camera to the
// group's sphere (clamped to the near plane) and f = H / (2 tan(fov / 2)) the focal length in
// device pixels, a group's projected error at level k is
//
//     sse = error_k * f / d                                              (pixels)
//
// and a group inside the view frustum is refined one level at a time while sse > DETAIL_PX;
// groups outside it go back to the base. Refinements are granted largest sse first within a
// budget of MAX_VERTICES drawn vertices: a group inside the frustum at level k costs
// count * R_k^2 (R_k the worker's samples per patch side at that level), a group outside it
// nothing (three.js culls its mesh: it is not drawn). The fitter keeps a group's finest
// mesh within a quarter of the budget (fitter.fitting.atlas.detail.GROUP_VERTICES, 250,000)
// and its patches within 256, so that a close view refines the part of the object it
// shows. (Counting every group's base, Stanford Lucy's 2,268 patches at 9 x 9 samples took
// 184 k of a 250 k budget, and no group of hers could ever be refined.)
//
// Only what changed is tessellated: a group's mesh (WorkerSession.atlas_part_meshes, one
// request for all the groups a batch needs) is its triangles of the whole atlas welded at
// the current levels, bit for bit (client_py.atlas_mesh.tessellate_atlas_parts: the welded
// mesh's rules are local, so the group's patches and the ring of patches around them
// decide it), so the groups meet without a crack or a wall. It depends on the levels of the
// group and of its neighbours (refinement.groups[g].neighbours: the groups of that ring), so
// a change of one group's level re-makes it and its neighbours; the meshes made are kept
// under the key of those levels (least recently used dropped beyond CACHE_VERTICES), so going
// back to levels seen before tessellates nothing. The packs of the groups to make and of
// their neighbours are needed. The packs a choice needs are fetched (at most
// FETCH_PARALLEL at once), handed to the worker (MeshWorkerClient.addPack) and those no
// longer needed dropped; the changed groups are swapped in in one frame. A refinement goes
// in two batches (batches()): the groups with the largest projected error first, about
// BATCH_VERTICES vertices to tessellate, then the rest; each is a choice within the
// budget, welded, and drawn when made, so the nearest detail shows before the whole view's
// (the Bali mask seen whole: 16 groups, 9 s of Python). The first frame is
// the whole atlas at the base welded in one mesh (Viewer.setMesh: it frames the view); right
// after it the worker makes every group's base mesh in the background, and the first
// refinement puts the groups in its place.
//
// Colour (a bundle with tiles.texture; WorkerSession.atlas_colour_refinement): a group drawn at
// level k is coloured per vertex from the colour pack (texture/C/G.webp) of colour level
// c = min(max(k, 0), C - 1), whose cells have as many texels per patch side as level c's mesh
// has cells (client_py.atlas_texture). As the single patch's texture tiles (tile-tree.js), a
// group is also refined while its texels look larger than TEXEL_PX on screen,
// texel_k * f / d > TEXEL_PX (texel_k: the world size of a texel at level k, median patch),
// and a finer colour level exists. Before the worker makes meshes (the welded first frame, or
// the groups not kept), the colour packs of those groups at their levels are fetched, decoded
// to RGB (page.js decodeTextureRgb) and handed to the worker (addColourPack), those no longer
// needed dropped (a group's mesh needs those of its neighbours too: a seam vertex takes the
// colour of the first patch that samples it, as in the welded mesh); the worker's meshes then
// carry RGB per vertex (one rule for the welded mesh and a group's:
// WorkerSession._colour_groups), shown through three.js vertex colours (converted from sRGB to
// linear, as the renderer expects). A kept group mesh is keyed by its group, the levels it
// depends on and its colour pack, so it is never shown with other colours than it was made
// with.
//
// Stats (window.tessera.stats): atlas_levels (per group), atlas_refined_groups,
// atlas_packs_loaded, atlas_pack_bytes, atlas_tessellate_ms (Python time of the groups the
// last update tessellated), atlas_parts_made and atlas_parts_cached (that update's groups
// tessellated and taken from the cache), atlas_refine_ms (its wall time, from the choice to
// the swap drawn), atlas_batches, atlas_first_batch_ms and atlas_update_python_ms (the last
// update's batches (0: nothing to change), the time from its start to its first batch
// drawn, the Python time of all its batches; an update that plans again because the camera
// moved counts all its passes), atlas_updates, vertices, triangles, tessellate_ms,
// atlas_colour_packs_loaded, atlas_colour_bytes.

import * as THREE from "three";

import { fetchBytes } from "./fetch-bytes.js";
import { decodeTextureRgb, forEachLimited } from "./page.js";
import { DETAIL_PX, TEXEL_PX } from "./tile-tree.js";

export const MAX_VERTICES = 1000000;
/** Vertices of the group meshes kept off screen (about 32 bytes each with their triangles). */
export const CACHE_VERTICES = 1000000;
const FETCH_PARALLEL = 6;
/** Vertices tessellated in a refinement's first batch (batches()): about a second of the
 *  worker's pure-Python kernel in Pyodide (60-135 k vertices a second with detail and without). */
export const BATCH_VERTICES = 100000;
const SETTLE_MS = 200;
/** sRGB byte -> linear intensity (IEC 61966-2-1), for three.js vertex colours. */
const SRGB_TO_LINEAR = Float32Array.from({ length: 256 }, (_, k) => {
  const c = k / 255;
  return c <= 0.04045 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4;
});

export class AtlasLayer {
  /**
   * @param {{viewer: import("./viewer.js").Viewer,
   *          worker: import("./mesh-worker-client.js").MeshWorkerClient,
   *          refinement: {groups: object[], base_error: number|null, levels: number,
   *                       resolutions: number[]},
   *          manifestUrl: string, stats: object, onError: (message: string) => void,
   *          onChange: () => void}} options
   */
  constructor({ viewer, worker, refinement, manifestUrl, stats, onError = () => {},
                onChange = () => {} }) {
    this.viewer = viewer;
    this.worker = worker;
    this.groups = refinement.groups;
    this.baseError = refinement.base_error;
    this.levelCount = refinement.levels;
    this.resolutions = refinement.resolutions; // samples per patch side at levels -1, 0, ..
    this.baseUrl = new URL(manifestUrl, window.location.href);
    this.stats = stats;
    this.onError = onError;
    this.onChange = onChange;
    this.shown = this.groups.map(() => -1); // the level of each group on screen
    this.cache = new Map(); // partKey -> the worker's mesh of that group, least recently used first
    this.baseParts = null; // the request for every group's base mesh (after the first frame)
    this.timer = null;
    this.running = null; // the update in progress, or null
    this.again = false; // the camera moved during an update: run once more after it
    this.colour = undefined; // WorkerSession.atlas_colour_refinement, read at the first show
    this.errorShown = false; // the worker colours the meshes by the error map (showErrorMap)
    this.errorBytes = null; // the bundle's error_raster.bin, fetched at the first showErrorMap
    Object.assign(stats, { atlas_levels: [...this.shown], atlas_refined_groups: 0,
                           atlas_packs_loaded: 0, atlas_pack_bytes: 0, atlas_tessellate_ms: 0,
                           atlas_parts_made: 0, atlas_parts_cached: 0, atlas_refine_ms: 0,
                           atlas_updates: 0, atlas_colour_packs_loaded: 0,
                           atlas_colour_bytes: 0 });
  }

  /** Whether the bundle has detail to refine with. */
  get enabled() {
    return this.levelCount > 0 && this.groups.length > 0;
  }

  /** Every group at `levels` on screen: the groups whose mesh at that level is neither
   *  shown nor kept are tessellated by the worker (one request), then the changed groups
   *  are swapped in at once. Resolves with the stats. */
  async show(levels) {
    const t0 = performance.now();
    if (this.viewer.mesh === null) return this._showFirst(levels);
    await this.baseParts; // the base of every group, asked for after the first frame
    const wanted = levels.map((_, g) => this.partKey(g, levels));
    const missing = levels.map((_, g) => g).filter((g) => !this.cache.has(wanted[g]));
    if (!this.errorShown) { // the error map's colours are the worker's already
      await this.bringColours([...this.withNeighbours(missing)].map((g) => [g, levels[g]]));
    }
    const meshes = missing.length ? await this.worker.atlasParts(levels, missing) : [];
    let pythonMs = 0;
    for (const mesh of meshes) {
      pythonMs += mesh.tessellate_ms;
      this._rememberMade(mesh, levels);
    }
    const parts = wanted.map((key) => this._cached(key));
    this.viewer.setAtlasParts(new Map(wanted.map((key, g) => [key, parts[g]])));
    useVertexColours(this.viewer.regionMaterial, parts.every((part) => part.colors));
    this.shown = [...levels];
    this._trimCache(new Set(wanted));
    const vertices = parts.reduce((sum, part) => sum + part.positions.length / 3, 0);
    const triangles = parts.reduce((sum, part) => sum + part.indices.length / 3, 0);
    Object.assign(this.stats, {
      vertices, triangles, tessellate_ms: pythonMs, atlas_tessellate_ms: pythonMs,
      atlas_parts_made: meshes.length, atlas_parts_cached: levels.length - meshes.length,
      round_trip_ms: performance.now() - t0, atlas_levels: [...levels],
      atlas_refined_groups: levels.filter((k) => k >= 0).length,
      meshes: (this.stats.meshes || 0) + 1,
    });
    await this.viewer.whenDrawn();
    this.stats.atlas_refine_ms = performance.now() - t0;
    return { ...this.stats };
  }

  /** The first frame: the whole atlas welded at `levels` in one mesh (WorkerSession.atlas_mesh:
   *  as fast as one group mesh per group, and Viewer.setMesh frames the view by it); then, in
   *  the background, every group's base mesh, which the first refinement shows beside the
   *  groups it refines. */
  async _showFirst(levels) {
    const t0 = performance.now();
    await this.bringColours(levels.map((level, g) => [g, level]));
    const mesh = await this.worker.atlasMesh(levels);
    this.viewer.setMesh(mesh, [0, 1, 0, 1]);
    this.showColours(mesh.colors);
    this.shown = [...levels];
    Object.assign(this.stats, {
      vertices: mesh.positions.length / 3, triangles: mesh.indices.length / 3,
      tessellate_ms: mesh.tessellate_ms, atlas_tessellate_ms: mesh.tessellate_ms,
      round_trip_ms: performance.now() - t0, atlas_levels: [...levels],
      atlas_refined_groups: levels.filter((k) => k >= 0).length,
      meshes: (this.stats.meshes || 0) + 1,
    });
    if (this.enabled) {
      const base = this.groups.map(() => -1);
      this.baseParts = this.worker.atlasParts(base, base.map((_, g) => g)).then(
        (meshes) => meshes.forEach((part) => this._rememberMade(part, base)),
        (error) => this.onError(`atlas groups: ${error.message}`));
    }
    return { ...this.stats };
  }

  /** The cache's key of group `g`'s mesh with every group h at levels[h]: its level, its
   *  neighbours' (what its mesh depends on) and the colour pack it is coloured from (what
   *  changes its colours; `coloured` false: none; "error map" while it is shown), so a kept
   *  mesh is never shown with other seams or stale colour. */
  partKey(g, levels, coloured = true) {
    const around = this.groups[g].neighbours.map((h) => levels[h]).join(",");
    if (this.errorShown) return `${g}/${levels[g]}/error map/${around}`;
    const pack = this.colour && coloured ? this.colour.group_packs[g][levels[g] + 1] : "";
    return `${g}/${levels[g]}/${pack}/${around}`;
  }

  /** `groups` and their neighbours (a Set). */
  withNeighbours(groups) {
    return new Set(groups.flatMap((g) => [g, ...this.groups[g].neighbours]));
  }

  /** Keep a group mesh the worker made at `levels`, its colours made linear (showColours'
   *  rule), under the key of the colours it carries: one made while its colour packs were
   *  not held (none) is not taken for a coloured one. */
  _rememberMade(mesh, levels) {
    const key = this.partKey(mesh.group, levels, Boolean(mesh.colors));
    mesh.colors = mesh.colors && linearColours(mesh.colors);
    this._remember(key, mesh);
  }

  _remember(key, mesh) {
    this.cache.delete(key);
    this.cache.set(key, mesh);
  }

  _cached(key) {
    const mesh = this.cache.get(key);
    if (!mesh) {
      throw new Error(`the worker made no mesh ${key} (group/level/colour pack/neighbours' levels)`);
    }
    this._remember(key, mesh); // most recently used
    return mesh;
  }

  /** Drop the least recently used meshes not on screen beyond CACHE_VERTICES. */
  _trimCache(shown) {
    let kept = 0;
    for (const [key, mesh] of [...this.cache].reverse()) {
      if (shown.has(key)) continue;
      kept += mesh.positions.length / 3;
      if (kept > CACHE_VERTICES) this.cache.delete(key);
    }
  }

  /** The error of group `g` at `level` (-1: the base's): its pack's geometric_error, or for
   *  a level without a pack the nearest coarser one's (no tiles: nothing changed). */
  error(g, level) {
    for (let k = level; k >= 0; k--) {
      const e = this.groups[g].errors[k];
      if (e !== null && e !== undefined) return e;
    }
    return this.baseError ?? Infinity;
  }

  /** The level each group should be drawn at for the current camera (module comment);
   *  `steps` gets the groups in the order their levels were raised, one entry a level
   *  (largest projected error first: batches()). */
  wanted(steps = []) {
    const camera = this.viewer.camera;
    camera.updateMatrixWorld();
    const frustum = new THREE.Frustum().setFromProjectionMatrix(
      new THREE.Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse));
    const focal = this.viewer.renderer.domElement.height /
      (2 * Math.tan(THREE.MathUtils.degToRad(camera.fov) / 2));
    const levels = this.groups.map(() => -1);
    const cost = (g, k) => this.groups[g].count * this.resolutions[k + 1] ** 2;
    const distance = this.groups.map((group) => {
      const sphere = new THREE.Sphere(new THREE.Vector3(...group.center), group.radius);
      if (!frustum.intersectsSphere(sphere)) return null;
      return Math.max(camera.position.distanceTo(sphere.center) - sphere.radius, camera.near);
    });
    let total = this.groups.reduce((sum, _, g) => sum + (distance[g] === null ? 0 : cost(g, -1)), 0);
    for (;;) {
      let best = -1, bestSse = DETAIL_PX;
      for (let g = 0; g < this.groups.length; g++) {
        if (distance[g] === null || levels[g] + 1 >= this.levelCount) continue;
        const sse = Math.max(this.error(g, levels[g]),
                             this.texelError(levels[g]) * DETAIL_PX / TEXEL_PX) * focal / distance[g];
        if (sse > bestSse && total - cost(g, levels[g]) + cost(g, levels[g] + 1) <= MAX_VERTICES) {
          best = g;
          bestSse = sse;
        }
      }
      if (best < 0) return levels;
      total += cost(best, levels[best] + 1) - cost(best, levels[best]);
      levels[best] += 1;
      steps.push(best);
    }
  }

  /** The world size of a texel drawn with a group at `level` when a finer colour level would
   *  show more (0 otherwise, or without colour): refining shows finer colour. */
  texelError(level) {
    const colour = this.colour;
    if (!colour) return 0;
    const c = Math.min(Math.max(level, 0), colour.levels - 1);
    const next = Math.min(Math.max(level + 1, 0), colour.levels - 1);
    return next > c ? colour.texel[level + 1] : 0;
  }

  /** Fetch, decode and hand the worker the colour packs of `parts` = [[group, level], ...]
   *  (the groups of the meshes it is to make and their neighbours: WorkerSession
   *  atlas_colour_refinement's group_packs), and drop the others it holds (a kept mesh has
   *  its colours). */
  async bringColours(parts) {
    if (this.colour === undefined) this.colour = await this.worker.atlasColour();
    if (!this.colour) return;
    const needed = new Set(parts.map(([g, level]) => this.colour.group_packs[g][level + 1]));
    const missing = [...needed].filter((name) => !this.worker.colourPacks.has(name));
    await forEachLimited(missing, FETCH_PARALLEL, async (name) => {
      const bytes = await fetchBytes(new URL(name, this.baseUrl).href, `colour pack ${name}`);
      this.stats.atlas_colour_bytes += bytes.length;
      this.stats.bytes_downloaded = (this.stats.bytes_downloaded || 0) + bytes.length;
      await this.worker.addColourPack(name, await decodeTextureRgb(bytes, { file: name }));
      this.stats.atlas_colour_packs_loaded += 1;
    });
    const unneeded = [...this.worker.colourPacks].filter((name) => !needed.has(name));
    if (unneeded.length) await this.worker.dropColourPacks(unneeded);
  }

  /** Colour every group by the error map `errorMap` (ErrorMap of the manifest's error_raster:
   *  its file fetched once, handed to the worker with the map's palette) or, null, by the
   *  colour packs again; the groups on screen are made again (or taken from the cache) with
   *  those colours. Resolves when they are drawn. */
  async showErrorMap(errorMap) {
    await this.baseParts; // made with the colours of before: kept under their own key
    await this.idle();
    if (errorMap) {
      if (!this.errorBytes) {
        this.errorBytes = await fetchBytes(new URL(errorMap.file, this.baseUrl).href,
                                           `error map ${errorMap.file}`);
        this.stats.bytes_downloaded = (this.stats.bytes_downloaded || 0) + this.errorBytes.length;
        this.stats.atlas_error_map_bytes = this.errorBytes.length;
      }
      await this.worker.setErrorMap(this.errorBytes.slice(), errorMap.palette());
    } else {
      await this.worker.setErrorMap(null);
    }
    this.errorShown = Boolean(errorMap);
    await this.show(this.shown);
  }

  /** Show the welded mesh's RGB per vertex (bytes, sRGB) as three.js vertex colours
   *  (linear), or the viewer's plain material without them. */
  showColours(colors) {
    if (colors) {
      this.viewer.mesh.geometry.setAttribute(
        "color", new THREE.BufferAttribute(linearColours(colors), 3));
    }
    useVertexColours(this.viewer.material, Boolean(colors));
    this.viewer.render();
  }

  /** Update once the camera has been still for SETTLE_MS (each change re-tessellates). */
  schedule(delay = SETTLE_MS) {
    if (!this.enabled) return;
    clearTimeout(this.timer);
    this.timer = setTimeout(() => {
      this.timer = null;
      this.update().catch((error) => this.onError(`atlas detail: ${error.message}`));
    }, delay);
  }

  /** Bring the mesh on screen to the levels the camera wants: fetch and hand over the packs
   *  they need, drop the others, re-tessellate. Resolves when done (an update asked for
   *  meanwhile runs after it). */
  async update() {
    if (this.running) {
      this.again = true;
      return this.running;
    }
    const t0 = performance.now();
    Object.assign(this.stats, { atlas_batches: 0, atlas_first_batch_ms: 0,
                                atlas_update_python_ms: 0 }); // this update's
    this.running = (async () => {
      do {
        this.again = false;
        await this._updateOnce(t0);
      } while (this.again);
    })();
    try {
      await this.running;
    } finally {
      this.running = null;
    }
  }

  /** One pass of update() (begun at `t0`): plan, then show the batches; its figures are
   *  added to the update's stats. */
  async _updateOnce(t0) {
    const steps = [];
    const levels = this.wanted(steps);
    if (levels.every((k, g) => k === this.shown[g])) return;
    const batches = this.batches(levels, steps);
    for (const [k, batch] of batches.entries()) {
      await this._showLevels(batch, k === batches.length - 1);
      if (!this.stats.atlas_batches) this.stats.atlas_first_batch_ms = performance.now() - t0;
      this.stats.atlas_batches += 1;
      this.stats.atlas_update_python_ms += this.stats.atlas_tessellate_ms;
      // the camera moved (the controls' own update of this move sets `again` too: only a
      // new choice ends the batches early): update() plans again from what is shown
      if (this.again && this.wanted().some((k, g) => k !== levels[g])) return;
    }
  }

  /** The level vectors shown on the way from this.shown to `levels` (wanted()'s, its
   *  `steps`), one or two: first the groups that go down and the first raises wanted()
   *  granted (largest projected error first) until about BATCH_VERTICES vertices are to
   *  tessellate (the raised groups and their neighbours, which are made again with them),
   *  then the rest: the view's nearest detail is drawn first. Each is a choice within the
   *  budget (a part of `levels`), welded. (Batches of BATCH_VERTICES all the way made the
   *  neighbours again at every batch: the bunny's close view took 12 batches and 40 s
   *  under SwiftShader instead of 6 s.) */
  batches(levels, steps) {
    const first = this.shown.map((k, g) => Math.min(k, levels[g]));
    const replay = this.groups.map(() => -1);
    const made = (g) => this.groups[g].count * this.resolutions[first[g] + 1] ** 2;
    let work = 0;
    for (const g of steps) {
      replay[g] += 1;
      if (replay[g] <= first[g]) continue;
      first[g] = replay[g];
      work += [g, ...this.groups[g].neighbours].reduce((sum, h) => sum + made(h), 0);
      if (work >= BATCH_VERTICES) break;
    }
    const done = first.every((k, g) => k === levels[g]);
    return done ? [first] : [first, [...levels]];
  }

  /** Fetch and hand over the packs `levels` needs, and show it; `drop`: also drop the packs
   *  held that it does not need (the last batch of an update). */
  async _showLevels(levels, drop) {
    // the packs of the groups to tessellate and of their neighbours (a kept mesh needs none)
    const made = levels.map((_, g) => g).filter((g) => !this.cache.has(this.partKey(g, levels)));
    const needed = new Set();
    for (const g of this.withNeighbours(made)) {
      for (let k = 0; k <= levels[g]; k++) if (this.groups[g].packs[k]) needed.add(this.groups[g].packs[k]);
    }
    const missing = [...needed].filter((name) => !this.worker.holds(name));
    let next = 0;
    const fetchOne = async () => {
      while (next < missing.length) {
        const name = missing[next++];
        const bytes = await fetchBytes(new URL(name, this.baseUrl).href, `detail pack ${name}`);
        this.stats.atlas_pack_bytes += bytes.length;
        this.stats.bytes_downloaded = (this.stats.bytes_downloaded || 0) + bytes.length;
        await this.worker.addPack(name, bytes);
        this.stats.atlas_packs_loaded += 1;
      }
    };
    await Promise.all(Array.from({ length: Math.min(FETCH_PARALLEL, missing.length) }, fetchOne));
    const unneeded = drop ? [...this.worker.heldPacks()].filter((name) => !needed.has(name)) : [];
    if (unneeded.length) await this.worker.dropPacks(unneeded);
    await this.show(levels);
    this.stats.atlas_updates += 1;
    this.onChange();
  }

  /** Resolves once no update is due or running. */
  async idle() {
    while (this.timer !== null || this.running) {
      if (this.running) await this.running.catch(() => {});
      else await new Promise((resolve) => setTimeout(resolve, 50));
    }
  }
}

/** sRGB bytes (RGB per vertex) -> linear intensities, as three.js vertex colours expect. */
function linearColours(colors) {
  const linear = new Float32Array(colors.length);
  for (let k = 0; k < colors.length; k++) linear[k] = SRGB_TO_LINEAR[colors[k]];
  return linear;
}

/** Draw `material` with the geometry's vertex colours (its own colour white, to multiply by)
 *  or, `on` false, with its own colour again. */
function useVertexColours(material, on) {
  if (Boolean(material.vertexColors) === Boolean(on)) return;
  if (on) {
    material.userData.plainColour = material.color.clone();
    material.color.set(0xffffff);
  } else {
    material.color.copy(material.userData.plainColour);
  }
  material.vertexColors = Boolean(on);
  material.needsUpdate = true;
}
