// TileTree: the manifest's tile quadtree (docs/format.md, "Tiles") and the choice of the
// regions to refine for a camera — screen-space error, as in OGC 3D Tiles.
//
// Node (k, i, j) covers [i/2^k, (i+1)/2^k] x [j/2^k, (j+1)/2^k] of the normalised (u, v)
// domain; (-1, 0, 0) is the base patch alone, whose child is the level-0 node. A region
// shown at node (k, i, j) carries every *present* detail tile of levels 0..k that covers it
// (its ancestors-or-self); an absent tile is a zero field. The error of what a region shows
// is its node's `geometric_error`, or for an absent node its nearest present ancestor's (the
// bound docs/format.md gives), or `detail.base.max` for the base.
//
// Selection: with d the distance from the camera to the node's bounding box (scan frame,
// clamped to the near plane), f = H / (2 tan(fov / 2)) the focal length in device pixels
// (H the drawing buffer's height), the projected error is
//
//     sse = geometric_error * f / d                                     (pixels)
//
// and a node in the view frustum is refined into its children while sse > DETAIL_PX (2 px)
// and a finer present tile lies below it — most projected error first, within a budget of
// MAX_REGIONS regions. Texture tiles refine the same way on their texel size: a texture of
// `size` texels over a node whose box measures e (its longest side) shows texels of e / size,
// refined while e / size * f / d > TEXEL_PX. Children outside the frustum are not shown (the
// base covers them until they come into view). Bounding boxes come from the base mesh on
// screen (the vertices whose (u, v) fall within one grid step of each finest cell), padded by
// the base's max deviation (detail.base.max: how far the detail may move the surface).
//
// Region grid: a region at a level-k node is tessellated on an R_k x R_k grid, R_k given per
// level by the worker's plan (client_py.bundle.drawn_region_resolution, the one rule of a
// level's grid: two vertices per knot span of the region's finest tile, finer at coarse levels
// so a level is never drawn on fewer than 256 cells across the domain; 257, 129, 65, 33 at
// levels 0..3 for the default 16 spans). This file has no copy of that rule.

import * as THREE from "three";

export const DETAIL_PX = 2;
export const TEXEL_PX = 1.5;
export const MAX_REGIONS = 48;

/**
 * The region grids of levels 0..maxLevel, checked: each an integer >= 2 (vertices per side).
 * @param {unknown} grids  the plan's levels[k].region_resolution, k = 0, 1, ..
 * @param {number} maxLevel  the tree's finest level
 * @returns {number[]}
 * @throws {Error} naming the level whose grid is missing or not an integer >= 2
 */
function checkedGrids(grids, maxLevel) {
  for (let k = 0; k <= maxLevel; k++) {
    const grid = Array.isArray(grids) ? grids[k] : undefined;
    if (!Number.isInteger(grid) || grid < 2) {
      throw new Error(`no region grid for level ${k} (vertices per side, the worker's plan of ` +
                      `the manifest's detail levels), got ${JSON.stringify(grid) ?? String(grid)}`);
    }
  }
  return grids.slice(0, maxLevel + 1);
}

const key = (level, i, j) => `${level}/${i}/${j}`;

export class TileTree {
  /**
   * @param {object|null} tiles  manifest.tiles (may be null or lack detail/texture)
   * @param {number[][]|null} transform  manifest.transform: the 4x4 row-major map from the
   *   patch's frame (centred, PCA-aligned: tight boxes) to the scan's; null for the identity
   * @param {number[]|null} regionGrids  vertices per side of a region at levels 0, 1, ..: the
   *   worker's plan (MeshWorkerClient.plan: levels[k].region_resolution)
   * @throws {Error} for a node with an invalid index or no file, or, when any node is present,
   *   a level up to the finest node's without a region grid
   */
  constructor(tiles, transform = null, regionGrids = null) {
    // boxes are kept in the patch frame, where they fit the surface closely
    this.frame = new THREE.Matrix4();
    if (transform) this.frame.set(...transform.flat());
    this.frameInverse = this.frame.clone().invert();
    const detail = (tiles && tiles.detail) || null;
    const texture = (tiles && tiles.texture) || null;
    this.detail = new Map();
    this.texture = new Map();
    for (const node of (detail && detail.nodes) || []) this.detail.set(key(node.level, node.i, node.j), node);
    for (const node of (texture && texture.nodes) || []) this.texture.set(key(node.level, node.i, node.j), node);
    this.baseError = detail && detail.base && Number.isFinite(detail.base.max) ? detail.base.max : 0;
    this.textureSize = texture && texture.size ? texture.size : 256;
    this.maxLevel = -1;
    // keys of the strict ancestors of present nodes (with the base, "-1/0/0"): refinable
    this.detailBelow = new Set();
    this.textureBelow = new Set();
    for (const [nodes, below] of [[this.detail, this.detailBelow], [this.texture, this.textureBelow]]) {
      for (const node of nodes.values()) {
        for (const name of ["level", "i", "j"]) {
          if (!Number.isInteger(node[name]) || node[name] < 0) {
            throw new Error(`manifest tile node ${JSON.stringify(node)}: ${name} is not a valid index`);
          }
        }
        if (node.i >= 2 ** node.level || node.j >= 2 ** node.level || typeof node.file !== "string") {
          throw new Error(`manifest tile node ${JSON.stringify(node)} is outside its level or has no file`);
        }
        this.maxLevel = Math.max(this.maxLevel, node.level);
        below.add(key(-1, 0, 0));
        for (let k = node.level - 1; k >= 0; k--) {
          below.add(key(k, node.i >> (node.level - k), node.j >> (node.level - k)));
        }
      }
    }
    // vertices per region side, per level; a tree with no node shows no region and needs none
    this.regionGrids = this.empty ? null : checkedGrids(regionGrids, this.maxLevel);
    this.boxes = null; // per level k in 0..maxLevel: Float64Array of 4^k boxes (6 numbers)
  }

