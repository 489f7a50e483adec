// BaseMesh: the base patch on screen as a mesh the worker tessellates on a square grid, its
// resolution following the view: a vertex every ~3 device pixels across the object, within
// MIN_RESOLUTION..MAX_RESOLUTION, re-tessellated once a zoom gesture ends when the wanted
// grid differs from the shown one by more than 1.4 x (unless the page fixes it, ?resolution=N).
// The first mesh is coarse (COARSE_RESOLUTION: ~1k vertices, drawn within milliseconds).
// With detail regions on screen (`backdrop()`), the base is a backdrop and its grid stays at
// most BACKDROP_RESOLUTION. Following the zoom comes after the detail: the re-tessellation
// waits until `waitFor()`
// (the tile layer idle: the zoom's refined regions drawn) and is dropped when a newer gesture
// ends meanwhile, so a wheel step reaches its refined view without the base's grid in the
// way (a 384² base is ~150k vertices of Python); onShown(mesh, {following: true}) tells the
// page it was such a re-tessellation.
// Stats: resolution, vertices, triangles, tessellate_ms (Python), round_trip_ms, meshes,
// base_shown_at (performance.now() when the last base mesh was put on screen).

export const COARSE_RESOLUTION = 24;
export const MIN_RESOLUTION = 48;
export const MAX_RESOLUTION = 384;
/** The grid of a base that detail regions cover (`backdrop()`): hidden under them and
 *  outside the view, it shows only where its own error is under a pixel or two, and every
 *  draw processes all its vertices (a 384² base: 147k, up to 2 s a draw under a software
 *  rasteriser; 96²: 9k). */
export const BACKDROP_RESOLUTION = 96;
const RETESSELLATE_RATIO = 1.4;
const ZOOM_SETTLE_MS = 150;

export class BaseMesh {
  /**
   * @param {{viewer: import("./viewer.js").Viewer,
   *          worker: import("./mesh-worker-client.js").MeshWorkerClient, stats: object,
   *          fixedResolution?: number|null, onShown?: (mesh: object) => void}} options
   *   fixedResolution: the page's ?resolution=N (no following the view); onShown: called with
   *   the worker's mesh once it is on screen
   */
  constructor({ viewer, worker, stats, fixedResolution = null, onShown = () => {},
                waitFor = async () => {}, backdrop = () => false }) {
    this.viewer = viewer;
    this.worker = worker;
    this.stats = stats;
    this.fixedResolution = fixedResolution;
    this.onShown = onShown;
    this.waitFor = waitFor; // resolves when a zoom's re-tessellation may start
    this.backdrop = backdrop; // whether detail regions are drawn over the base now
    this.gesture = 0; // zoom gestures ended so far: a newer one supersedes a waiting one
    this.domain = null; // [u0, u1, v0, v1] of the patch, once the worker has read it
    this.resolution = 0; // grid of the mesh on screen (0: none yet)
    this.uvs = null; // its (u, v) per vertex, the order of the worker's PLY of this grid
    this.pending = null;
  }

  /** The grid the view wants: a vertex every ~3 device pixels across the object on screen,
   *  at most BACKDROP_RESOLUTION while detail regions cover the view (`backdrop()`). */
  viewResolution() {
    const pixels = this.viewer.projectedDiameter() / 3;
    const top = this.backdrop() ? BACKDROP_RESOLUTION : MAX_RESOLUTION;
    return Math.min(top, Math.max(MIN_RESOLUTION, Math.round(pixels / 16) * 16));
  }

  /** The grid to show once loaded: the fixed one, or the view's. */
  targetResolution() {
    return this.fixedResolution || this.viewResolution();
  }

  /** Tessellate on a `resolution` x `resolution` grid and show it; resolves with a copy of
   *  the stats. */
  async show(resolution, { following = false } = {}) {
    const t0 = performance.now();
    const mesh = await this.worker.tessellate(resolution);
    this.viewer.setMesh(mesh, this.domain);
    this.resolution = resolution;
    this.uvs = mesh.uvs;
    Object.assign(this.stats, {
      resolution, vertices: mesh.positions.length / 3, triangles: mesh.indices.length / 3,
      tessellate_ms: mesh.tessellate_ms, round_trip_ms: performance.now() - t0,
      meshes: this.stats.meshes + 1, base_shown_at: performance.now(),
    });
    this.onShown(mesh, { following });
    return { ...this.stats };
  }

  /** After each zoom gesture, re-tessellate when the view wants a grid far enough from the
   *  one shown, once `waitFor()` resolves and unless a newer gesture ended meanwhile; a
   *  failure goes to `onError(message)`. */
  followZoom(onError) {
    this.viewer.controls.addEventListener("end", () => {
      if (this.fixedResolution || !this.domain) return;
      const gesture = ++this.gesture;
      clearTimeout(this.pending);
      this.pending = setTimeout(async () => {
        try {
          await this.waitFor();
          const wanted = this.viewResolution(); // the view (and its regions) once the detail is in
          if (gesture !== this.gesture || wanted === this.resolution ||
              Math.abs(Math.log(wanted / this.resolution)) < Math.log(RETESSELLATE_RATIO)) return;
          await this.show(wanted, { following: true });
        } catch (error) {
          onError(error.message);
        }
      }, ZOOM_SETTLE_MS);
    });
  }
}
