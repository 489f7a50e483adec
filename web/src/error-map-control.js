// ErrorMapControl: the viewer's "Error map" button and legend over the bundle's fit-error grid
// (manifest.error_grid, read by ErrorMap). A bundle without a grid, or with a malformed one,
// leaves the button disabled (its title says why); pressed, it lays the grid's colours over
// the base and shows the legend. A base PLY written while it is shown takes its colours.

import { ErrorMap } from "./error-map.js";
import { $, formatLength } from "./page.js";

export class ErrorMapControl {
  /**
   * @param {object} manifest  the bundle's manifest.json, parsed
   * @param {import("./viewer.js").Viewer} viewer
   */
  constructor(manifest, viewer) {
    this.viewer = viewer;
    this.button = $("toggle-error");
    this.errorMap = null;
    const units = manifest.units || "";
    if (manifest.error_grid) {
      try {
        this.errorMap = new ErrorMap(manifest.error_grid, units);
      } catch (error) { // a malformed grid: no error map, said so on the button
        this.button.title = error.message;
      }
    }
    if (this.errorMap) {
      $("legend-bar").style.background = this.errorMap.cssGradient();
      $("legend-max").textContent = formatLength(this.errorMap.max, units);
      this.button.disabled = false;
    }
    this.button.addEventListener("click", () => this.toggle());
  }

  /** Whether the error map is laid over the base now. */
  get shown() {
    return this.button.getAttribute("aria-pressed") === "true";
  }

  toggle() {
    const on = !this.shown && this.errorMap !== null;
    this.button.setAttribute("aria-pressed", String(on));
    const map = this.errorMap;
    this.viewer.setErrorOverlay(on ? { rgba: map.rgba(), cols: map.cols, rows: map.rows } : null);
    $("legend").hidden = !on;
  }

  /** RGB per vertex of `uvs` (patch parameters in `domain`) while the map is shown, else null. */
  vertexColors(uvs, domain) {
    return this.shown ? this.errorMap.vertexColors(uvs, domain) : null;
  }
}
