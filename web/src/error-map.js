// ErrorMap: the fit's deviation over the patch's (u, v) domain as colours, per vertex.
//
// Its source is the manifest's error_raster (fitter.fitting.error.error_raster): rows x cols
// cells of the normalised domain, rows over u, row-major, each the largest |d| of the covered
// scan points in the cell, one byte of `max` (code k < 255: k / 254 max; 255: no scan point),
// base64. `max` is the manifest's stats.max, the panel's "max": the colour scale ends there.
// A single patch's error_raster (bundles since session 17) names a file of its codes instead
// of holding them (zlib of the rows x cols bytes, docs/format.md): load() fetches it the first
// time the map is shown, so the codes are not downloaded before a level is drawn.
// An atlas bundle's error_raster names a file instead of holding data (docs/format.md: per
// patch rows x cols cells of its (u, v), zlib, one byte per cell as above): the worker colours
// its meshes per vertex from it (WorkerSession.set_error_map, through the atlas's one
// per-vertex colouring rule), with palette() — this file's colour of each code — so the scale
// is defined here alone; the legend is the same.
// A bundle written before the raster has error_grid instead ({rows, cols, max, values}: the
// RMS per cell, null where no point fell); it is read the same way, its max its own.
//
// The value at a point (s, t) of the normalised domain is the bilinear interpolation of the
// cell values at the cell centres around it ((i + 1/2) / rows, (j + 1/2) / cols), over the
// neighbours that hold a value (their weights renormalised); where the cell under the point
// holds none (a hole of the scan, or a part of the patch no scan point maps to) it has no
// value and takes HOLE_COLOR. Interpolating never exceeds the largest cell value, so no vertex
// is brighter than the legend's end. Colours follow viridis (perceptually uniform,
// colour-blind safe) from 0 to max.

import { fetchBytes } from "./fetch-bytes.js";

const VIRIDIS = [
  [68, 1, 84], [72, 40, 120], [62, 74, 137], [49, 104, 142], [38, 130, 142],
  [31, 158, 137], [53, 183, 121], [109, 205, 89], [180, 222, 44], [253, 231, 37],
];
/** The colour of no value (a hole, an uncovered part): a grey-purple outside viridis. */
export const HOLE_COLOR = [150, 128, 170];
const EMPTY_CODE = 255;
const MAX_SIDE = 1024; // cells per side accepted (the fitter writes at most 64)
const TEXTURE_SIDE = 256; // texels per side of the on-screen map (at least the raster's)

/** RGB (0-255) of viridis at t in [0, 1]. */
export function viridis(t) {
  const x = Math.min(Math.max(t, 0), 1) * (VIRIDIS.length - 1);
  const k = Math.min(Math.floor(x), VIRIDIS.length - 2);
  const f = x - k;
  return VIRIDIS[k].map((c, i) => Math.round(c + f * (VIRIDIS[k + 1][i] - c)));
}

function checkShape(name, rows, cols) {
  if (!Number.isInteger(rows) || !Number.isInteger(cols) || rows < 1 || cols < 1 ||
      rows > MAX_SIDE || cols > MAX_SIDE) {
    throw new Error(`manifest ${name} is malformed: rows and cols must be integers in ` +
                    `1..${MAX_SIDE}, got ${rows}x${cols}`);
  }
}

/** The cell values (NaN: no point) and max of a manifest error_raster. */
function decodeRaster(raster) {
  const { rows, cols, max, data } = raster;
  checkShape("error_raster", rows, cols);
  if (!(Number.isFinite(max) && max >= 0) || typeof data !== "string") {
    throw new Error(`manifest error_raster is malformed: max must be a number >= 0 and data ` +
                    `a base64 string, got max ${max} and data of type ${typeof data}`);
  }
  let bytes;
  try {
    bytes = Uint8Array.from(atob(data), (c) => c.charCodeAt(0));
  } catch {
    throw new Error("manifest error_raster is malformed: data is not base64");
  }
  if (bytes.length !== rows * cols) {
    throw new Error(`manifest error_raster is malformed: ${rows}x${cols} cells but ` +
                    `${bytes.length} bytes of data`);
  }
  return { rows, cols, max, values: cellValues(bytes, max), statistic: "largest distance to the scan" };
}

