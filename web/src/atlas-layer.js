// AtlasLayer: an atlas bundle (manifest format_version 2) on screen — one welded mesh of every
// patch that the worker re-tessellates with each GROUP of patches at its own detail level,
// chosen by screen-space error as in OGC 3D Tiles (docs/format.md, "Bundle manifest,
// version 2 (atlas)").
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
// budget of MAX_VERTICES drawn vertices (a group at level k costs count * R_k^2, R_k the
// worker's samples per patch side at that level), since the whole atlas is tessellated again
// in pure Python for each change (client_py.atlas_mesh; about 2 s per 40 000 vertices in
// CPython on a busy machine, more in Pyodide). The packs a choice needs are fetched (at most
// FETCH_PARALLEL at once), handed to the worker (MeshWorkerClient.addPack) and those no
// longer needed dropped; then WorkerSession.atlas_mesh draws the new mesh, which replaces the
// shown one in one frame.
//
// Colour (a bundle with tiles.texture; WorkerSession.atlas_colour_refinement): a group drawn at
// level k is coloured per vertex from the colour pack (texture/C/G.webp) of colour level
// c = min(max(k, 0), C - 1), whose cells have as many texels per patch side as level c's mesh
// has cells (client_py.atlas_texture). As the single patch's texture tiles (tile-tree.js), a
// group is also refined while its texels look larger than TEXEL_PX on screen,
// texel_k * f / d > TEXEL_PX (texel_k: the world size of a texel at level k, median patch),
// and a finer colour level exists. Before each mesh, the packs the levels need are fetched,
// decoded to RGB (page.js decodeTextureRgb) and handed to the worker (addColourPack), those
// no longer needed dropped; the worker's mesh then carries RGB per vertex, shown through
// three.js vertex colours (converted from sRGB to linear, as the renderer expects).
//
// Stats (window.tessera.stats): atlas_levels (per group), atlas_refined_groups,
// atlas_packs_loaded, atlas_pack_bytes, atlas_tessellate_ms, atlas_updates, vertices,
// triangles, tessellate_ms, atlas_colour_packs_loaded, atlas_colour_bytes.

import * as THREE from "three";

import { fetchBytes } from "./fetch-bytes.js";
import { decodeTextureRgb, forEachLimited } from "./page.js";
import { DETAIL_PX, TEXEL_PX } from "./tile-tree.js";

export const MAX_VERTICES = 250000;
const FETCH_PARALLEL = 6;
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
    this.timer = null;
    this.running = null; // the update in progress, or null
    this.again = false; // the camera moved during an update: run once more after it
    this.colour = undefined; // WorkerSession.atlas_colour_refinement, read at the first show
    Object.assign(stats, { atlas_levels: [...this.shown], atlas_refined_groups: 0,
                           atlas_packs_loaded: 0, atlas_pack_bytes: 0, atlas_tessellate_ms: 0,
                           atlas_updates: 0, atlas_colour_packs_loaded: 0,
                           atlas_colour_bytes: 0 });
  }

  /** Whether the bundle has detail to refine with. */
  get enabled() {
    return this.levelCount > 0 && this.groups.length > 0;
  }

  /** The whole atlas with every group at `levels` from the worker, shown; resolves with
   *  the worker's mesh. */
  async show(levels) {
    const t0 = performance.now();
    await this.bringColours(levels);
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
    return mesh;
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

  /** The level each group should be drawn at for the current camera (module comment). */
  wanted() {
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
    let total = this.groups.reduce((sum, _, g) => sum + cost(g, -1), 0);
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

  /** Fetch, decode and hand the worker the colour packs `levels` need (WorkerSession
   *  atlas_colour_refinement's group_packs), and drop the others it holds. */
  async bringColours(levels) {
    if (this.colour === undefined) this.colour = await this.worker.atlasColour();
    if (!this.colour) return;
    const needed = new Set(levels.map((level, g) => this.colour.group_packs[g][level + 1]));
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

  /** Show the mesh's RGB per vertex (bytes, sRGB) as three.js vertex colours (linear), or
   *  the viewer's plain material without them. */
  showColours(colors) {
    const material = this.viewer.material;
    if (!colors) {
      if (material.vertexColors) {
        material.vertexColors = false;
        material.color.copy(this.plainColour);
        material.needsUpdate = true;
      }
      return;
    }
    const linear = new Float32Array(colors.length);
    for (let k = 0; k < colors.length; k++) linear[k] = SRGB_TO_LINEAR[colors[k]];
    this.viewer.mesh.geometry.setAttribute("color", new THREE.BufferAttribute(linear, 3));
    if (!material.vertexColors) {
      this.plainColour = material.color.clone();
      material.vertexColors = true;
      material.color.set(0xffffff);
      material.needsUpdate = true;
    }
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
    this.running = (async () => {
      do {
        this.again = false;
        await this._updateOnce();
      } while (this.again);
    })();
    try {
      await this.running;
    } finally {
      this.running = null;
    }
  }

  async _updateOnce() {
    const levels = this.wanted();
    if (levels.every((k, g) => k === this.shown[g])) return;
    const needed = new Set();
    levels.forEach((level, g) => {
      for (let k = 0; k <= level; k++) if (this.groups[g].packs[k]) needed.add(this.groups[g].packs[k]);
    });
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
    const unneeded = [...this.worker.heldPacks()].filter((name) => !needed.has(name));
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
