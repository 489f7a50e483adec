// What every object page shares: the server's JSON config block, the stats object of the
// testing contract (window.tessera.stats), and the loading and error panels
// (templates/_status.html). On failure the message goes to document.body.dataset.error.

export const $ = (id) => document.getElementById(id);

export function startPage(stages, extraStats = {}) {
  const config = JSON.parse($("tessera-config").textContent);
  const stats = { vertices: 0, triangles: 0, tessellate_ms: null, pyodide_load_ms: null,
    first_frame_ms: null, bytes_downloaded: 0, kernel: null, ...extraStats };
  window.tessera = { config, stats };

  function showStage(stage) {
    $("loading-text").textContent = stages[stage] || stage;
    document.body.dataset.stage = stage;
  }

  function showError(message) {
    document.body.dataset.error = message;
    $("loading").hidden = true;
    $("error").hidden = false;
    $("error-text").textContent = message;
  }

  return { config, stats, showStage, showError };
}
