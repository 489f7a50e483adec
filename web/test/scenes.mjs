// Test scenes for the tile modules: a flat square patch, complete tile pyramids, cameras, and
// an independent reference of what a camera sees (clip-space box test, box distance by hand).

import * as THREE from "three";

/** The base mesh of a square `side` x `side` at z = height(u, v) (flat by default) on an
 *  n x n grid (scan frame = patch frame); uvs are the normalised (u, v), domain [0, 1, 0, 1]. */
export function planeMesh(side = 100, n = 33, height = () => 0) {
  const positions = new Float32Array(3 * n * n);
  const uvs = new Float32Array(2 * n * n);
  for (let a = 0; a < n; a++) {
    for (let b = 0; b < n; b++) {
      const k = a * n + b;
      const u = a / (n - 1), v = b / (n - 1);
      positions.set([u * side, v * side, height(u, v)], 3 * k);
      uvs.set([u, v], 2 * k);
    }
  }
  return { positions, uvs, domain: [0, 1, 0, 1] };
}

/** Every node of levels `levels` (each level complete), `extra(level, i, j)` merged in. */
export function completeNodes(levels, folder, extension, extra = () => ({})) {
  const nodes = [];
  for (const level of levels) {
    const n = 2 ** level;
    for (let i = 0; i < n; i++) {
      for (let j = 0; j < n; j++) {
        nodes.push({ level, i, j, uv: [i / n, j / n, (i + 1) / n, (j + 1) / n],
                     file: `${folder}/${level}/${i}_${j}.${extension}`, bytes: 100 + level,
                     ...extra(level, i, j) });
      }
    }
  }
  return nodes;
}

/** manifest.tiles with complete detail levels 0..errors.length-1, level k's nodes of
 *  geometric_error errors[k]. */
/** Region grids per level as a worker's plan gives them (levels[k].region_resolution):
 *  arbitrary stand-ins, not client_py's rule, so a test sees the tree use what it is given. */
export const REGION_GRIDS = [41, 21, 11, 9, 7, 5, 3];

export function detailTiles(errors, { spans = 16, baseMax = 1 } = {}) {
  return {
    version: 1,
    detail: {
      format: "tsd", format_version: 2, degree: 2, spans_per_tile: spans,
      base: { rms: baseMax / 3, max: baseMax },
      levels: errors.map((error, level) => ({ level, rms: error / 3, max: error })),
      nodes: completeNodes(errors.map((_, level) => level), "detail", "tsd",
                           (level) => ({ geometric_error: errors[level] })),
    },
    texture: null,
  };
}

/** A 90° camera (focal length = heightPx / 2 device pixels) at `position` looking at `target`. */
export function camera(position, target) {
  const cam = new THREE.PerspectiveCamera(90, 1, 0.1, 10000);
  cam.position.set(...position);
  cam.up.set(0, 1, 0);
  cam.lookAt(...target);
  cam.updateMatrixWorld();
  cam.updateProjectionMatrix();
  return cam;
}

/** The 8 corners of an axis-aligned box [min, max] mapped by the 4x4 row-major `frame`. */
function corners(min, max, frame) {
  const out = [];
  for (const x of [min[0], max[0]]) {
    for (const y of [min[1], max[1]]) {
      for (const z of [min[2], max[2]]) {
        const p = [x, y, z, 1];
        out.push(frame.map((row) => row.reduce((sum, m, c) => sum + m * p[c], 0)));
      }
    }
  }
  return out;
}

/** True unless all 8 corners of the box (patch frame) fail one clip-space inequality
 *  -w <= x, y, z <= w of `cam` (the box is then wholly outside one side of the frustum). */
export function boxInView(cam, min, max, frame) {
  const clip = new THREE.Matrix4().multiplyMatrices(cam.projectionMatrix, cam.matrixWorldInverse);
  const e = clip.elements; // column-major
  const points = corners(min, max, frame).map(([x, y, z]) => [0, 1, 2, 3].map(
    (r) => e[r] * x + e[4 + r] * y + e[8 + r] * z + e[12 + r]));
  for (let axis = 0; axis < 3; axis++) {
    if (points.every((c) => c[axis] < -c[3]) || points.every((c) => c[axis] > c[3])) return false;
  }
  return true;
}

/** Euclidean distance from point p to the box [min, max]. */
export function boxDistance(p, min, max) {
  let sum = 0;
  for (let a = 0; a < 3; a++) {
    const gap = Math.max(min[a] - p[a], 0, p[a] - max[a]);
    sum += gap * gap;
  }
  return Math.sqrt(sum);
}

/** Rigid 4x4 row-major frame: rotation by `angle` about z, then about x by `tilt`, then a
 *  translation; with its inverse applied to points. */
export function rigidFrame(angle, tilt, offset) {
  const [c, s, ct, st] = [Math.cos(angle), Math.sin(angle), Math.cos(tilt), Math.sin(tilt)];
  const rz = [[c, -s, 0], [s, c, 0], [0, 0, 1]];
  const rx = [[1, 0, 0], [0, ct, -st], [0, st, ct]];
  const r = rx.map((row) => [0, 1, 2].map((col) => row.reduce((sum, m, k) => sum + m * rz[k][col], 0)));
  const frame = [[...r[0], offset[0]], [...r[1], offset[1]], [...r[2], offset[2]], [0, 0, 0, 1]];
  const inverse = (p) => [0, 1, 2].map((col) => [0, 1, 2].reduce(
    (sum, k) => sum + r[k][col] * (p[k] - offset[k]), 0));
  return { frame, inverse };
}

/** Map a mesh's positions by the row-major 4x4 `frame`. */
export function mapPositions(positions, frame) {
  const out = new Float32Array(positions.length);
  for (let k = 0; k < positions.length; k += 3) {
    const p = [positions[k], positions[k + 1], positions[k + 2], 1];
    for (let r = 0; r < 3; r++) out[k + r] = frame[r].reduce((sum, m, col) => sum + m * p[col], 0);
  }
  return out;
}
