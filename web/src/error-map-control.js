// ErrorMapControl: the viewer's "Error map" button and legend over the bundle's fit error
// (manifest.error_raster, read by ErrorMap: the largest distance to the scan near each vertex,
// interpolated per vertex). A bundle without one, or with a malformed one, leaves the button
// disabled (its title says why); pressed, it lays the map's colours over the base and shows
// the legend: the colour scale from 0 to the map's max in the bundle's units — the fitter
// writes the statistics' max there, so the legend ends at the panel's "max" (FactsPanel, the
// same formatLength) — and the colour of no scan point (holes, uncovered parts). A base PLY
// written while it is shown takes its colours. An atlas's map is shown by the `show` given
// (AtlasLayer.showErrorMap: the worker colours its meshes per vertex), not by the overlay. A
// single patch's cells in a file (ErrorMap.load) are fetched when the map is first pressed.

import { cssColor, ErrorMap, HOLE_COLOR } from "./error-map.js";
import { $, formatLength } from "./page.js";

export class ErrorMapControl {
  /**
   * @param {object} manifest  the bundle's manifest.json, parsed
   * @param {import("./viewer.js").Viewer} viewer
   * @param {{show?: (errorMap: ErrorMap|null) => Promise<void>}} [options]  how the map is
   *   shown (default: the viewer's overlay over the single patch's (u, v))
   * @param {URL|string} [options.baseUrl]  the manifest's URL, against which the map's file
   *   is fetched (default: the page's)
   */
  constructor(manifest, viewer, { show = null, baseUrl = null } = {}) {
    this.viewer = viewer;
    this.baseUrl = baseUrl;
    this.show = show ?? (async (map) => viewer.setErrorOverlay(map ? map.rgba() : null));
    this.button = $("toggle-error");
    this.errorMap = null;
    try {
      this.errorMap = ErrorMap.fromManifest(manifest);
    } catch (error) { // a malformed map: no error map, said so on the button
      this.button.title = error.message;
    }
    if (this.errorMap) {
      $("legend-bar").style.background = this.errorMap.cssGradient();
      $("legend-max").textContent = formatLength(this.errorMap.max, manifest.units || "unknown");
      $("legend-what").textContent = this.errorMap.statistic;
      $("legend-hole-swatch").style.background = cssColor(HOLE_COLOR);
      this.button.disabled = false;
    }
    this.button.addEventListener("click", () => this.toggle());
  }

  /** Whether the error map is laid over the base now. */
  get shown() {
    return this.button.getAttribute("aria-pressed") === "true";
  }

  /** Show or hide the map; resolves when it is drawn (document.body.dataset.errorMapBusy
   *  is "1" meanwhile; a failure goes to the button's title and hides the map again). */
  async toggle() {
    const on = !this.shown && this.errorMap !== null;
    this.button.disabled = true;
    document.body.dataset.errorMapBusy = "1";
    try {
      // pressed only once the cells are here: vertexColors (a PLY written meanwhile) reads them
      if (on) await this.errorMap.load(this.baseUrl ?? globalThis.location?.href);
      this.button.setAttribute("aria-pressed", String(on));
      await this.show(on ? this.errorMap : null);
      $("legend").hidden = !on;
      // the panel scrolls: below a long title and the facts the legend may start out of sight
      if (on) $("legend").scrollIntoView({ block: "nearest" });
    } catch (error) {
      this.button.setAttribute("aria-pressed", "false");
      this.button.title = `The error map failed: ${error.message}`;
      $("legend").hidden = true;
    } finally {
      this.button.disabled = false;
      delete document.body.dataset.errorMapBusy;
    }
  }

  /** RGB per vertex of `uvs` (patch parameters in `domain`) while the map is shown, else null. */
  vertexColors(uvs, domain) {
    return this.shown ? this.errorMap.vertexColors(uvs, domain) : null;
  }
}
