// TileTree (web/src/tile-tree.js): the manifest's tile tree, the region grid, node boxes and
// the choice of regions by projected error e f / d > 2 px, frustum, budget and texel size.

import assert from "node:assert/strict";
import { describe, test } from "node:test";

import { DETAIL_PX, MAX_REGIONS, TEXEL_PX, TileTree } from "../src/tile-tree.js";
import {
  REGION_GRIDS, boxDistance, boxInView, camera, completeNodes, detailTiles, mapPositions, planeMesh,
  rigidFrame,
} from "./scenes.mjs";

const HEIGHT = 600; // drawing buffer height: focal length 300 px with the 90° test camera
const FOCAL = HEIGHT / 2;

function treeOver(tiles, { side = 100, frame = null, height = undefined } = {}) {
  const tree = new TileTree(tiles, frame, REGION_GRIDS);
  const mesh = planeMesh(side, 33, height);
  const positions = frame ? mapPositions(mesh.positions, frame) : mesh.positions;
  tree.setBounds(positions, mesh.uvs, mesh.domain, tree.baseError);
  return tree;
}

const ids = (leaves) => leaves.map(({ level, i, j }) => `${level}/${i}/${j}`).sort();

describe("region grid", () => {
  test("each level's grid is the one the plan gives, whatever spans_per_tile says", () => {
    // the rule is client_py's (bundle.drawn_region_resolution): the tree has no copy of it
    for (const spans of [16, 64]) {
      const tree = new TileTree(detailTiles([1, 0.5, 0.2], { spans }), null, REGION_GRIDS);
      assert.deepEqual([0, 1, 2].map((k) => tree.regionGrid(k)), [41, 21, 11]);
    }
    const tree = new TileTree(detailTiles([1, 0.5]), null, [257, 129, 65, 33]);
    assert.deepEqual([tree.regionGrid(0), tree.regionGrid(1)], [257, 129]);
  });

  test("a tree with tiles but no valid grid up to its finest level is an error naming the level", () => {
    const tiles = detailTiles([1, 0.5, 0.2]);
    for (const [grids, pattern] of [
      [null, /no region grid for level 0 .*got undefined/],
      [[33, 17], /no region grid for level 2 .*got undefined/],
      [[33, 1, 9], /no region grid for level 1 .*got 1$/],
      [[33, 16.5, 9], /no region grid for level 1 .*got 16\.5/],
      [[33, "17", 9], /no region grid for level 1 .*got "17"/],
    ]) {
      assert.throws(() => new TileTree(tiles, null, grids), pattern);
    }
    // texture tiles alone still make regions: they need a grid too
    const texture = { texture: { size: 256, nodes: completeNodes([0], "texture", "webp") } };
    assert.throws(() => new TileTree(texture), /no region grid for level 0/);
    assert.equal(new TileTree(texture, null, [5]).regionGrid(0), 5);
  });

  test("no tiles: an empty tree, no grid", () => {
    for (const tiles of [null, {}, { detail: null, texture: null }]) {
      const tree = new TileTree(tiles);
      assert.equal(tree.empty, true);
      assert.equal(tree.regionGrid(0), null);
    }
  });
});

