// The error map (error-map.js, error-map-control.js): per vertex from the manifest's
// error_raster, its legend's max the panel's max (facts-panel.js), holes in their own colour.

import assert from "node:assert/strict";
import { test } from "node:test";
import { deflateSync } from "node:zlib";

import { ErrorMap, HOLE_COLOR, viridis } from "../src/error-map.js";

/** A stand-in for the page's elements: what the control and the panel read and write. */
function fakeDocument() {
  const elements = new Map();
  const element = (id) => {
    if (!elements.has(id)) {
      const attributes = new Map();
      elements.set(id, {
        id, textContent: "", title: "", hidden: true, disabled: true, style: {},
        listeners: [],
        addEventListener(type, listener) { this.listeners.push(listener); },
        setAttribute(name, value) { attributes.set(name, String(value)); },
        getAttribute(name) { return attributes.has(name) ? attributes.get(name) : null; },
        click() { for (const listener of this.listeners) listener(); },
        scrolledIntoView: 0,
        scrollIntoView() { this.scrolledIntoView += 1; },
      });
    }
    return elements.get(id);
  };
  globalThis.document = { getElementById: element, body: { dataset: {} } };
  return element;
}

/** A manifest error_raster of `codes` (rows x cols bytes, 255: no point) and `max`. */
function raster(rows, cols, codes, max) {
  return { rows, cols, max, statistic: "max |d|", encoding: "uint8 base64",
           data: Buffer.from(Uint8Array.from(codes)).toString("base64") };
}

// 4 x 4 cells, rows over u: a hole at (1, 2), the worst cell (code 254) at (3, 3)
const CODES = [0, 50, 100, 150, 20, 70, 255, 170, 40, 90, 140, 190, 60, 110, 160, 254];
const MAX = 6.68;
const MANIFEST = {
  units: "mm", stats: { rms: 0.9, max: MAX }, error_raster: raster(4, 4, CODES, MAX),
};

test("the legend ends at the panel's max, in the bundle's units", async () => {
  const element = fakeDocument();
  const { ErrorMapControl } = await import("../src/error-map-control.js");
  const { FactsPanel } = await import("../src/facts-panel.js");
  const ready = { patch: { units: "mm", shape: [12, 12], degree: [2, 2], rational: false },
                  patch_bytes: 1000 };
  new FactsPanel().describe(MANIFEST, ready, { bytes_downloaded: 2000 });
  const overlays = [];
  const control = new ErrorMapControl(MANIFEST, { setErrorOverlay: (image) => overlays.push(image) });
  assert.equal(element("fact-max").textContent, "6.68 mm");
  assert.equal(element("legend-max").textContent, element("fact-max").textContent);
  assert.equal(element("toggle-error").disabled, false);
  assert.equal(element("legend-hole-swatch").style.background, `rgb(${HOLE_COLOR.join(",")})`);
  element("toggle-error").click();
  await new Promise((resolve) => setTimeout(resolve, 0)); // toggle() resolves after its show
  assert.equal(control.shown, true);
  assert.equal(element("legend").hidden, false);
  assert.equal(element("legend").scrolledIntoView, 1, "the panel scrolls to the legend");
  const image = overlays[0];
  assert.ok(image.rows >= 256 && image.cols >= 256, "finer than the cells: no blocks");
  assert.equal(image.rgba.length, 4 * image.rows * image.cols);
});

test("a single patch's codes in a file: fetched when the map is first pressed, then the same map", async () => {
  const element = fakeDocument();
  const { ErrorMapControl } = await import("../src/error-map-control.js");
  const zipped = deflateSync(Uint8Array.from(CODES)); // zlib (RFC 1950), as the fitter writes
  const fetched = [];
  globalThis.fetch = async (url) => {
    fetched.push(String(url));
    return new Response(url.endsWith("error_raster.bin") ? zipped : new Uint8Array(3));
  };
  try {
    const manifest = { units: "mm", stats: { max: MAX },
                       error_raster: { file: "error_raster.bin", rows: 4, cols: 4, max: MAX,
                                       statistic: "max |d|", bytes: zipped.length } };
    const overlays = [];
    const control = new ErrorMapControl(manifest, { setErrorOverlay: (image) => overlays.push(image) },
                                        { baseUrl: "http://host/b/manifest.json" });
    assert.equal(control.errorMap.values, null, "nothing fetched before the map is pressed");
    assert.equal(element("legend-max").textContent, "6.68 mm");
    const pressing = control.toggle();
    // while the file is on its way the map is not shown: a PLY written now has no colours
    assert.equal(control.shown, false);
    assert.equal(control.vertexColors(new Float32Array([0.5, 0.5]), [0, 1, 0, 1]), null);
    await pressing;
    assert.equal(element("toggle-error").title, "");
    assert.deepEqual(fetched, ["http://host/b/error_raster.bin"]);
    assert.equal(control.shown, true);
    assert.equal(overlays.length, 1);
    const inline = ErrorMap.fromManifest(MANIFEST); // the same codes held in the manifest
    assert.deepEqual([...control.errorMap.values], [...inline.values]);
    await control.toggle();
    await control.toggle();
    assert.equal(overlays.length, 3);
    assert.equal(fetched.length, 1, "fetched once");
    const short = new ErrorMap({ rows: 4, cols: 5, max: MAX, values: null, statistic: "",
                                 file: "error_raster.bin" });
    await assert.rejects(short.load("http://host/b/manifest.json"), /4x5 cells but 16 codes/);
  } finally {
    delete globalThis.fetch;
  }
});

