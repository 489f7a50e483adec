// The first view of an object and the turntable's limits, as plain vector math (no three.js,
// so node --test checks it): the camera looks at the object's front from a little above,
// with the object's up (the manifest's `view.up`, docs/format.md) as screen-up.
//
// The camera sits at  c + d (f cos t + u sin t)  looking at c, where c and r are the bounding
// sphere's centre and radius, u the unit up, f the unit front made perpendicular to u,
// t = TILT_DEG and d = 1.05 r / sin(fit / 2) with fit the smaller of the vertical field of
// view and the horizontal one: the sphere just fits the visible part of the canvas.

export const TILT_DEG = 10;
/** The turntable's polar limits (radians from up): it cannot turn over the poles. */
export const MIN_POLAR = 0.12;
export const MAX_POLAR = Math.PI - 0.12;
const MARGIN = 1.05;

function dot(a, b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

function unit(a, what) {
  const length = Math.hypot(a[0], a[1], a[2]);
  if (!(length > 1e-9) || !Number.isFinite(length)) {
    throw new Error(`${what} must be a finite non-zero 3-vector, got [${a}]`);
  }
  return a.map((x) => x / length);
}

/** The unit front made perpendicular to the unit up: f - (f.u) u, normalised; a front along
 *  up (no horizontal part) is refused. */
export function horizontalFront(up, front) {
  const u = unit(up, "up");
  const f = unit(front, "front");
  const along = dot(f, u);
  return unit(f.map((x, k) => x - along * u[k]), "front perpendicular to up");
}

/**
 * The camera of the first view.
 * @param {{center: number[], radius: number, up: number[], front: number[],
 *          fovDeg: number, aspect: number}} scene  aspect: width/height of the visible canvas
 * @returns {{position: number[], target: number[], up: number[], distance: number,
 *            near: number, far: number}}
 */
export function frontView({ center, radius, up, front, fovDeg, aspect }) {
  if (!(radius > 0) || !(fovDeg > 0 && fovDeg < 180) || !(aspect > 0)) {
    throw new Error(`frontView needs radius > 0, 0 < fovDeg < 180 and aspect > 0, got ` +
                    `${radius}, ${fovDeg}, ${aspect}`);
  }
  const u = unit(up, "up");
  const f = horizontalFront(u, front);
  const tilt = (TILT_DEG * Math.PI) / 180;
  const look = f.map((x, k) => x * Math.cos(tilt) + u[k] * Math.sin(tilt));
  const fov = (fovDeg * Math.PI) / 180;
  const fit = Math.min(fov, 2 * Math.atan(Math.tan(fov / 2) * aspect));
  const distance = (MARGIN * radius) / Math.sin(fit / 2);
  return {
    position: center.map((x, k) => x + distance * look[k]),
    target: [...center],
    up: u,
    distance,
    near: distance / 100,
    far: distance * 100,
  };
}

/** The polar angle (radians) of the camera at `position` about `target`, from `up`. */
export function polarAngle(position, target, up) {
  const offset = unit(position.map((x, k) => x - target[k]), "camera offset");
  return Math.acos(Math.max(-1, Math.min(1, dot(offset, unit(up, "up")))));
}
