// Viewer: the three.js scene that shows a tessellated patch — a turntable orbit about the
// object's up (the manifest's `view`, web/src/camera-view.js), zoom, pan, front and reset
// views, an error-map overlay, detail regions superimposed on the base; rendering on demand (only
// when the view or the meshes change).
//
// Detail regions (web/src/tile-layer.js) are meshes over quadtree rectangles of the patch's
// normalised (u, v) domain. Where a region is shown the base mesh is cut away exactly by a
// fragment discard against a small mask texture over (u, v) (one texel per finest-level
// cell), so base and regions never overlap; the regions' skirts close the seams.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

import { frontView, MAX_POLAR, MIN_POLAR } from "./camera-view.js";

const STONE = 0xd9cfbf;
export const BACKGROUND = 0x23262b;

/** Unit mean of the vertex normals (the direction a relief faces), +z if they cancel out. */
function meanNormal(normals) {
  const sum = new THREE.Vector3();
  for (let k = 0; k < normals.length; k += 3) {
    sum.x += normals[k];
    sum.y += normals[k + 1];
    sum.z += normals[k + 2];
  }
  return sum.lengthSq() > 1e-12 ? sum.normalize() : new THREE.Vector3(0, 0, 1);
}

/** Direction of largest spread of the vertices in the plane perpendicular to `facing`
 *  (the principal eigenvector of their 2x2 in-plane covariance). */
function principalAxis(positions, centre, facing) {
  const helper = Math.abs(facing.x) < 0.9 ? new THREE.Vector3(1, 0, 0) : new THREE.Vector3(0, 1, 0);
  const a = new THREE.Vector3().crossVectors(helper, facing).normalize();
  const b = new THREE.Vector3().crossVectors(facing, a);
  let saa = 0, sab = 0, sbb = 0;
  const step = Math.max(3, 3 * Math.floor(positions.length / 3 / 4096)); // a sample is enough
  for (let k = 0; k < positions.length; k += step) {
    const x = positions[k] - centre.x, y = positions[k + 1] - centre.y, z = positions[k + 2] - centre.z;
    const pa = x * a.x + y * a.y + z * a.z;
    const pb = x * b.x + y * b.y + z * b.z;
    saa += pa * pa; sab += pa * pb; sbb += pb * pb;
  }
  const angle = 0.5 * Math.atan2(2 * sab, saa - sbb);
  return a.multiplyScalar(Math.cos(angle)).addScaledVector(b, Math.sin(angle)).normalize();
}

/** The vertices the triangles use (a trimmed patch's grid keeps the others, off the object):
 *  their positions and normals, compacted, and their bounding sphere (centre of their box). */
function drawnVertices(positions, normals, indices) {
  const used = new Uint8Array(positions.length / 3);
  for (let k = 0; k < indices.length; k++) used[indices[k]] = 1;
  let count = 0;
  for (let k = 0; k < used.length; k++) count += used[k];
  const pos = new Float32Array(3 * count), nrm = new Float32Array(3 * count);
  for (let k = 0, j = 0; k < used.length; k++) {
    if (!used[k]) continue;
    for (let c = 0; c < 3; c++) {
      pos[j + c] = positions[3 * k + c];
      nrm[j + c] = normals[3 * k + c];
    }
    j += 3;
  }
  const box = new THREE.Box3().setFromArray(pos);
  const centre = box.getCenter(new THREE.Vector3());
  let r2 = 0;
  for (let k = 0; k < pos.length; k += 3) {
    const dx = pos[k] - centre.x, dy = pos[k + 1] - centre.y, dz = pos[k + 2] - centre.z;
    r2 = Math.max(r2, dx * dx + dy * dy + dz * dz);
  }
  return { positions: pos, normals: nrm, sphere: new THREE.Sphere(centre, Math.sqrt(r2)) };
}