/** The value of each one-byte code (NaN: no scan point). */
function cellValues(codes, max) {
  return Float64Array.from(codes, (code) => (code === EMPTY_CODE ? NaN : (code / 254) * max));
}

/** The shape and max of an error_raster whose codes are in the bundle's file (values null):
 *  a single patch's, read by ErrorMap.load, or with `atlas` an atlas's, patch after patch,
 *  read by its worker (AtlasLayer.showErrorMap). */
function decodeFileRaster(raster, atlas) {
  const { rows, cols, max, file, patches } = raster;
  checkShape("error_raster", rows, cols);
  const patchesOk = !atlas || (Number.isInteger(patches) && patches >= 1);
  if (!(Number.isFinite(max) && max >= 0) || typeof file !== "string" || !patchesOk) {
    throw new Error(`manifest error_raster is malformed: ${atlas ? "an atlas's" : "a single patch's"} ` +
                    `needs max >= 0 and a file${atlas ? " and patches >= 1" : ""}, got max ${max}, ` +
                    `file ${file}${atlas ? `, patches ${patches}` : ""}`);
  }
  return { rows, cols, max, values: null, statistic: "largest distance to the scan", file,
           patches: atlas ? patches : 1, atlas };
}

/** The bytes of a zlib stream (RFC 1950), by the platform's DecompressionStream. */
async function inflate(bytes) {
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

/** The cell values (NaN: no point) and max of a manifest error_grid (older bundles). */
function decodeGrid(grid) {
  const { rows, cols, values } = grid;
  checkShape("error_grid", rows, cols);
  if (!Array.isArray(values) || values.length !== rows * cols) {
    throw new Error(`manifest error_grid is malformed: ${rows}x${cols} with ` +
                    `${Array.isArray(values) ? values.length : "no"} values`);
  }
  const decoded = Float64Array.from(values, (v) => (typeof v === "number" && Number.isFinite(v) ? v : NaN));
  const largest = Math.max(0, ...decoded.filter((v) => !Number.isNaN(v)));
  const max = Number.isFinite(grid.max) && grid.max > 0 ? grid.max : largest;
  return { rows, cols, max, values: decoded, statistic: "RMS distance to the scan" };
}

export class ErrorMap {
  /**
   * The error map of a bundle, or null when its manifest has none.
   * @param {object} manifest  the bundle's manifest.json, parsed
   * @throws {Error} a malformed error_raster (or error_grid), naming what is wrong
   */
  static fromManifest(manifest) {
    const raster = manifest.error_raster;
    if (raster && raster.file !== undefined) {
      return new ErrorMap(decodeFileRaster(raster, manifest.format_version === 2),
                          manifest.units || "");
    }
    if (raster) return new ErrorMap(decodeRaster(raster), manifest.units || "");
    if (manifest.error_grid) return new ErrorMap(decodeGrid(manifest.error_grid), manifest.units || "");
    return null;
  }

  /**
   * @param {{rows: number, cols: number, max: number, values: Float64Array,
   *          statistic: string}} cells  values per cell, rows over u, NaN where no point
   * @param {string} units
   */
  constructor({ rows, cols, max, values, statistic, file = null, patches = 1, atlas = false },
              units = "") {
    this.rows = rows;
    this.file = file; // the bundle's file of the cells (values null until read)
    this.atlas = atlas; // an atlas's file is read by its worker, a single patch's by load()
    this.patches = patches;
    this.cols = cols;
    this.values = values;
    this.max = max;
    this.statistic = statistic;
    this.units = units;
  }

  /**
   * Read a single patch's cells from its file the first time (values are null until then);
   * nothing to do for a raster held in the manifest, or an atlas's (its worker reads it).
   * @param {URL|string} baseUrl  the manifest's URL: the file's name is relative to it
   * @throws {Error} the fetch failed, or the file does not hold rows x cols codes
   */
  async load(baseUrl) {
    if (this.values !== null || this.file === null || this.atlas) return;
    const what = `error map ${this.file}`;
    const codes = await inflate(await fetchBytes(new URL(this.file, baseUrl).href, what));
    if (codes.length !== this.rows * this.cols) {
      throw new Error(`${what} is malformed: ${this.rows}x${this.cols} cells but ` +
                      `${codes.length} codes`);
    }
    this.values = cellValues(codes, this.max);
  }

  /** The map's value at (s, t) of the normalised domain (s along u), NaN where no scan
   *  point is (see the top of this file). */
  valueAt(s, t) {
    const { rows, cols, values } = this;
    const clampIndex = (k, n) => Math.min(n - 1, Math.max(0, k));
    const own = values[clampIndex(Math.floor(s * rows), rows) * cols + clampIndex(Math.floor(t * cols), cols)];
    if (Number.isNaN(own)) return NaN;
    const x = s * rows - 0.5;
    const y = t * cols - 0.5;
    const i0 = Math.floor(x);
    const j0 = Math.floor(y);
    const fx = x - i0;
    const fy = y - j0;
    let sum = 0;
    let weights = 0;
    let largest = own;
    for (const [di, wi] of [[0, 1 - fx], [1, fx]]) {
      for (const [dj, wj] of [[0, 1 - fy], [1, fy]]) {
        const value = values[clampIndex(i0 + di, rows) * cols + clampIndex(j0 + dj, cols)];
        const w = wi * wj;
        if (w > 0 && !Number.isNaN(value)) {
          sum += w * value;
          weights += w;
          largest = Math.max(largest, value);
        }
      }
    }
    // (the bound holds in exact arithmetic; the min keeps rounding from passing it)
    return weights > 0 ? Math.min(sum / weights, largest) : own;
  }

  /** RGB of a value: viridis of value / max, HOLE_COLOR for NaN. */
  color(value) {
    if (Number.isNaN(value)) return HOLE_COLOR;
    return viridis(this.max > 0 ? value / this.max : 0);
  }

  /** RGBA bytes of the on-screen map, `cols` wide and `rows` tall, row 0 first (for a
   *  three.js DataTexture over uv = (t, s)): the values at the texel centres, at least
   *  TEXTURE_SIDE texels per side so that the interpolation, not the cells, is seen. */
  rgba() {
    const scale = Math.max(1, Math.ceil(TEXTURE_SIDE / Math.max(this.rows, this.cols)));
    const rows = this.rows * scale;
    const cols = this.cols * scale;
    const out = new Uint8Array(rows * cols * 4);
    for (let r = 0; r < rows; r++) {
      for (let c = 0; c < cols; c++) {
        const k = 4 * (r * cols + c);
        out.set(this.color(this.valueAt((r + 0.5) / rows, (c + 0.5) / cols)), k);
        out[k + 3] = 255;
      }
    }
    return { rgba: out, rows, cols };
  }

  /**
   * RGB per vertex from the vertices' surface parameters.
   * @param {Float32Array} uvs  u, v per vertex (parameter values)
   * @param {number[]} domain  [u0, u1, v0, v1]
   */
  vertexColors(uvs, domain) {
    const [u0, u1, v0, v1] = domain;
    const n = uvs.length / 2;
    const out = new Uint8Array(3 * n);
    for (let k = 0; k < n; k++) {
      const value = this.valueAt((uvs[2 * k] - u0) / (u1 - u0), (uvs[2 * k + 1] - v0) / (v1 - v0));
      out.set(this.color(value), 3 * k);
    }
    return out;
  }

  /** RGB of each of the raster's 256 codes (k < 255: the value k / 254 max; 255: no scan
   *  point), 768 bytes: what the worker colours an atlas's vertices with. */
  palette() {
    const out = new Uint8Array(3 * 256);
    for (let code = 0; code < 256; code++) {
      out.set(this.color(code === EMPTY_CODE ? NaN : (code / 254) * this.max), 3 * code);
    }
    return out;
  }

  /** A CSS linear-gradient of the colour scale, for the legend. */
  cssGradient() {
    const stops = VIRIDIS.map((c, i) => `rgb(${c.join(",")}) ${(100 * i) / (VIRIDIS.length - 1)}%`);
    return `linear-gradient(to right, ${stops.join(", ")})`;
  }
}

/** A CSS colour of an RGB triple. */
export function cssColor(rgb) {
  return `rgb(${rgb.join(",")})`;
}
