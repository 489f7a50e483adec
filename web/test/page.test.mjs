// page.js's text helpers: byte sizes, lengths with units, plurals.

import assert from "node:assert/strict";
import { test } from "node:test";

import { formatBytes, formatLength, plural } from "../src/page.js";

test("formatBytes: B below 1 KiB, then KB and MB with one decimal (1024-based)", () => {
  assert.equal(formatBytes(0), "0 B");
  assert.equal(formatBytes(1023), "1023 B");
  assert.equal(formatBytes(1024), "1.0 KB");
  assert.equal(formatBytes(1536), "1.5 KB");
  assert.equal(formatBytes(1024 * 1024 - 1), "1024.0 KB");
  assert.equal(formatBytes(1024 * 1024), "1.0 MB");
  assert.equal(formatBytes(5.25 * 1024 * 1024), "5.3 MB");
});

test("formatLength: 1 or 2 decimals from 1, else 3 significant digits; small m/cm in mm", () => {
  assert.equal(formatLength(0.01234, "mm"), "0.0123 mm");
  assert.equal(formatLength(0.0003091, "mm"), "0.000309 mm"); // never "0.000 mm"
  assert.equal(formatLength(1.2345, "mm"), "1.23 mm");
  assert.equal(formatLength(-1.2345, "m"), "-1.23 m");
  assert.equal(formatLength(12.345, "cm"), "12.3 cm");
  assert.equal(formatLength(9.999, "mm"), "10.00 mm");
  assert.equal(formatLength(0.0003091, "m"), "0.309 mm"); // a Stanford scan's RMS
  assert.equal(formatLength(0.002306, "m"), "2.31 mm");
  assert.equal(formatLength(0.5, "m"), "500.0 mm");
  assert.equal(formatLength(0.25, "cm"), "2.50 mm");
  assert.equal(formatLength(0.25, "in"), "0.250 in"); // not metric: left in its unit
  assert.equal(formatLength(0, "m"), "0 mm");
  assert.equal(formatLength(0.5, "unknown"), "0.500");
  assert.equal(formatLength(0.0001234, "unknown"), "0.000123");
  assert.equal(formatLength(2, ""), "2.00");
  for (const none of [undefined, null, NaN, Infinity]) assert.equal(formatLength(none, "mm"), "—");
});

test("plural: singular for one, grouped thousands", () => {
  assert.equal(plural(1, "tile"), "1 tile");
  assert.equal(plural(0, "tile"), "0 tiles");
  assert.equal(plural(2, "detail tile"), "2 detail tiles");
  assert.equal(plural(12345, "vertex colour"), "12,345 vertex colours");
});