describe("tile tree", () => {
  test("malformed nodes are rejected, naming the node", () => {
    const tiles = detailTiles([1]);
    for (const [node, pattern] of [
      [{ level: -1, i: 0, j: 0, file: "a" }, /level is not a valid index/],
      [{ level: 0, i: 0.5, j: 0, file: "a" }, /i is not a valid index/],
      [{ level: 1, i: 0, j: 2, file: "a" }, /outside its level/],
      [{ level: 1, i: 0, j: 0 }, /has no file/],
    ]) {
      tiles.detail.nodes = [node];
      assert.throws(() => new TileTree(tiles, null, REGION_GRIDS), pattern);
    }
  });

  test("chains, texture nodes and errors of a sparse tree", () => {
    const nodes = [
      { level: 0, i: 0, j: 0, file: "d0", geometric_error: 1 },
      { level: 1, i: 1, j: 0, file: "d1", geometric_error: 0.5 },
      { level: 2, i: 2, j: 1, file: "d2", geometric_error: 0.2 },
    ];
    const tree = new TileTree({
      detail: { spans_per_tile: 8, base: { max: 3 }, nodes },
      texture: { size: 128, nodes: [{ level: 0, i: 0, j: 0, file: "t0" }, { level: 1, i: 1, j: 0, file: "t1" }] },
    }, null, [17, 9, 5]);
    assert.equal(tree.maxLevel, 2);
    assert.equal(tree.regionGrid(2), 5);
    assert.deepEqual(tree.detailChain(2, 2, 1).map((n) => n.file), ["d0", "d1", "d2"]);
    assert.deepEqual(tree.detailChain(2, 3, 1).map((n) => n.file), ["d0", "d1"]); // 2/3/1 absent
    assert.deepEqual(tree.detailChain(2, 0, 3).map((n) => n.file), ["d0"]);
    assert.equal(tree.detailError(-1, 0, 0), 3);
    assert.equal(tree.detailError(2, 2, 1), 0.2);
    assert.equal(tree.detailError(2, 3, 1), 0.5); // nearest present ancestor's bound
    assert.equal(tree.detailError(1, 0, 1), 1);
    assert.equal(tree.textureNode(2, 3, 0).file, "t1");
    assert.equal(tree.textureNode(2, 0, 3).file, "t0");
    assert.equal(tree.textureNode(-1, 0, 0), null);
    assert.deepEqual(TileTree.rect(2, 1, 3), [0.25, 0.75, 0.5, 1]);
  });

  test("node boxes hold their part of the surface, within a grid step and the margin", () => {
    const { frame } = rigidFrame(0.7, 0.4, [5, -3, 12]);
    const side = 100, margin = 1.5;
    const height = (u, v) => 6 * Math.sin(2 * Math.PI * u) * Math.cos(Math.PI * v);
    const tree = treeOver(detailTiles([2, 1, 0.5, 0.25], { baseMax: margin }), { side, frame, height });
    const step = 1 / 32; // one grid step of the 33 x 33 base (normalised)
    const eps = 1e-3;
    /** x, y, z ranges of the exact surface over [u0, u1] x [v0, v1] (dense samples) */
    const extent = (u0, u1, v0, v1) => {
      const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
      for (let a = 0; a <= 64; a++) {
        for (let b = 0; b <= 64; b++) {
          const u = u0 + (u1 - u0) * a / 64, v = v0 + (v1 - v0) * b / 64;
          [u * side, v * side, height(u, v)].forEach((x, c) => {
            lo[c] = Math.min(lo[c], x);
            hi[c] = Math.max(hi[c], x);
          });
        }
      }
      return { lo, hi };
    };
    for (let level = 0; level <= 3; level++) {
      const n = 2 ** level;
      for (let i = 0; i < n; i++) {
        for (let j = 0; j < n; j++) {
          const box = tree.box(level, i, j);
          const min = [box.min.x, box.min.y, box.min.z], max = [box.max.x, box.max.y, box.max.z];
          const inner = extent(i / n, (i + 1) / n, j / n, (j + 1) / n);
          const outer = extent(Math.max(i / n - step, 0), Math.min((i + 1) / n + step, 1),
                               Math.max(j / n - step, 0), Math.min((j + 1) / n + step, 1));
          for (let c = 0; c < 3; c++) {
            const where = `${level}/${i}/${j} axis ${c}: [${min[c]}, ${max[c]}]`;
            // holds the node's surface, padded by the margin ...
            assert.ok(min[c] <= inner.lo[c] - margin + eps && max[c] >= inner.hi[c] + margin - eps,
                      `${where} vs [${inner.lo[c]}, ${inner.hi[c]}]`);
            // ... and no more than the surface within one grid step of it
            assert.ok(min[c] >= outer.lo[c] - margin - eps && max[c] <= outer.hi[c] + margin + eps,
                      `${where} vs [${outer.lo[c]}, ${outer.hi[c]}]`);
          }
        }
      }
    }
  });
});

