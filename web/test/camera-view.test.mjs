// camera-view.js: the first view's camera and the turntable's polar limits.

import assert from "node:assert/strict";
import { test } from "node:test";

import { frontView, horizontalFront, MAX_POLAR, MIN_POLAR, polarAngle, TILT_DEG }
  from "../src/camera-view.js";

const close = (a, b, eps = 1e-9) =>
  a.forEach((x, k) => assert.ok(Math.abs(x - b[k]) < eps, `[${a}] != [${b}]`));

test("horizontalFront removes the part along up and normalises; a front along up is refused", () => {
  close(horizontalFront([0, 0, 2], [3, 0, 4]), [1, 0, 0]);
  close(horizontalFront([0, 1, 0], [0, 0.5, -2]), [0, 0, -1]);
  assert.throws(() => horizontalFront([0, 1, 0], [0, -3, 0]), /front perpendicular to up/);
  assert.throws(() => horizontalFront([0, 0, 0], [1, 0, 0]), /up must be a finite non-zero/);
});

test("frontView: camera on the front side, TILT_DEG above the horizon, up = the object's up", () => {
  const pose = frontView({ center: [1, 2, 3], radius: 2, up: [0, 0, 5], front: [0, -1, 0],
                           fovDeg: 35, aspect: 1.5 });
  close(pose.up, [0, 0, 1]);
  close(pose.target, [1, 2, 3]);
  const offset = pose.position.map((x, k) => x - pose.target[k]);
  const length = Math.hypot(...offset);
  assert.ok(Math.abs(length - pose.distance) < 1e-9);
  const t = (TILT_DEG * Math.PI) / 180;
  close(offset.map((x) => x / length), [0, -Math.cos(t), Math.sin(t)]);
  // aspect >= 1: the vertical field of view fits the sphere with a 5 % margin
  assert.ok(Math.abs(pose.distance - (1.05 * 2) / Math.sin((35 * Math.PI) / 360)) < 1e-9);
  assert.ok(pose.near < pose.distance - 2 && pose.far > pose.distance + 2);
  assert.ok(Math.abs(polarAngle(pose.position, pose.target, pose.up) - (Math.PI / 2 - t)) < 1e-9);
});

test("frontView: a narrow canvas backs off so the sphere fits its width", () => {
  const wide = frontView({ center: [0, 0, 0], radius: 1, up: [0, 1, 0], front: [0, 0, 1],
                           fovDeg: 35, aspect: 2 });
  const narrow = frontView({ center: [0, 0, 0], radius: 1, up: [0, 1, 0], front: [0, 0, 1],
                             fovDeg: 35, aspect: 0.5 });
  assert.ok(narrow.distance > 1.8 * wide.distance);
});

test("frontView refuses a degenerate scene", () => {
  const scene = { center: [0, 0, 0], radius: 1, up: [0, 1, 0], front: [0, 0, 1], fovDeg: 35, aspect: 1 };
  assert.throws(() => frontView({ ...scene, radius: 0 }), /radius > 0/);
  assert.throws(() => frontView({ ...scene, aspect: -1 }), /aspect > 0/);
  assert.throws(() => frontView({ ...scene, front: [0, 2, 0] }), /perpendicular/);
});

test("the polar limits keep the turntable off both poles", () => {
  assert.ok(MIN_POLAR > 0 && MAX_POLAR < Math.PI && MIN_POLAR < MAX_POLAR);
  assert.ok(Math.abs(polarAngle([0, 5, 0], [0, 0, 0], [0, 1, 0])) < 1e-9);
  assert.ok(Math.abs(polarAngle([0, -5, 0], [0, 0, 0], [0, 1, 0]) - Math.PI) < 1e-9);
});
