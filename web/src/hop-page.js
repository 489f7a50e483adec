// The 3DHOP page: client_py writes the PLY in the browser (mesh worker), 3DHOP shows it.
//
// The PLY reaches 3DHOP as a blob: URL with mType "ply" (3DHOP's own loader, js/ply.js).
// Loaded state: 3DHOP's presenter reports its scene ready (presenter._isSceneReady(), set
// when every mesh of the scene has been parsed and uploaded); the page then sets
// document.body.dataset.ready = "1" after the next frame, as the viewer page does.

import { ErrorMap } from "./error-map.js";
import { MeshWorkerClient } from "./mesh-worker-client.js";
import { $, startPage } from "./page.js";

const RESOLUTION = 192; // 36,864 vertices: one 3DHOP chunk (its limit is 65,535 per chunk)
const { config, stats, showStage, showError } = startPage({
  runtime: "Starting the Python runtime (Pyodide)…",
  client_py: "Installing client_py…",
  patch: "Reading the NURBS patch…",
  ply: "Writing the PLY mesh…",
  hop: "Handing the mesh to 3DHOP…",
}, { ply_bytes: 0 });

// 3DHOP's toolbar (init.js) calls this global.
window.actionsToolbar = (action) => {
  const presenter = window.presenter;
  if (!presenter) return;
  if (action === "home") presenter.resetTrackball();
  else if (action === "zoomin") presenter.zoomIn();
  else if (action === "zoomout") presenter.zoomOut();
  else if (action === "light" || action === "light_on") {
    presenter.enableLightTrackball(!presenter.isLightTrackballEnabled());
    window.lightSwitch();
  } else if (action === "full" || action === "full_on") window.fullscreenSwitch();
};

/** Column-major 4x4 rotation turning the mean normal towards 3DHOP's camera (+z) and the
 *  longest in-plane extent of the vertices horizontal (+x), as the three.js viewer frames it. */
function facingMatrix(positions, normals, tilt = (20 * Math.PI) / 180) {
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (v) => { const l = Math.hypot(...v) || 1; return v.map((x) => x / l); };
  let f = [0, 0, 0];
  for (let k = 0; k < normals.length; k += 3) f = [f[0] + normals[k], f[1] + normals[k + 1], f[2] + normals[k + 2]];
  f = Math.hypot(...f) > 1e-9 ? norm(f) : [0, 0, 1];
  // In-plane principal axis: 2x2 covariance of the vertices in a basis (a, b) orthogonal to f.
  const a = norm(cross(Math.abs(f[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0], f));
  const b = cross(f, a);
  const n = positions.length / 3;
  const c = [0, 0, 0];
  for (let k = 0; k < positions.length; k += 3) for (let i = 0; i < 3; i++) c[i] += positions[k + i] / n;
  let saa = 0, sab = 0, sbb = 0;
  for (let k = 0; k < positions.length; k += 3) {
    const d = [positions[k] - c[0], positions[k + 1] - c[1], positions[k + 2] - c[2]];
    const pa = dot(d, a), pb = dot(d, b);
    saa += pa * pa; sab += pa * pb; sbb += pb * pb;
  }
  const angle = 0.5 * Math.atan2(2 * sab, saa - sbb);
  const right = norm(a.map((x, i) => Math.cos(angle) * x + Math.sin(angle) * b[i]));
  const up0 = cross(f, right);
  // Then tilt by `tilt` about x: the camera looks from a little above, like the three.js viewer.
  const ct = Math.cos(tilt), st = Math.sin(tilt);
  const up = up0.map((x, i) => ct * x - st * f[i]);
  const back = up0.map((x, i) => st * x + ct * f[i]);
  // Rows of the rotation are right, up, back; column-major storage puts row r, column c at [4c + r].
  return [right[0], up[0], back[0], 0, right[1], up[1], back[1], 0, right[2], up[2], back[2], 0,
          0, 0, 0, 1];
}

function waitForScene(presenter, timeoutMs) {
  return new Promise((resolve, reject) => {
    const start = performance.now();
    const poll = () => {
      if (presenter._isSceneReady()) resolve();
      else if (performance.now() - start > timeoutMs) reject(new Error(`3DHOP did not load the mesh within ${timeoutMs / 1000} s`));
      else setTimeout(poll, 20);
    };
    poll();
  });
}

async function main() {
  if (typeof Presenter === "undefined") throw new Error("3DHOP's scripts did not load (check TESSERA_3DHOP_DIR / TESSERA_3DHOP_URL)");
  window.init3dhop();
  const presenter = new Presenter("draw-canvas");
  window.presenter = presenter;

  const worker = new MeshWorkerClient(config.worker_url, { onStage: showStage });
  const ready = await worker.init({
    pyodideUrl: config.pyodide_url, pyodideSnapshotUrl: config.pyodide_snapshot_url,
    clientPyUrl: config.client_py_url, patchUrl: config.patch_url,
  }, config.pyodide_timeout_s);
  stats.pyodide_load_ms = ready.pyodide_load_ms;
  stats.kernel = ready.kernel;
  stats.bytes_downloaded += ready.patch_bytes;

  let errorMap = null;
  const useColors = new URLSearchParams(location.search).get("colors") === "error";
  $("hop-colors").checked = useColors;
  $("hop-colors").addEventListener("change", () => {
    const url = new URL(location.href);
    if ($("hop-colors").checked) url.searchParams.set("colors", "error"); else url.searchParams.delete("colors");
    location.assign(url);
  });
  const resolution = config.resolution || RESOLUTION;
  showStage("ply");
  const mesh = await worker.tessellate(resolution);
  stats.tessellate_ms = mesh.tessellate_ms;
  let colors = null;
  if (useColors) {
    const response = await fetch(config.manifest_url);
    if (!response.ok) throw new Error(`cannot fetch the manifest: HTTP ${response.status}`);
    const manifest = await response.json();
    if (!manifest.error_grid) throw new Error("this bundle has no error data to colour the mesh with");
    errorMap = new ErrorMap(manifest.error_grid, manifest.units || "");
    colors = errorMap.vertexColors(mesh.uvs, ready.patch.domain);
  }
  const ply = await worker.ply(resolution, colors);
  stats.vertices = ply.vertices;
  stats.triangles = mesh.indices.length / 3;
  stats.ply_bytes = ply.bytes.length;
  const url = URL.createObjectURL(new Blob([ply.bytes], { type: "application/octet-stream" }));
  window.tessera.plyUrl = url;

  showStage("hop");
  presenter.setScene({
    meshes: { tessera: { url, mType: "ply", transform: { matrix: facingMatrix(mesh.positions, mesh.normals) } } },
    // A stone-like solid colour, or -2,-2,-2 meaning "the vertex colours" when the mesh has
    // them (client_py writes texture_u/v only with a texture, which 3DHOP would sample).
    modelInstances: { object: { mesh: "tessera", useSolidColor: true,
                                color: colors ? [-2.0, -2.0, -2.0] : [0.86, 0.82, 0.75],
                                specularColor: [0.08, 0.08, 0.08, 32.0] } },
    trackball: {
      type: SphereTrackball,
      trackOptions: { startDistance: 2.4, minMaxDist: [0.4, 6.0] },
    },
    space: { cameraFOV: 40.0 },
  });
  await waitForScene(presenter, 20000);
  presenter.repaint();
  await new Promise((resolve) => requestAnimationFrame(() => requestAnimationFrame(resolve)));
  stats.first_frame_ms = performance.now();
  $("loading").hidden = true;
  document.body.dataset.ready = "1";
}

main().catch((error) => {
  showError(error.message || String(error));
});