  get empty() {
    return this.maxLevel < 0;
  }

  /** Vertices per side of a region at a level-`level` node (null in an empty tree). */
  regionGrid(level) {
    return this.regionGrids ? this.regionGrids[level] : null;
  }

  static rect(level, i, j) {
    const n = 2 ** level;
    return [i / n, j / n, (i + 1) / n, (j + 1) / n];
  }

  /** Present detail nodes covering (level, i, j), levels 0..level, coarsest first. */
  detailChain(level, i, j) {
    const chain = [];
    for (let k = 0; k <= level; k++) {
      const node = this.detail.get(key(k, i >> (level - k), j >> (level - k)));
      if (node) chain.push(node);
    }
    return chain;
  }

  /** The finest present texture node covering (level, i, j) at a level <= level, or null. */
  textureNode(level, i, j) {
    for (let k = level; k >= 0; k--) {
      const node = this.texture.get(key(k, i >> (level - k), j >> (level - k)));
      if (node) return node;
    }
    return null;
  }

  /** Max deviation left where (level, i, j) is shown (scan units). */
  detailError(level, i, j) {
    for (let k = level; k >= 0; k--) {
      const node = this.detail.get(key(k, i >> (level - k), j >> (level - k)));
      if (node && Number.isFinite(node.geometric_error)) return node.geometric_error;
    }
    return this.baseError;
  }

  /**
   * Bounding boxes of every node from a base mesh on a square grid: positions (scan frame)
   * and uvs (patch parameters in `domain` = [u0, u1, v0, v1]); each box padded by `margin`
   * (the displacement the detail may add) on every side.
   */
  setBounds(positions, uvs, domain, margin) {
    if (this.empty) return;
    const [a0, a1, b0, b1] = domain;
    const top = this.maxLevel;
    const boxes = [];
    for (let k = 0; k <= top; k++) {
      const box = new Float64Array(6 * 4 ** k);
      for (let c = 0; c < box.length; c += 6) box.set([Infinity, Infinity, Infinity, -Infinity, -Infinity, -Infinity], c);
      boxes.push(box);
    }
    const n = 2 ** top;
    const finest = boxes[top];
    const grow = (box, c, x, y, z) => {
      if (x < box[c]) box[c] = x;
      if (y < box[c + 1]) box[c + 1] = y;
      if (z < box[c + 2]) box[c + 2] = z;
      if (x > box[c + 3]) box[c + 3] = x;
      if (y > box[c + 4]) box[c + 4] = y;
      if (z > box[c + 5]) box[c + 5] = z;
    };
    // each vertex counts in every finest cell within one grid step of it (`step`, normalised),
    // so a cell's box holds the surface up to its borders, not only its inner vertices
    const count = uvs.length / 2;
    const side = Math.max(Math.round(Math.sqrt(count)), 2);
    const step = 1 / (side - 1);
    const p = new THREE.Vector3();
    for (let v = 0; v < count; v++) {
      p.fromArray(positions, 3 * v).applyMatrix4(this.frameInverse);
      const u = (uvs[2 * v] - a0) / (a1 - a0);
      const w = (uvs[2 * v + 1] - b0) / (b1 - b0);
      const i0 = Math.max(0, Math.floor((u - step) * n)), i1 = Math.min(n - 1, Math.floor((u + step) * n));
      const j0 = Math.max(0, Math.floor((w - step) * n)), j1 = Math.min(n - 1, Math.floor((w + step) * n));
      for (let i = i0; i <= i1; i++) {
        for (let j = j0; j <= j1; j++) {
          grow(finest, 6 * (i * n + j), p.x, p.y, p.z);
        }
      }
    }
    // up the tree: a node's box holds its children's
    for (let k = top - 1; k >= 0; k--) {
      const m = 2 ** k;
      for (let i = 0; i < m; i++) {
        for (let j = 0; j < m; j++) {
          const c = 6 * (i * m + j);
          for (const [di, dj] of [[0, 0], [0, 1], [1, 0], [1, 1]]) {
            const child = boxes[k + 1];
            const d = 6 * ((2 * i + di) * 2 * m + 2 * j + dj);
            if (child[d] <= child[d + 3]) {
              grow(boxes[k], c, child[d], child[d + 1], child[d + 2]);
              grow(boxes[k], c, child[d + 3], child[d + 4], child[d + 5]);
            }
          }
        }
      }
    }
    // down the tree: a node no vertex fell in (a coarse base grid) takes its parent's box
    for (let k = 1; k <= top; k++) {
      const m = 2 ** k;
      for (let c = 0; c < 4 ** k; c++) {
        const box = boxes[k];
        if (box[6 * c] > box[6 * c + 3]) {
          const i = Math.floor(c / m), j = c % m;
          const p = 6 * ((i >> 1) * (m / 2) + (j >> 1));
          box.set(boxes[k - 1].subarray(p, p + 6), 6 * c);
        }
      }
    }
    for (const box of boxes) {
      for (let c = 0; c < box.length; c += 6) {
        for (let a = 0; a < 3; a++) {
          box[c + a] -= margin;
          box[c + 3 + a] += margin;
        }
      }
    }
    this.boxes = boxes;
  }