export class Viewer {
  /** @param {HTMLCanvasElement} canvas */
  constructor(canvas) {
    this.canvas = canvas;
    // preserveDrawingBuffer: screenshots and the tests read the canvas after drawing.
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.outputColorSpace = THREE.SRGBColorSpace;
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(BACKGROUND);
    this.camera = new THREE.PerspectiveCamera(35, 1, 0.1, 1000);
    this.scene.add(this.camera);

    // Soft sky/ground fill plus a key light riding with the camera (raking from the upper
    // left, as photographers light reliefs) and a weak rim light from behind.
    this.scene.add(new THREE.HemisphereLight(0xf6f2ea, 0x3a3530, 0.55));
    const key = new THREE.DirectionalLight(0xfff6e8, 2.8);
    key.position.set(-1.2, 1.0, 0.8);
    this.camera.add(key);
    const rim = new THREE.DirectionalLight(0xcfd8ff, 0.5);
    rim.position.set(1.0, -0.5, -1.0);
    this.camera.add(rim);

    this.material = new THREE.MeshStandardMaterial({
      color: STONE, roughness: 0.82, metalness: 0.0, side: THREE.DoubleSide,
    });
    this.mesh = null;
    this.errorTexture = null;
    this.overlay = false;
    this.baseTexture = null; // a level-0 texture tile over the whole domain, or null
    // Detail regions: key -> THREE.Mesh, drawn instead of the base inside their rectangles.
    this.regions = new Map();
    this.regionGroup = new THREE.Group();
    this.scene.add(this.regionGroup);
    this.regionMaterial = this.material.clone();
    // A patch's detached pieces (setPieces): stone, never masked, textured nor error-mapped.
    this.pieces = null;
    this.piecesMaterial = this.material.clone();
    // An atlas's groups (setAtlasParts): key -> THREE.Mesh, drawn instead of this.mesh.
    this.atlasParts = new Map();
    this.atlasGroup = new THREE.Group();
    this.scene.add(this.atlasGroup);
    this.mask = null; // {texture: DataTexture, cells}: 1 where a region replaces the base
    this.maskUniforms = { tesseraMask: { value: null }, tesseraMaskOn: { value: 0 } };
    this.material.onBeforeCompile = (shader) => {
      Object.assign(shader.uniforms, this.maskUniforms);
      shader.vertexShader = shader.vertexShader
        .replace("#include <common>", "#include <common>\nvarying vec2 vTesseraUv;")
        .replace("#include <begin_vertex>", "#include <begin_vertex>\nvTesseraUv = uv;");
      shader.fragmentShader = shader.fragmentShader
        .replace("#include <common>", "#include <common>\nvarying vec2 vTesseraUv;\n" +
                 "uniform sampler2D tesseraMask;\nuniform float tesseraMaskOn;")
        .replace("void main() {", "void main() {\n" +
                 "  if (tesseraMaskOn > 0.5 && texture2D(tesseraMask, vTesseraUv).r > 0.5) discard;");
    };
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.addEventListener("change", () => this.render());
    this.objectView = null; // {up, front} in scan coordinates, or null: the fallback framing
    this.onRender = null;
    this._frame = null; // the animation frame a draw is requested for (render), or null
    this.insets = { left: 0, bottom: 0 };
    this._resizeObserver = new ResizeObserver(() => this.resize());
    this._resizeObserver.observe(canvas);
    this.resize();
  }

  resize() {
    const width = this.canvas.clientWidth || 1;
    const height = this.canvas.clientHeight || 1;
    this.renderer.setSize(width, height, false);
    this.camera.aspect = width / height;
    const left = Math.min(this.insets.left, width / 2);
    const bottom = Math.min(this.insets.bottom, height / 2);
    if (left > 0 || bottom > 0) {
      this.camera.setViewOffset(width, height, -left / 2, bottom / 2, width, height);
    } else {
      this.camera.clearViewOffset();
    }
    this.camera.updateProjectionMatrix();
    this.render();
  }

  /** Draw the scene at the next animation frame: every change within one frame (a camera
   *  move, a base texture, a region swap) makes one draw, not one each — under a software
   *  rasteriser (SwiftShader) a draw of the canvas takes 0.3-1.5 s of GPU time, and queued
   *  draws made a zoom wait seconds for its regions. */
  render() {
    if (this._frame !== null) return;
    this._frame = requestAnimationFrame(() => this.renderNow());
  }

