// PlyDownload: the viewer's "Download PLY" control. It writes the level chosen next to it
// (#ply-level): "base", the mesh on screen (with the error map's colours when it is shown), or
// detail level L: every detail tile of levels 0..L is fetched (those the worker already holds
// are not) and the worker tessellates the whole patch with them on the level's R x R grid
// (the plan's levels[L].resolution, client_py.bundle.drawn_level_resolution), as
// `tessera tessellate OUTDIR --level L`; a bundle with texture tiles gives the vertices
// colours sampled from them (decoded here, sampled by client_py in the worker; page.js
// levelPly, on the worker's plan of each level: client_py.bundle.plan_level).
// Its stats: ply_level (-1 base), ply_bytes (the file's size), ply_vertices, ply_resolution,
// ply_ms (Python), ply_total_ms (fetch + tessellate + write), ply_tiles_fetched,
// ply_fetch_bytes (detail tiles), ply_textures, ply_texture_bytes (texture tiles fetched),
// ply_progress (the shares of an atlas's tessellation the worker reported, shown as a
// percentage in #ply-status);
// document.body.dataset.plyBusy is "1" while a PLY is being made, and #ply-status (under the
// buttons) says what is being done, then the file written. "Open in 3DHOP" follows the level
// chosen (its ?level=L).

import { $, formatBytes, levelOption, levelPly } from "./page.js";

const REVOKE_AFTER_MS = 10000; // the download has started by then

/** Offer `bytes` as a download named `name`. */
function saveFile(bytes, name) {
  const url = URL.createObjectURL(new Blob([bytes], { type: "application/octet-stream" }));
  const link = document.createElement("a");
  link.href = url;
  link.download = name;
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), REVOKE_AFTER_MS);
}

export class PlyDownload {
  /**
   * @param {{worker: import("./mesh-worker-client.js").MeshWorkerClient,
   *          base: import("./base-mesh.js").BaseMesh,
   *          errorMap: import("./error-map-control.js").ErrorMapControl,
   *          config: {ply_name: string, manifest_url: string, hop_url?: string},
   *          stats: object, onError: (message: string) => void}} options
   */
  constructor({ worker, base, errorMap, config, stats, onError }) {
    this.worker = worker;
    this.base = base;
    this.errorMap = errorMap;
    this.config = config;
    this.stats = stats;
    this.onError = onError;
    this.select = $("ply-level");
    this.button = $("download-ply");
    this.levels = []; // entries of the worker's plan (MeshWorkerClient.plan), one per level
    this.atlas = false; // an atlas bundle: "base" is a level PLY too (offerAtlasLevels)
    this.button.addEventListener("click", () => this.download(Number(this.select.value)));
  }

  /** The base PLY alone: the level choice stays hidden, `reason` in its title. */
  offerBaseOnly(reason) {
    this.select.title = reason;
    console.warn(reason);
    this.button.disabled = false;
  }

  /**
   * Offer the base and every level of `plan` (MeshWorkerClient.plan's reply).
   * @param {{levels: object[], max_resolution: number, spans_per_tile: number}} plan
   * @param {string} units  the bundle's length units, for the RMS of each level
   * @param {boolean} textured  the bundle has texture tiles (a level PLY has colours)
   */
  offerLevels(plan, units, textured) {
    this.levels = plan.levels;
    const select = this.select;
    for (const choice of this.levels) select.append(levelOption(choice, units));
    if (this.levels.length) {
      select.title = "Level of detail of the PLY. base: the mesh on screen (with the error map's " +
        "colours when it is shown). level L: the base with every detail tile of levels 0..L " +
        "(their total size is shown; tiles already loaded are not fetched again), the RMS " +
        "distance to the scan at that level, tessellated over the whole object on the R × R " +
        "grid shown: two vertices per knot span of the level's tiles, finer at the coarse " +
        `levels (at most ${plan.max_resolution})` + (textured
          ? "; with the object's colours sampled from its texture tiles (size included)." : ".");
      select.hidden = false;
      select.disabled = false;
      this._followWithHopLink();
    }
    this.button.disabled = false;
  }