test("a malformed raster leaves the button disabled and says why", async () => {
  const element = fakeDocument();
  const { ErrorMapControl } = await import("../src/error-map-control.js");
  const manifest = { ...MANIFEST, error_raster: raster(4, 4, CODES.slice(0, 15), MAX) };
  new ErrorMapControl(manifest, { setErrorOverlay() {} });
  assert.equal(element("toggle-error").disabled, true);
  assert.match(element("toggle-error").title, /error_raster is malformed: 4x4 cells but 15 bytes/);
});

test("per vertex: cell values at cell centres, bilinear between, the max never exceeded", () => {
  const map = ErrorMap.fromManifest(MANIFEST);
  const value = (i, j) => (CODES[4 * i + j] / 254) * MAX;
  // a cell centre is its value exactly; the worst cell decodes to the panel's max
  assert.ok(Math.abs(map.valueAt(0.125, 0.125) - value(0, 0)) < 1e-12);
  assert.equal(map.valueAt(0.875, 0.875), MAX);
  // halfway between two cell centres along v: their mean
  assert.ok(Math.abs(map.valueAt(0.125, 0.25) - (value(0, 0) + value(0, 1)) / 2) < 1e-12);
  // next to the hole, the hole's cell does not count (its weight goes to the others)
  // (u = 0.375 is row 1's centre; v = 0.45 is 0.3 of the way from cell 1 to the hole)
  assert.ok(Math.abs(map.valueAt(0.375, 0.45) - value(1, 1)) < 1e-12);
  // and a point inside the hole's cell has no value
  assert.ok(Number.isNaN(map.valueAt(0.375, 0.6)));
  let largest = 0;
  for (let s = 0; s <= 1; s += 1 / 97) {
    for (let t = 0; t <= 1; t += 1 / 89) {
      const v = map.valueAt(s, t);
      if (!Number.isNaN(v)) largest = Math.max(largest, v);
    }
  }
  assert.ok(largest <= MAX);
});

test("holes and uncovered parts take their own colour, outside the scale", () => {
  const map = ErrorMap.fromManifest(MANIFEST);
  // vertices at parameters (u, v) over the domain [10, 20] x [0, 2]: one in the hole cell
  const uvs = Float32Array.from([10 + 10 * 0.375, 2 * 0.625, 10, 0, 20, 2]);
  const colours = map.vertexColors(uvs, [10, 20, 0, 2]);
  assert.deepEqual([...colours.subarray(0, 3)], HOLE_COLOR);
  assert.deepEqual([...colours.subarray(3, 6)], viridis(0));
  assert.deepEqual([...colours.subarray(6, 9)], viridis(1));
  for (let k = 0; k <= 100; k++) {
    const c = viridis(k / 100);
    const distance = Math.hypot(...c.map((x, i) => x - HOLE_COLOR[i]));
    assert.ok(distance > 40, `viridis(${k / 100}) = ${c} is too close to the hole colour`);
  }
});

test("older bundles' error_grid (RMS per cell, null where empty) is still read", () => {
  const map = ErrorMap.fromManifest({ units: "mm", error_grid: { rows: 2, cols: 2, max: 4,
                                                                 values: [1, null, 3, 4] } });
  assert.equal(map.max, 4);
  assert.ok(Number.isNaN(map.valueAt(0.25, 0.75)));
  assert.equal(map.valueAt(0.75, 0.75), 4);
  assert.equal(ErrorMap.fromManifest({ units: "mm" }), null);
});

test("an atlas's raster: the same legend, its file and a palette of every code for the worker", async () => {
  const element = fakeDocument();
  const { ErrorMapControl } = await import("../src/error-map-control.js");
  const manifest = { units: "mm", format_version: 2, stats: { max: MAX },
                     error_raster: { file: "error_raster.bin", patches: 576, rows: 8, cols: 8,
                                     max: MAX, statistic: "max |d|", bytes: 900 } };
  const shown = [];
  const control = new ErrorMapControl(manifest, {}, { show: async (map) => shown.push(map) });
  assert.equal(element("toggle-error").disabled, false);
  assert.equal(element("legend-max").textContent, "6.68 mm");
  element("toggle-error").click();
  await new Promise((resolve) => setTimeout(resolve, 0));
  assert.equal(shown[0].file, "error_raster.bin");
  assert.equal(control.shown, true);
  const palette = shown[0].palette();
  assert.equal(palette.length, 768);
  assert.deepEqual([...palette.slice(0, 3)], viridis(0));
  assert.deepEqual([...palette.slice(3 * 254, 3 * 255)], viridis(1)); // code 254: the max
  assert.deepEqual([...palette.slice(3 * 255)], HOLE_COLOR);
  element("toggle-error").click();
  await new Promise((resolve) => setTimeout(resolve, 0));
  assert.deepEqual(shown, [shown[0], null]);
  assert.equal(element("legend").hidden, true);
  assert.throws(() => ErrorMap.fromManifest({ ...manifest,
                                              error_raster: { ...manifest.error_raster, patches: 0 } }),
                /an atlas's needs max >= 0 and a file and patches >= 1/);
  // an atlas's raster without its patch count is refused, not read as a single patch's
  const { patches, ...withoutPatches } = manifest.error_raster;
  assert.equal(patches, 576);
  assert.throws(() => ErrorMap.fromManifest({ ...manifest, error_raster: withoutPatches }),
                /patches undefined/);
});