  /** THREE.Box3 of node (level, i, j) in the patch frame; the base (-1) is the level-0 box. */
  box(level, i, j) {
    const k = Math.max(level, 0);
    const box = this.boxes[k];
    const c = 6 * (i * 2 ** k + j);
    return new THREE.Box3(new THREE.Vector3(box[c], box[c + 1], box[c + 2]),
                          new THREE.Vector3(box[c + 3], box[c + 4], box[c + 5]));
  }

  /**
   * The regions to show for `camera` on a drawing buffer `heightPx` tall.
   * @returns {{level: number, i: number, j: number, sse: number, centre: number}[]} the
   *   visible leaves of the refinement at levels >= 0 (empty: the base alone suffices);
   *   centre: the distance of the node's box centre from the view's centre in normalised
   *   device coordinates (0 at the centre, 1 at the middle of an edge)
   */
  select(camera, heightPx, { detailPx = DETAIL_PX, texelPx = TEXEL_PX, maxRegions = MAX_REGIONS } = {}) {
    if (this.empty || !this.boxes) return [];
    camera.updateMatrixWorld();
    // frustum planes and the eye in the patch frame (the frame map is rigid: distances hold)
    const frustum = new THREE.Frustum().setFromProjectionMatrix(new THREE.Matrix4()
      .multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse).multiply(this.frame));
    const focal = (heightPx * camera.zoom) / (2 * Math.tan(THREE.MathUtils.degToRad(camera.fov) / 2));
    const eye = camera.position.clone().applyMatrix4(this.frameInverse);
    // patch frame -> normalised device coordinates: how far a box's centre is from the view's
    const toScreen = new THREE.Matrix4().multiplyMatrices(camera.projectionMatrix,
                                                          camera.matrixWorldInverse).multiply(this.frame);
    const centre = new THREE.Vector3();
    // a node's need for refinement: the largest ratio of projected error to its threshold
    const consider = (level, i, j) => {
      const box = this.box(level, i, j);
      if (!frustum.intersectsBox(box)) return null;
      const scale = focal / Math.max(box.distanceToPoint(eye), camera.near);
      const id = key(level, i, j);
      let need = 0;
      const sse = this.detailError(level, i, j) * scale;
      if (this.detailBelow.has(id)) need = sse / detailPx;
      if (this.textureBelow.has(id)) {
        const shown = this.textureNode(level, i, j);
        const size = shown ? this.box(shown.level, shown.i, shown.j).getSize(new THREE.Vector3()) : box.getSize(new THREE.Vector3());
        const texel = (shown ? Math.max(size.x, size.y, size.z) / this.textureSize : Infinity) * scale;
        need = Math.max(need, texel / texelPx);
      }
      box.getCenter(centre).applyMatrix4(toScreen);
      return { level, i, j, sse, need, centre: Math.hypot(centre.x, centre.y) };
    };
    const root = consider(-1, 0, 0);
    if (!root || root.need <= 1) return [];
    const leaves = [];
    const open = [root]; // nodes wanting refinement, most needy last
    let count = 0; // regions the refinement would show
    while (open.length) {
      open.sort((a, b) => a.need - b.need);
      const node = open.pop();
      const children = node.level < 0 ? [[0, 0, 0]] : [[0, 0], [0, 1], [1, 0], [1, 1]].map(
        ([di, dj]) => [node.level + 1, 2 * node.i + di, 2 * node.j + dj]);
      if (node.level >= 0 && count - 1 + children.length > maxRegions) {
        leaves.push(node); // over budget: shown as it is
        continue;
      }
      if (node.level >= 0) count -= 1;
      for (const [level, i, j] of children) {
        const child = consider(level, i, j);
        if (!child) continue; // out of view: the base shows there
        count += 1;
        if (child.need > 1) open.push(child);
        else leaves.push(child);
      }
    }
    return leaves.map(({ level, i, j, sse, centre }) => ({ level, i, j, sse, centre }));
  }
}
