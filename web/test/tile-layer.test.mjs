// TileLayer (web/src/tile-layer.js) with a stand-in worker, viewer and fetch: the region grid
// it asks the worker for (each level's, as the worker's plan gives it), the tiles it fetches (only those the
// chosen regions need, each once, resolved against the manifest's URL), unloading and the
// error path. No WebGL, no Worker: the layer only moves messages and buffers.

import assert from "node:assert/strict";
import { afterEach, beforeEach, describe, test } from "node:test";

import { fetchBytes } from "../src/fetch-bytes.js";
import { REGION_BATCH, TileLayer } from "../src/tile-layer.js";
import { TileTree } from "../src/tile-tree.js";
import { REGION_GRIDS, camera, detailTiles, planeMesh } from "./scenes.mjs";

const PAGE = "http://tessera.test/objects/relief/";
const MANIFEST_URL = "/bundles/relief/manifest.json";
const BUNDLE = "http://tessera.test/bundles/relief/";
const HEIGHT = 600;

let fetched;
let missing;

beforeEach(() => {
  fetched = [];
  missing = new Set();
  globalThis.window = { location: { href: PAGE } };
  globalThis.fetch = async (url) => {
    fetched.push(url);
    const name = url.slice(BUNDLE.length);
    if (missing.has(name)) return new Response("no such tile", { status: 404 });
    return new Response(new TextEncoder().encode(`bytes of ${name}`));
  };
});

afterEach(() => {
  delete globalThis.window;
  delete globalThis.fetch;
});

/** A worker and viewer that record what the layer asks of them. */
function standIns(cam) {
  const worker = {
    held: new Map(), regions: [], dropped: [],
    // requests run one at a time in the order they came, as in mesh-worker.js
    queue: Promise.resolve(),
    run(job) {
      const result = this.queue.then(job);
      this.queue = result.catch(() => {});
      return result;
    },
    async addTile(name, bytes) { this.held.set(name, bytes); },
    // as mesh-worker.js's fetchTiles: fetched by the worker itself (the same fetchBytes)
    fetchTiles(tiles) {
      return this.run(async () => {
        const fetchedHere = await Promise.all(tiles.map(async ({ name, url }) =>
          ({ name, bytes: await fetchBytes(url, name) })));
        return fetchedHere.map(({ name, bytes }) => {
          this.held.set(name, bytes);
          return { name, bytes: bytes.length };
        });
      });
    },
    async dropTiles(names) {
      this.dropped.push(...names);
      for (const name of names) this.held.delete(name);
    },
    batches: [],
    regionBatch(regions) {
      return this.run(async () => {
        for (const { names } of regions) {
          for (const name of names) {
            if (!this.held.has(name)) throw new Error(`detail tile ${name} was not handed over`);
          }
        }
        this.batches.push(regions.length);
        return regions.map(({ level, i, j, grid, names, skirtDepth }) => {
          this.regions.push({ level, i, j, grid, names, skirtDepth });
          return { tessellate_ms: 2, level, i, j, grid };
        });
      });
    },
  };
  const viewer = {
    camera: cam, renderer: { domElement: { height: HEIGHT } }, shown: null, baseTexture: "unset",
    makeRegionMesh(data, texture, rect) { return { data, texture, rect }; },
    setRegions(regions, mask) { this.shown = { regions, mask }; },
    setBaseTexture(texture) { this.baseTexture = texture; },
    draws: 0,
    async whenDrawn() { this.draws += 1; },
  };
  return { worker, viewer };
}

function layerFor(tiles, cam, errors = [], regionGrids = REGION_GRIDS) {
  const { worker, viewer } = standIns(cam);
  const stats = { bytes_downloaded: 0 };
  const layer = new TileLayer({ viewer, worker, manifest: { tiles, transform: null },
                                manifestUrl: MANIFEST_URL, regionGrids, stats,
                                onError: (message) => errors.push(message) });
  const mesh = planeMesh();
  layer.setBase(mesh, mesh.domain);
  return { layer, worker, viewer, stats };
}

