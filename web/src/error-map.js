// ErrorMap: the bundle's fit-error grid (manifest.error_grid) as colours.
//
// error_grid = {rows, cols, max, values}: rows over u, columns over v, row-major, each value
// the RMS deviation of the scan points in that (u, v) cell, null where no point fell.
// Colours follow viridis (perceptually uniform, colour-blind safe), 0 -> max; empty cells grey.

const VIRIDIS = [
  [68, 1, 84], [72, 40, 120], [62, 74, 137], [49, 104, 142], [38, 130, 142],
  [31, 158, 137], [53, 183, 121], [109, 205, 89], [180, 222, 44], [253, 231, 37],
];
const EMPTY = [150, 150, 150];

/** RGB (0-255) of viridis at t in [0, 1]. */
export function viridis(t) {
  const x = Math.min(Math.max(t, 0), 1) * (VIRIDIS.length - 1);
  const k = Math.min(Math.floor(x), VIRIDIS.length - 2);
  const f = x - k;
  return VIRIDIS[k].map((c, i) => Math.round(c + f * (VIRIDIS[k + 1][i] - c)));
}

export class ErrorMap {
  /**
   * @param {{rows: number, cols: number, max: number, values: (number|null)[]}} grid
   * @param {string} units
   */
  constructor(grid, units = "") {
    const { rows, cols, values } = grid;
    if (!Number.isInteger(rows) || !Number.isInteger(cols) || rows < 1 || cols < 1 ||
        !Array.isArray(values) || values.length !== rows * cols) {
      throw new Error(`manifest error_grid is malformed: ${rows}x${cols} with ` +
                      `${Array.isArray(values) ? values.length : "no"} values`);
    }
    const finite = values.filter((v) => v !== null && Number.isFinite(v));
    this.rows = rows;
    this.cols = cols;
    this.values = values;
    this.max = Number.isFinite(grid.max) && grid.max > 0 ? grid.max : Math.max(1e-12, ...finite);
    this.units = units;
  }

  /** RGB of cell (row, col). */
  cellColor(row, col) {
    const value = this.values[row * this.cols + col];
    return value === null || !Number.isFinite(value) ? EMPTY : viridis(value / this.max);
  }

  /** RGBA bytes, `cols` wide and `rows` tall, row 0 first (for a three.js DataTexture). */
  rgba() {
    const out = new Uint8Array(this.rows * this.cols * 4);
    for (let r = 0; r < this.rows; r++) {
      for (let c = 0; c < this.cols; c++) {
        const k = 4 * (r * this.cols + c);
        out.set(this.cellColor(r, c), k);
        out[k + 3] = 255;
      }
    }
    return out;
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
      const row = Math.min(this.rows - 1, Math.floor(((uvs[2 * k] - u0) / (u1 - u0)) * this.rows));
      const col = Math.min(this.cols - 1, Math.floor(((uvs[2 * k + 1] - v0) / (v1 - v0)) * this.cols));
      out.set(this.cellColor(Math.max(row, 0), Math.max(col, 0)), 3 * k);
    }
    return out;
  }

  /** A CSS linear-gradient of the colour scale, for the legend. */
  cssGradient() {
    const stops = VIRIDIS.map((c, i) => `rgb(${c.join(",")}) ${(100 * i) / (VIRIDIS.length - 1)}%`);
    return `linear-gradient(to right, ${stops.join(", ")})`;
  }
}
