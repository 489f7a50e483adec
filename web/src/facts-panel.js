// FactsPanel: the viewer's information panel (the #fact-* entries of templates/viewer.html):
// what the bundle is (units, sizes, surface, fit error; the source is the server's), the base
// mesh on screen, the detail tiles shown, and the bytes: what this visit transferred and
// what the object costs (showTransfer, from a TransferTally's summary). It only writes text;
// the numbers come from the manifest, the worker's reply, window.tessera.stats and the
// Resource Timing API.

import { $, formatBytes, formatLength, plural } from "./page.js";

export class FactsPanel {
  /** Write `text` into the fact `id` (absent from the page: nothing to do). */
  set(id, text) {
    const element = $(id);
    if (element) element.textContent = text;
  }

  /**
   * The bundle's facts.
   * @param {object} manifest  the bundle's manifest.json, parsed
   * @param {{patch: {units?: string, shape: number[], degree: number[], rational: boolean},
   *          patch_bytes: number}} ready  the worker's init reply
   * @param {{bytes_downloaded: number}} stats
   */
  describe(manifest, ready, stats) {
    const units = manifest.units || ready.patch.units || "unknown";
    const fit = manifest.stats || {};
    this.set("fact-units", units);
    this.set("fact-bundle", formatBytes(stats.bytes_downloaded));
    this.set("fact-patch", formatBytes(ready.patch_bytes));
    this.set("fact-grid", `${ready.patch.shape.join(" × ")} control points, degree ` +
      `${ready.patch.degree.join(", ")}` + (ready.patch.rational ? ", rational" : ""));
    this.set("fact-rms", formatLength(fit.rms, units));
    this.set("fact-max", formatLength(fit.max, units));
    // fact-source (the scan's points and the bytes of every file the fit read, a .conf's
    // range scans included) is written by the server: fitter.server.api.scan_size
  }

  /**
   * An atlas bundle's facts (manifest format_version 2): its patches instead of a patch's grid.
   * @param {object} manifest
   * @param {{patch: {kind: "atlas", patches: number, degree: number, spans: number,
   *          rational: boolean, units?: string}, patch_bytes: number}} ready
   * @param {{bytes_downloaded: number}} stats
   */
  describeAtlas(manifest, ready, stats) {
    const units = manifest.units || ready.patch.units || "unknown";
    const fit = manifest.stats || {};
    const { patches, degree, spans, rational } = ready.patch;
    this.set("fact-units", units);
    this.set("fact-bundle", formatBytes(stats.bytes_downloaded));
    this.set("fact-patch", formatBytes(ready.patch_bytes));
    this.set("fact-grid", `atlas of ${patches.toLocaleString("en")} patches, degree ${degree}, ` +
      `${plural(spans, "span")} a side` + (rational ? ", rational" : ""));
    this.set("fact-rms", formatLength(fit.rms, units));
    this.set("fact-max", formatLength(fit.max, units));
  }

  /** The atlas's groups drawn with detail (AtlasLayer's stats). */
  showAtlas(stats, groups) {
    this.set("fact-detail", stats.atlas_refined_groups
      ? `${stats.atlas_refined_groups} of ${groups} groups refined, ${stats.atlas_packs_loaded} ` +
        `packs (${formatBytes(stats.atlas_pack_bytes)} fetched), ` +
        `${stats.atlas_tessellate_ms.toFixed(0)} ms`
      : `base only (${groups} groups; zoom in for detail)`);
  }

  /**
   * The bytes of this visit and of the object (TransferTally.summary()): "This visit" is what
   * came over the network (runtime, object), "Object" what the object's files weigh as served
   * (manifest, patch, the tiles shown), whether they came from the network or the cache.
   * @param {{runtime: number, object: number, total: number, objectCost: number,
   *          requests: number, cached: number}} summary
   */
  showTransfer(summary) {
    this.set("fact-visit", `${formatBytes(summary.total)} transferred ` +
      `(runtime ${formatBytes(summary.runtime)}, object ${formatBytes(summary.object)})` +
      (summary.cached ? `; ${summary.cached} of ${summary.requests} files from the cache` : ""));
    this.set("fact-bundle", formatBytes(summary.objectCost));
  }

  /** The base mesh on screen: its size and the worker's time for it. */
  showMesh(stats) {
    this.set("fact-mesh", `${stats.vertices.toLocaleString("en")} vertices, ` +
      `${stats.triangles.toLocaleString("en")} triangles`);
    this.set("fact-time", `${stats.tessellate_ms.toFixed(0)} ms in Python (${stats.kernel} kernel)`);
  }

  /** The detail regions shown and the tiles behind them (nothing before the first update). */
  showTiles(stats) {
    if (stats.tile_updates === undefined) return;
    this.set("fact-detail", stats.regions
      ? `${stats.regions} regions, ${stats.tiles_loaded} tiles (${formatBytes(stats.tile_bytes)} fetched), ` +
        `${stats.tile_tessellate_ms.toFixed(0)} ms`
      : `base only (${stats.tile_bytes ? formatBytes(stats.tile_bytes) + " of tiles fetched" : "zoom in for detail"})`);
  }
}
