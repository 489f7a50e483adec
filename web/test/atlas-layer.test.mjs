// AtlasLayer.batches (web/src/atlas-layer.js): the way from the levels on screen to the
// levels the camera wants, a batch at a time. No WebGL, no Worker: a stand-in viewer and
// worker, and the refinement table of a few groups.

import assert from "node:assert/strict";
import { beforeEach, describe, test } from "node:test";

import { AtlasLayer, BATCH_VERTICES } from "../src/atlas-layer.js";

beforeEach(() => {
  globalThis.window = { location: { href: "http://tessera.test/objects/atlas/" } };
});

/** A layer over `counts` groups of patches in a row (each the neighbour of the next), drawn
 *  at 9, 17 and 33 samples a patch side at levels -1, 0 and 1. */
function layer(counts) {
  const groups = counts.map((count, g) => ({
    first: 0, count, center: [g, 0, 0], radius: 0.5, packs: [null, null], bytes: [0, 0],
    errors: [1, 0.5], neighbours: [g - 1, g + 1].filter((h) => h >= 0 && h < counts.length),
  }));
  return new AtlasLayer({
    viewer: {}, worker: {}, manifestUrl: "/bundles/atlas/manifest.json", stats: {},
    refinement: { groups, base_error: 2, levels: 2, resolutions: [9, 17, 33] },
  });
}

describe("AtlasLayer.batches", () => {
  test("the first raises granted go first, about BATCH_VERTICES, then the rest", () => {
    const atlas = layer([200, 200, 200, 200]); // a group at level 1: 200 x 33^2 = 217,800
    const steps = [2, 2, 1, 1, 3, 0];
    const levels = [0, 1, 1, 0];
    const batches = atlas.batches(levels, steps);
    assert.equal(batches.length, 2, JSON.stringify(batches));
    // group 2 first, alone: to level 0 (with its neighbours 1 and 3 at the base, 90,200
    // vertices to make), then to level 1 (217,800 + 32,400 more), past BATCH_VERTICES
    assert.deepEqual(batches[0], [-1, -1, 1, -1]);
    assert.deepEqual(batches[1], levels);
    assert.ok(200 * 17 * 17 + 2 * 200 * 9 * 9 < BATCH_VERTICES);
  });

  test("groups that go down go in the first batch; a small change is one batch", () => {
    const atlas = layer([10, 10, 10]);
    atlas.shown = [1, 1, -1];
    assert.deepEqual(atlas.batches([-1, 0, 0], [2]), [[-1, 0, 0]]);
    const big = layer([300, 300, 300]);
    big.shown = [1, -1, -1];
    const batches = big.batches([-1, 1, 0], [1, 1, 2]);
    assert.deepEqual(batches[0][0], -1);
    assert.deepEqual(batches[batches.length - 1], [-1, 1, 0]);
  });

  test("levels already shown are not raised again", () => {
    const atlas = layer([300, 300]);
    atlas.shown = [1, -1];
    assert.deepEqual(atlas.batches([1, 0], [0, 0, 1]), [[1, 0]]);
  });
});
