// transfer-tally.js: a visit's transferred bytes split into runtime and object, and the
// object's cost as served, from Resource Timing entries of the page and the worker.

import assert from "node:assert/strict";
import { test } from "node:test";

import { TransferTally } from "../src/transfer-tally.js";

const PAGE = "http://host/objects/relief/";
const entry = (name, transferSize, encodedBodySize) => ({ name, transferSize, encodedBodySize });

test("runtime and object bytes are split by the bundle's folder; the navigation counts as runtime", () => {
  const tally = new TransferTally("/bundles/relief/manifest.json", PAGE);
  tally.add("page", [entry(PAGE, 4000, 3700), entry("http://host/web/v/1/src/viewer.js", 900, 600),
                     entry("http://host/bundles/relief/manifest.json", 1300, 1000),
                     entry("http://host/bundles/relief/detail/0/0_0.tsd", 2300, 2000)]);
  tally.add("worker", [entry("http://host/vendor/pyodide/v/1/pyodide.asm.wasm", 2_700_300, 2_700_000),
                       entry("http://host/bundles/relief/base.tsp", 5300, 5000)]);
  assert.deepEqual(tally.summary(), { runtime: 4000 + 900 + 2_700_300, object: 1300 + 2300 + 5300,
    total: 4000 + 900 + 2_700_300 + 1300 + 2300 + 5300, objectCost: 1000 + 2000 + 5000,
    requests: 6, cached: 0 });
});

test("cache hits transfer nothing but the object still costs its bytes as served", () => {
  const tally = new TransferTally("http://host/bundles/relief/manifest.json", PAGE);
  tally.add("page", [entry("http://host/bundles/relief/manifest.json", 0, 1000),
                     entry("http://host/web/v/1/src/viewer.js", 0, 600)]);
  const summary = tally.summary();
  assert.equal(summary.total, 0);
  assert.equal(summary.objectCost, 1000);
  assert.equal(summary.cached, 2);
});

test("a file fetched twice is one cost, two transfers; add() replaces a timeline's entries", () => {
  const tally = new TransferTally("/bundles/a/manifest.json", PAGE);
  const tile = "http://host/bundles/a/detail/1/0_0.tsd";
  tally.add("page", [entry(tile, 600, 500)]);
  tally.add("worker", [entry(tile, 600, 500)]);
  assert.equal(tally.summary().objectCost, 500);
  assert.equal(tally.summary().object, 1200);
  tally.add("worker", []);
  assert.equal(tally.summary().object, 600);
  // another bundle's files (a prefix that only looks alike) are not this object's
  tally.add("page", [entry("http://host/bundles/ab/base.tsp", 700, 700)]);
  assert.equal(tally.summary().objectCost, 0);
  assert.equal(tally.summary().runtime, 700);
});