describe("tile layer", () => {
  test("regions are tessellated on their level's grid with their tiles, fetched once", async () => {
    const errors = [0.8, 0.4, 0.2];
    const tiles = detailTiles(errors, { spans: 64 });
    const close = camera([20, 30, 25], [30, 40, 0]);
    const { layer, worker, viewer, stats } = layerFor(tiles, close);
    assert.deepEqual([0, 1, 2].map((k) => layer.regionGrid(k)), [41, 21, 11]);
    await layer.update();

    // the regions TileTree picks for this camera, each with its chain of tiles
    const reference = new TileTree(tiles, null, REGION_GRIDS);
    const mesh = planeMesh();
    reference.setBounds(mesh.positions, mesh.uvs, mesh.domain, reference.baseError);
    const leaves = reference.select(close, HEIGHT);
    assert.ok(leaves.length > 4, leaves.length);
    const key = (r) => `${r.level}/${r.i}/${r.j}`;
    assert.deepEqual(worker.regions.map(key).sort(), leaves.map(key).sort());
    const nodes = new Map(tiles.detail.nodes.map((node) => [key(node), node]));
    for (const region of worker.regions) {
      assert.equal(region.grid, REGION_GRIDS[region.level]);
      const chain = [];
      for (let k = 0; k <= region.level; k++) {
        chain.push(nodes.get(`${k}/${region.i >> (region.level - k)}/${region.j >> (region.level - k)}`).file);
      }
      assert.deepEqual(region.names, chain); // coarsest first
      assert.equal(region.skirtDepth, 2 * errors[region.level]);
    }
    const needed = new Set(worker.regions.flatMap((region) => region.names));
    assert.deepEqual([...fetched].sort(), [...needed].map((name) => BUNDLE + name).sort());
    assert.deepEqual([...worker.held.keys()].sort(), [...needed].sort());
    const bytes = [...needed].reduce((sum, name) => sum + `bytes of ${name}`.length, 0);
    assert.equal(stats.tile_bytes, bytes);
    assert.equal(stats.bytes_downloaded, bytes);
    assert.equal(stats.tiles_fetched, needed.size);
    assert.equal(stats.regions, leaves.length);
    assert.equal(stats.tiles_loaded, needed.size);
    assert.equal(stats.tile_tessellate_ms, 2 * leaves.length);
    assert.equal(viewer.shown.regions.size, leaves.length);
    assert.equal(viewer.shown.mask.cells, 4); // 2^maxLevel cells per side
    assert.equal(viewer.baseTexture, null); // no texture tiles

    // the same view again: nothing fetched, nothing tessellated
    fetched.length = 0;
    const made = worker.regions.length;
    layer.schedule(0);
    await layer.idle();
    assert.equal(fetched.length, 0);
    assert.equal(worker.regions.length, made);
    assert.equal(stats.tile_updates, 2);

    // far away: the base suffices, every tile is dropped
    layer.viewer.camera = camera([50, 50, 5000], [50, 50, 0]);
    await layer.update();
    assert.deepEqual(worker.dropped.sort(), [...needed].sort());
    assert.equal(worker.held.size, 0);
    assert.equal(stats.regions, 0);
    assert.equal(stats.tiles_loaded, 0);
    assert.equal(fetched.length, 0);
  });

  test("a tile that cannot be fetched stops the layer with its name", async () => {
    const tiles = detailTiles([0.8, 0.4]);
    missing.add("detail/0/0_0.tsd");
    const errors = [];
    const { layer, worker } = layerFor(tiles, camera([50, 50, 60], [50, 50, 0]), errors);
    await layer.update();
    assert.equal(errors.length, 1);
    assert.match(errors[0], /^detail tiles: cannot fetch detail\/0\/0_0\.tsd \(http:\/\/tessera\.test\/bundles\/relief\/detail\/0\/0_0\.tsd\): HTTP 404$/);
    assert.equal(layer.enabled, false);
    assert.equal(worker.regions.length, 0);
  });

  test("a layer without a region grid for each level of its tiles is refused", () => {
    const tiles = detailTiles([0.8, 0.4]);
    assert.throws(() => layerFor(tiles, camera([50, 50, 60], [50, 50, 0]), [], [33]),
                  /no region grid for level 1 .*got undefined/);
    assert.throws(() => layerFor(tiles, camera([50, 50, 60], [50, 50, 0]), [], null),
                  /no region grid for level 0/);
  });

  test("a bundle without tiles makes no layer work", async () => {
    const { layer, worker } = layerFor(null, camera([50, 50, 10], [50, 50, 0]));
    assert.equal(layer.enabled, false);
    assert.equal(layer.regionGrid(0), null);
    await layer.update();
    assert.equal(worker.regions.length, 0);
    assert.equal(fetched.length, 0);
  });

  test("new regions go in batches, most projected error first; a view seen again comes from the cache", async () => {
    const errors = [0.8, 0.4, 0.2];
    const tiles = detailTiles(errors, { spans: 16 });
    const close = camera([20, 30, 25], [30, 40, 0]);
    const { layer, worker, viewer, stats } = layerFor(tiles, close);
    await layer.update();
    const count = worker.regions.length;
    assert.ok(count > REGION_BATCH, count);
    assert.ok(worker.batches.every((size) => size <= REGION_BATCH), worker.batches);
    assert.equal(worker.batches.length, Math.ceil(count / REGION_BATCH));
    // the order the worker made them in: projected error never increases
    const reference = new TileTree(tiles, null, REGION_GRIDS);
    const mesh = planeMesh();
    reference.setBounds(mesh.positions, mesh.uvs, mesh.domain, reference.baseError);
    const sse = new Map(reference.select(close, HEIGHT).map((l) => [`${l.level}/${l.i}/${l.j}`, l.sse]));
    const order = worker.regions.map((r) => sse.get(`${r.level}/${r.i}/${r.j}`));
    assert.deepEqual(order, [...order].sort((a, b) => b - a));
    assert.equal(viewer.draws, 1); // drawn once, when swapped in
    assert.equal(stats.tile_tessellate_ms, 2 * count);
    assert.ok(stats.tile_refine_ms >= 0 && stats.tile_timing.made === count);

    // away (the base alone), then back: the regions come from the cache, no worker call
    layer.viewer.camera = camera([50, 50, 5000], [50, 50, 0]);
    await layer.update();
    assert.equal(stats.regions, 0);
    layer.viewer.camera = close;
    await layer.update();
    assert.equal(worker.regions.length, count);
    assert.equal(stats.regions, count);
    assert.equal(stats.regions_cached, count);
    assert.equal(stats.tile_tessellate_ms, 0); // this refinement ran no Python
    assert.equal(viewer.draws, 3);
    // nothing changed: no draw
    await layer.update();
    assert.equal(viewer.draws, 3);
  });

  test("a camera that moves on stops the batches; the next update shows its view", async () => {
    const errors = [0.8, 0.4, 0.2];
    const tiles = detailTiles(errors, { spans: 16 });
    const close = camera([20, 30, 25], [30, 40, 0]);
    const { layer, worker, viewer, stats } = layerFor(tiles, close);
    const regionBatch = worker.regionBatch.bind(worker);
    let first = true;
    worker.regionBatch = async (regions) => {
      if (first) { // the camera moves on while the first batch is being made
        first = false;
        layer.viewer.camera = camera([70, 60, 25], [70, 60, 0]);
        layer.update(); // as schedule() would, once due: marks the running update stale
      }
      return regionBatch(regions);
    };
    await layer.update();
    await layer.idle();
    // two batches had been sent (two in flight), no more for the old view
    const reference = new TileTree(tiles, null, REGION_GRIDS);
    const mesh = planeMesh();
    reference.setBounds(mesh.positions, mesh.uvs, mesh.domain, reference.baseError);
    const key = (r) => `${r.level}/${r.i}/${r.j}`;
    const now = reference.select(layer.viewer.camera, HEIGHT).map(key).sort();
    assert.deepEqual([...viewer.shown.regions.keys()].sort(), now);
    const old = new Set(reference.select(close, HEIGHT).map(key));
    const wasted = worker.regions.filter((r) => old.has(key(r)) && !now.includes(key(r)));
    assert.ok(wasted.length <= 2 * REGION_BATCH, wasted.length);
    assert.equal(stats.regions, now.length);
    assert.equal(viewer.draws, 1); // the stale view was never swapped in
  });
});