/** The regions an unbudgeted refinement shows (a reference written apart from TileTree.select):
 *  a node in view is split while e f / d > detailPx and a finer node lies below it. */
function referenceLeaves(tree, tiles, cam, inverse, errors, baseMax) {
  const eye = inverse([cam.position.x, cam.position.y, cam.position.z]);
  const frame = tiles.transform;
  const deepest = errors.length - 1;
  const leaves = [];
  const visit = (level, i, j) => {
    const box = tree.box(level, i, j);
    const min = [box.min.x, box.min.y, box.min.z], max = [box.max.x, box.max.y, box.max.z];
    if (!boxInView(cam, min, max, frame)) return;
    const error = level < 0 ? baseMax : errors[level];
    const sse = error * FOCAL / Math.max(boxDistance(eye, min, max), cam.near);
    if (level < deepest && sse > DETAIL_PX) {
      if (level < 0) visit(0, 0, 0);
      else for (const [di, dj] of [[0, 0], [0, 1], [1, 0], [1, 1]]) visit(level + 1, 2 * i + di, 2 * j + dj);
    } else if (level >= 0) {
      leaves.push({ level, i, j, sse });
    }
  };
  visit(-1, 0, 0);
  return leaves;
}

describe("selection by projected error", () => {
  test("the base is refined exactly while e f / d > 2 px", () => {
    // one level-0 tile; the base's error 1 pads the box by 1: from straight above the
    // centre at height h, d = h - 1 and e f / d > 2 while h < 151
    const tree = treeOver(detailTiles([0.5]));
    assert.deepEqual(tree.select(camera([50, 50, 152], [50, 50, 0]), HEIGHT), []);
    const leaves = tree.select(camera([50, 50, 150], [50, 50, 0]), HEIGHT);
    assert.deepEqual(ids(leaves), ["0/0/0"]);
    assert.ok(Math.abs(leaves[0].sse - 0.5 * FOCAL / 149) < 1e-9, leaves[0].sse);
  });

  test("each level is refined at its own error's distance", () => {
    // level 0 (e 0.8) splits while h - 1 < 120, level 1 (e 0.4; the camera above the corner
    // all four share) while h - 1 < 60; level 2 is the finest
    const tree = treeOver(detailTiles([0.8, 0.4, 0.1]));
    const at = (h) => ids(tree.select(camera([50, 50, h], [50, 50, 0]), HEIGHT));
    assert.deepEqual(at(122), ["0/0/0"]);
    assert.deepEqual(at(120), ["1/0/0", "1/0/1", "1/1/0", "1/1/1"]);
    assert.deepEqual(at(62), ["1/0/0", "1/0/1", "1/1/0", "1/1/1"]);
    assert.equal(at(60).length, 16);
    assert.ok(at(60).every((id) => id.startsWith("2/")));
  });

  test("an oblique view matches the reference, and what is out of view is not shown", () => {
    const { frame, inverse } = rigidFrame(0.9, -0.5, [-20, 40, 7]);
    const errors = [2, 1, 0.5, 0.25, 0.12];
    const tiles = { ...detailTiles(errors, { baseMax: 3 }), transform: frame };
    const tree = treeOver(tiles, { frame });
    // low over the patch's middle, looking along it: what lies behind is culled
    const eye = mapPositions(new Float32Array([50, 45, 6]), frame);
    const target = mapPositions(new Float32Array([90, 60, 0]), frame);
    const cam = camera([...eye], [...target]);
    const leaves = tree.select(cam, HEIGHT, { maxRegions: 10000 });
    const reference = referenceLeaves(tree, tiles, cam, inverse, errors, 3);
    assert.deepEqual(ids(leaves), ids(reference));
    // the view is partial: fewer regions than a full cover at the finest level shown
    const levels = new Set(leaves.map((leaf) => leaf.level));
    assert.ok(levels.size > 1, [...levels]);
    const area = leaves.reduce((sum, leaf) => sum + 4 ** -leaf.level, 0);
    assert.ok(area < 1, `regions cover ${area} of the patch: nothing was culled`);
    for (const leaf of leaves) {
      const match = reference.find((r) => r.level === leaf.level && r.i === leaf.i && r.j === leaf.j);
      assert.ok(Math.abs(leaf.sse - match.sse) < 1e-6 * match.sse, `${leaf.sse} vs ${match.sse}`);
    }
  });

  test("at most 48 regions, the neediest split first", () => {
    const errors = [4, 2, 1, 0.5, 0.25, 0.12, 0.06];
    const tree = treeOver(detailTiles(errors, { baseMax: 8 }));
    const cam = camera([50, 50, 20], [50, 50, 0]); // close: the uncapped refinement is deep
    const uncapped = tree.select(cam, HEIGHT, { maxRegions: 100000 });
    assert.ok(uncapped.length > 4 * MAX_REGIONS, uncapped.length);
    const capped = tree.select(cam, HEIGHT);
    assert.ok(capped.length <= MAX_REGIONS && capped.length >= MAX_REGIONS - 2, capped.length);
    // the capped regions cover the uncapped ones, coarser (a node left whole may show parts
    // its split would have culled)
    for (const leaf of uncapped) {
      assert.ok(capped.some((c) => c.level <= leaf.level &&
                            leaf.i >> (leaf.level - c.level) === c.i && leaf.j >> (leaf.level - c.level) === c.j));
    }

    // budget 7: the level-0 node splits (4 regions), then only the neediest level-1 node
    // (the one nearest the camera, above the patch's corner (0, 0)) splits into 4
    const corner = camera([10, 10, 40], [10, 10, 0]);
    const seven = tree.select(corner, HEIGHT, { maxRegions: 7 });
    assert.deepEqual(ids(seven), ["1/0/1", "1/1/0", "1/1/1", "2/0/0", "2/0/1", "2/1/0", "2/1/1"]);
  });

  test("texture tiles refine while a texel exceeds 1.5 px", () => {
    // no detail tile, flat boxes (margin 0): a level-0 texture of 256 texels over 100 units
    // seen from straight above at height h shows texels of (100 / 256) f / h pixels
    const tiles = {
      detail: { spans_per_tile: 16, base: { max: 0 }, nodes: [] },
      texture: { format: "webp", size: 256, nodes: completeNodes([0, 1], "texture", "webp") },
    };
    const tree = treeOver(tiles);
    const limit = (100 / 256) * FOCAL / TEXEL_PX; // 78.125
    assert.deepEqual(ids(tree.select(camera([50, 50, limit + 0.2], [50, 50, 0]), HEIGHT)), ["0/0/0"]);
    assert.deepEqual(ids(tree.select(camera([50, 50, limit - 0.2], [50, 50, 0]), HEIGHT)),
                     ["1/0/0", "1/0/1", "1/1/0", "1/1/1"]);
    // a coarser texel budget stops the split
    assert.deepEqual(ids(tree.select(camera([50, 50, limit - 0.2], [50, 50, 0]), HEIGHT, { texelPx: 2 })),
                     ["0/0/0"]);
  });

  test("nothing is selected before the boxes are known or when looking away", () => {
    const tree = new TileTree(detailTiles([0.5, 0.2]), null, REGION_GRIDS);
    assert.deepEqual(tree.select(camera([50, 50, 10], [50, 50, 0]), HEIGHT), []);
    tree.setBounds(planeMesh().positions, planeMesh().uvs, [0, 1, 0, 1], tree.baseError);
    assert.ok(tree.select(camera([50, 50, 10], [50, 50, 0]), HEIGHT).length > 0);
    assert.deepEqual(tree.select(camera([50, 50, 10], [50, 50, 100]), HEIGHT), []);
  });
});