  /** Draw now (and cancel a draw requested for the next frame). */
  renderNow() {
    if (this._frame !== null) cancelAnimationFrame(this._frame);
    this._frame = null;
    this.renderer.render(this.scene, this.camera);
    if (this.onRender) this.onRender();
  }

  /** Resolves once the draws requested so far are on the canvas (the frame after them). */
  whenDrawn() {
    return new Promise((resolve) => requestAnimationFrame(() => {
      if (this._frame !== null) this.renderNow();
      resolve();
    }));
  }

  /**
   * Show a mesh from the worker; the first one also fits the view.
   * @param {{positions: Float32Array, normals: Float32Array, uvs: Float32Array, indices: Uint32Array}} data
   * @param {number[]} domain  [u0, u1, v0, v1] of the patch, to map uvs onto the error map
   */
  setMesh(data, domain) {
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(data.positions, 3));
    geometry.setAttribute("normal", new THREE.BufferAttribute(data.normals, 3));
    // Texture coordinates (s, t) = (v, u) normalised: the error grid's columns run along v.
    const [u0, u1, v0, v1] = domain;
    const st = new Float32Array(data.uvs.length);
    for (let k = 0; k < st.length; k += 2) {
      st[k] = (data.uvs[k + 1] - v0) / (v1 - v0);
      st[k + 1] = (data.uvs[k] - u0) / (u1 - u0);
    }
    geometry.setAttribute("uv", new THREE.BufferAttribute(st, 2));
    // uv1: normalised (u, v), addressing a level-0 texture tile (docs/format.md, "Texture tiles")
    const uv1 = new Float32Array(data.uvs.length);
    for (let k = 0; k < uv1.length; k += 2) {
      uv1[k] = st[k + 1];
      uv1[k + 1] = st[k];
    }
    geometry.setAttribute("uv1", new THREE.BufferAttribute(uv1, 2));
    geometry.setIndex(new THREE.BufferAttribute(data.indices, 1));
    this.drawn = drawnVertices(data.positions, data.normals, data.indices);
    geometry.boundingSphere = this.drawn.sphere;
    const first = this.mesh === null;
    if (first) {
      // the first mesh frames every later first view (Reset): a refined mesh's slightly
      // different bounds must not move it
      this.framing = this.drawn;
      this.mesh = new THREE.Mesh(geometry, this.material);
      this.scene.add(this.mesh);
      this.fitView();
    } else {
      this.mesh.geometry.dispose();
      this.mesh.geometry = geometry;
    }
    this.render();
  }

  /**
   * The object's up and front (the manifest's `view`: unit 3-vectors in scan coordinates, the
   * frame of the meshes). The camera's up becomes the object's up and the controls turn about
   * it like a turntable, never over the poles. Call before the first mesh; null keeps the
   * fallback framing (bundles without `view`).
   * @param {{up: number[], front: number[]} | null} view
   */
  setObjectView(view) {
    this.objectView = view ? { up: [...view.up], front: [...view.front] } : null;
    const up = view ? new THREE.Vector3(...view.up).normalize() : new THREE.Vector3(0, 1, 0);
    this.camera.up.copy(up);
    // OrbitControls measures its polar angle from the up it read at construction (_quat,
    // _quatInverse); a new up must reach them, or the orbit would turn about the old axis.
    this.controls._quat.setFromUnitVectors(up, new THREE.Vector3(0, 1, 0));
    this.controls._quatInverse.copy(this.controls._quat).invert();
    this.controls.minPolarAngle = view ? MIN_POLAR : 0;
    this.controls.maxPolarAngle = view ? MAX_POLAR : Math.PI;
    if (this.mesh) this.fitView();
  }

  /** The first view: with an object view, its front from a little above with its up as
   *  screen-up (web/src/camera-view.js); without, the fallback framing. Centred in the part
   *  of the canvas the panel leaves free. */
  fitView() {
    if (!this.mesh) return;
    if (!this.objectView) {
      this._fallbackView();
      return;
    }
    const pose = this._frontPose();
    this._applyPose(pose, pose.distance);
  }

  /** Turn to the front, keeping the current distance to the object's centre. */
  showFront() {
    if (!this.mesh) return;
    if (!this.objectView) {
      this._fallbackView();
      return;
    }
    this._applyPose(this._frontPose(), this.camera.position.distanceTo(this.controls.target));
  }

  /** The object view's front pose for the first mesh's bounds (camera-view.js frontView). */
  _frontPose() {
    const sphere = this.framing.sphere;
    return frontView({
      center: sphere.center.toArray(), radius: sphere.radius, up: this.objectView.up,
      front: this.objectView.front, fovDeg: this.camera.fov, aspect: this.visibleAspect(),
    });
  }

  _applyPose(pose, distance) {
    const target = new THREE.Vector3(...pose.target);
    const look = new THREE.Vector3(...pose.position).sub(target).normalize();
    this.camera.up.set(...pose.up);
    this.camera.position.copy(target).addScaledVector(look, distance);
    this.camera.near = Math.min(pose.near, distance / 100);
    this.camera.far = Math.max(pose.far, distance * 100);
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(target);
    this.controls.update();
    this.render();
  }

  /** Bundles without `view`: the object seen from the side its normals face on average (a
   *  relief's front), its longest extent horizontal. */
  _fallbackView() {
    const sphere = this.framing.sphere;
    const facing = meanNormal(this.framing.normals);
    const right = principalAxis(this.framing.positions, sphere.center, facing);
    let up = new THREE.Vector3().crossVectors(facing, right).normalize();
    // Look from a little above the front, so the relief reads as relief and not as a photo.
    const tilt = THREE.MathUtils.degToRad(20);
    const view = facing.clone().multiplyScalar(Math.cos(tilt)).addScaledVector(up, Math.sin(tilt));
    up = new THREE.Vector3().crossVectors(view, right).normalize();
    const fov = THREE.MathUtils.degToRad(this.camera.fov);
    const fit = Math.min(fov, 2 * Math.atan(Math.tan(fov / 2) * this.visibleAspect()));
    const distance = (1.05 * sphere.radius) / Math.sin(fit / 2);
    this.camera.up.copy(up);
    this.camera.position.copy(sphere.center).addScaledVector(view, distance);
    this.camera.near = distance / 100;
    this.camera.far = distance * 100;
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(sphere.center);
    this.controls.update();
    this.render();
  }

  /**
   * Look at the base surface's point at normalised (u, v) from `distance` scan units along its
   * normal (on the side the camera is on). `uvs` are the base mesh's patch parameters
   * (domain = [u0, u1, v0, v1]): the nearest vertex stands for the point.
   */
  lookAtSurface(u, v, distance, uvs, domain) {
    if (!this.mesh) return;
    if (!(u >= 0 && u <= 1 && v >= 0 && v <= 1 && distance > 0)) {
      throw new Error(`zoomTo(u, v, distance) needs 0 <= u, v <= 1 and distance > 0, got ${u}, ${v}, ${distance}`);
    }
    const [u0, u1, v0, v1] = domain;
    let best = 0, bestD = Infinity;
    for (let k = 0; k < uvs.length / 2; k++) {
      const du = (uvs[2 * k] - u0) / (u1 - u0) - u, dv = (uvs[2 * k + 1] - v0) / (v1 - v0) - v;
      if (du * du + dv * dv < bestD) {
        bestD = du * du + dv * dv;
        best = k;
      }
    }
    const point = new THREE.Vector3().fromBufferAttribute(this.mesh.geometry.getAttribute("position"), best);
    const normal = new THREE.Vector3().fromBufferAttribute(this.mesh.geometry.getAttribute("normal"), best);
    if (normal.dot(this.camera.position.clone().sub(point)) < 0) normal.negate();
    this.camera.position.copy(point).addScaledVector(normal, distance);
    this.camera.near = Math.min(this.camera.near, distance / 10);
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(point);
    this.controls.update();
    this.render();
  }

  /** Width/height of the canvas area not covered by the panel. */
  visibleAspect() {
    const width = this.canvas.clientWidth || 1;
    const height = this.canvas.clientHeight || 1;
    return Math.max(width - this.insets.left, width / 2) /
      Math.max(height - this.insets.bottom, height / 2);
  }

  /** Keep room for a panel at the left or the bottom (pixels): the view centres in the rest. */
  setInsets({ left = 0, bottom = 0 }) {
    this.insets = { left, bottom };
    this.resize();
  }

  /** Approximate diameter of the object on screen, in device pixels. */
  projectedDiameter() {
    if (!this.mesh) return this.canvas.height;
    const sphere = this.mesh.geometry.boundingSphere;
    const distance = Math.max(this.camera.position.distanceTo(sphere.center), 1e-9);
    const viewHeight = 2 * distance * Math.tan(THREE.MathUtils.degToRad(this.camera.fov) / 2);
    return (2 * sphere.radius / viewHeight) * this.renderer.domElement.height;
  }

  /**
   * Overlay the error map (RGBA bytes, cols x rows) or remove it (null).
   * @param {{rgba: Uint8Array, cols: number, rows: number} | null} image
   */
  setErrorOverlay(image) {
    if (image && !this.errorTexture) {
      this.errorTexture = new THREE.DataTexture(image.rgba, image.cols, image.rows, THREE.RGBAFormat);
      this.errorTexture.colorSpace = THREE.SRGBColorSpace;
      this.errorTexture.magFilter = THREE.NearestFilter;
      this.errorTexture.needsUpdate = true;
    }
    this.overlay = Boolean(image);
    this._applyMaps();
    this.render();
  }

  /** Show a texture over the whole domain on the base mesh (a level-0 texture tile; its
   *  texture.channel must be 1), or none. */
  setBaseTexture(texture) {
    this.baseTexture = texture;
    this._applyMaps();
    this.render();
  }

  /** Each material's map: the error map (uv channel 0) when the overlay is on, else its
   *  texture tile (channel 1) if any, else the plain stone colour. */
  _applyMaps() {
    const assign = (material, texture) => {
      const map = this.overlay ? this.errorTexture : texture;
      if (material.map !== map) {
        material.map = map;
        material.needsUpdate = true;
      }
      material.color.set(map ? 0xffffff : STONE);
    };
    assign(this.material, this.baseTexture);
    assign(this.regionMaterial, null);
    for (const mesh of this.regions.values()) {
      if (mesh.material !== this.regionMaterial) assign(mesh.material, mesh.userData.texture);
    }
  }

  /**
   * Show a patch bundle's detached pieces (the worker's pieces mesh, scan frame: the scan's
   * fragments the height field cannot hold, docs/format.md "Pieces") beside the patch, at
   * every level; a second call replaces them.
   * @param {{positions: Float32Array, normals: Float32Array, indices: Uint32Array}} data
   */
  setPieces(data) {
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(data.positions, 3));
    geometry.setAttribute("normal", new THREE.BufferAttribute(data.normals, 3));
    geometry.setIndex(new THREE.BufferAttribute(data.indices, 1));
    geometry.computeBoundingSphere();
    if (this.pieces) {
      this.pieces.geometry.dispose();
      this.pieces.geometry = geometry;
    } else {
      this.pieces = new THREE.Mesh(geometry, this.piecesMaterial);
      this.scene.add(this.pieces);
    }
    this.render();
  }

  /**
   * A region mesh from the worker (not yet shown): normalised uvs, optionally textured by a
   * tile over `textureRect` = [u0, v0, u1, v1] (its texture.channel must be 1).
   * @param {{positions: Float32Array, normals: Float32Array, uvs: Float32Array, indices: Uint32Array}} data
   */
  makeRegionMesh(data, texture = null, textureRect = null) {
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(data.positions, 3));
    geometry.setAttribute("normal", new THREE.BufferAttribute(data.normals, 3));
    const st = new Float32Array(data.uvs.length); // (v, u): the error map's orientation
    for (let k = 0; k < st.length; k += 2) {
      st[k] = data.uvs[k + 1];
      st[k + 1] = data.uvs[k];
    }
    geometry.setAttribute("uv", new THREE.BufferAttribute(st, 2));
    let material = this.regionMaterial;
    if (texture) {
      const [u0, v0, u1, v1] = textureRect;
      const local = new Float32Array(data.uvs.length);
      for (let k = 0; k < local.length; k += 2) {
        local[k] = (data.uvs[k] - u0) / (u1 - u0);
        local[k + 1] = (data.uvs[k + 1] - v0) / (v1 - v0);
      }
      geometry.setAttribute("uv1", new THREE.BufferAttribute(local, 2));
      material = this.regionMaterial.clone();
    }
    geometry.setIndex(new THREE.BufferAttribute(data.indices, 1));
    geometry.computeBoundingSphere();
    const mesh = new THREE.Mesh(geometry, material);
    mesh.userData.texture = texture;
    return mesh;
  }

  /**
   * Show exactly the regions of `wanted` (key -> mesh from makeRegionMesh, or one already
   * shown) in one frame: new ones added, the others removed and disposed, the base's mask
   * redrawn. `mask` is {cells, rects}: the mask's cells per side (2^finest level) and the
   * [u0, v0, u1, v1] rectangles the regions cover.
   */
  /**
   * An atlas drawn as separate groups (AtlasLayer) in place of the one mesh: `parts` maps a
   * key to the worker's mesh data ({positions, normals, indices, colors?}: colors linear RGB
   * per vertex, drawn when the material has vertexColors); parts already shown under the same
   * key stay, the others are built, the rest removed, in one frame.
   */
  setAtlasParts(parts) {
    for (const [key, mesh] of this.atlasParts) {
      if (parts.has(key)) continue;
      this.atlasGroup.remove(mesh);
      mesh.geometry.dispose();
      this.atlasParts.delete(key);
    }
    for (const [key, data] of parts) {
      if (this.atlasParts.has(key)) continue;
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute("position", new THREE.BufferAttribute(data.positions, 3));
      geometry.setAttribute("normal", new THREE.BufferAttribute(data.normals, 3));
      if (data.colors) geometry.setAttribute("color", new THREE.BufferAttribute(data.colors, 3));
      geometry.setIndex(new THREE.BufferAttribute(data.indices, 1));
      geometry.computeBoundingSphere();
      const mesh = new THREE.Mesh(geometry, this.regionMaterial);
      this.atlasParts.set(key, mesh);
      this.atlasGroup.add(mesh);
    }
    if (this.mesh) this.mesh.visible = false;
    this.render();
  }

  setRegions(wanted, mask) {
    for (const [key, mesh] of this.regions) {
      if (wanted.get(key) === mesh) continue;
      this.regionGroup.remove(mesh);
      mesh.geometry.dispose();
      if (mesh.material !== this.regionMaterial) mesh.material.dispose();
      this.regions.delete(key);
    }
    for (const [key, mesh] of wanted) {
      if (this.regions.get(key) === mesh) continue;
      this.regions.set(key, mesh);
      this.regionGroup.add(mesh);
    }
    this._applyMaps();
    this._drawMask(mask);
    this.render();
  }

  _drawMask({ cells, rects }) {
    if (!this.mask || this.mask.cells !== cells) {
      if (this.mask) this.mask.texture.dispose();
      const texture = new THREE.DataTexture(new Uint8Array(cells * cells * 4), cells, cells,
                                            THREE.RGBAFormat);
      texture.magFilter = THREE.NearestFilter;
      texture.minFilter = THREE.NearestFilter;
      this.mask = { texture, cells };
      this.maskUniforms.tesseraMask.value = texture;
    }
    const data = this.mask.texture.image.data;
    data.fill(0);
    // texel (column = v cell, row = u cell): the base's uv attribute is (v, u)
    for (const [u0, v0, u1, v1] of rects) {
      for (let r = Math.round(u0 * cells); r < Math.round(u1 * cells); r++) {
        for (let c = Math.round(v0 * cells); c < Math.round(v1 * cells); c++) {
          data.fill(255, 4 * (r * cells + c), 4 * (r * cells + c) + 4);
        }
      }
    }
    this.mask.texture.needsUpdate = true;
    this.maskUniforms.tesseraMaskOn.value = rects.length > 0 ? 1 : 0;
  }
}