  /**
   * An atlas bundle's levels: `base` (page.js atlasBaseChoice: the welded atlas at
   * base.resolution samples per patch side) and every level of `plan`, each one welded PLY
   * of the whole object with the packs of levels 0..L.
   */
  offerAtlasLevels(plan, units, base) {
    this.atlas = true;
    this.offerLevels(plan, units, base.texture_nodes.length > 0); // coloured from colour packs
    this.levels = [base, ...plan.levels];
    this.select.options[0].textContent = "base (the atlas alone)";
    this.select.title = "Level of detail of the PLY, one welded mesh of every patch: base, the " +
      `atlas alone (${base.resolution} samples per patch side); level L: with every detail ` +
      "pack of levels 0..L (their size shown; packs already loaded are not fetched again), " +
      "R = min(129, 2 × spans per tile × 2^L + 1) samples per patch side.";
    this.select.hidden = false;
    this.select.disabled = false;
  }

  /** "Open in 3DHOP" shows the level chosen here (the 3DHOP page's ?level=L). */
  _followWithHopLink() {
    const hopUrl = this.config.hop_url;
    const hopLink = hopUrl &&
      [...document.querySelectorAll(".actions a")].find((a) => a.getAttribute("href") === hopUrl);
    if (!hopLink) return;
    this.select.addEventListener("change", () => {
      const url = new URL(hopUrl, window.location.href);
      if (Number(this.select.value) >= 0) url.searchParams.set("level", this.select.value);
      hopLink.href = url.href;
    });
  }

  /** Progress and outcome, in the panel's status line under its buttons (the loading panel's
   *  grey text would sit on the object). */
  _showStatus(text) {
    const line = $("ply-status");
    line.textContent = text;
    line.hidden = !text;
    if (text) line.scrollIntoView({ block: "nearest" }); // the panel scrolls (a long title)
  }

  /** Make and save the PLY of `level` (-1: the base on screen); a failure goes to onError. */
  async download(level) {
    this.button.disabled = true;
    this.select.disabled = true;
    document.body.dataset.plyBusy = "1";
    document.body.dataset.stage = "ply";
    this._showStatus(level < 0 ? "Writing the PLY…" : "");
    try {
      const { ply, name } = level < 0 && !this.atlas ? await this._writeBase()
        : await this._writeLevel(level);
      Object.assign(this.stats, { ply_level: level, ply_bytes: ply.bytes.length,
                                  ply_vertices: ply.vertices, ply_resolution: ply.resolution,
                                  ply_ms: ply.write_ms });
      saveFile(ply.bytes, name);
      this._showStatus(`${name}: ${formatBytes(ply.bytes.length)}, ` +
        `${ply.vertices.toLocaleString("en")} vertices (${ply.resolution}² grid` +
        `${this.atlas ? " per patch" : ""}), ` +
        `${(this.stats.ply_total_ms / 1000).toFixed(1)} s`);
    } catch (error) {
      this._showStatus("");
      this.onError(`Download PLY${level >= 0 ? ` (level ${level})` : ""} failed: ${error.message}`);
    } finally {
      delete document.body.dataset.plyBusy;
      this.button.disabled = false;
      this.select.disabled = !this.levels.length;
    }
  }

  /** The mesh on screen, with the error map's colours when it is shown. */
  async _writeBase() {
    const t0 = performance.now();
    const colors = this.errorMap.vertexColors(this.base.uvs, this.base.domain);
    const ply = await this.worker.ply(this.base.resolution, colors);
    Object.assign(this.stats, { ply_total_ms: performance.now() - t0, ply_tiles_fetched: 0,
                                ply_fetch_bytes: 0, ply_textures: 0, ply_texture_bytes: 0 });
    return { ply, name: this.config.ply_name };
  }

  /** The whole patch at detail `level`, its tiles fetched as needed (page.js levelPly). */
  async _writeLevel(level) {
    const choice = this.levels.find((entry) => entry.level === level);
    if (!choice) throw new Error(`no detail level ${level} in this bundle`);
    const ply = await levelPly(this.worker, choice, { manifestUrl: this.config.manifest_url,
                                                      stats: this.stats,
                                                      onProgress: (text) => this._showStatus(text) });
    if (level < 0) return { ply, name: this.config.ply_name };
    return { ply, name: `${this.config.ply_name.replace(/\.ply$/i, "")}_level${level}.ply` };
  }
}
