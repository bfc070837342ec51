// An orbit camera: a target, a distance, yaw and pitch around the target, a vertical field of
// view. Orbit (left drag), pan (right or shift drag), zoom (wheel), fit to a bounding box.

import {
  add, sub, scale, cross, normalize, length, clamp, lookAt, perspective, multiply, rad, deg,
} from "./math.js";

export class OrbitCamera {
  constructor() {
    this.target = [0, 0, 0];
    this.distance = 1;
    this.yaw = 0; // radians, around +Y; 0 looks along −Z
    this.pitch = 0; // radians, positive looks down from above
    this.fovDeg = 40;
    this.sceneRadius = 1;
  }

  /** Sets the camera from a position and a target (the scene's or the URL's camera). */
  setLookAt(position, target, fovDeg) {
    const d = sub(position, target);
    this.target = [...target];
    this.distance = Math.max(length(d), 1e-6);
    this.yaw = Math.atan2(d[0], d[2]);
    this.pitch = Math.asin(clamp(d[1] / this.distance, -1, 1));
    if (fovDeg) this.fovDeg = fovDeg;
  }

  eye() {
    const c = Math.cos(this.pitch);
    const off = [c * Math.sin(this.yaw), Math.sin(this.pitch), c * Math.cos(this.yaw)];
    return add(this.target, scale(off, this.distance));
  }

  /** Right and up unit vectors of the view. */
  basis() {
    const f = normalize(sub(this.target, this.eye()));
    const r = normalize(cross(f, [0, 1, 0]));
    const u = cross(r, f);
    return { f, r, u };
  }

  orbit(dxPx, dyPx) {
    this.yaw -= dxPx * 0.006;
    this.pitch = clamp(this.pitch + dyPx * 0.006, rad(-89), rad(89));
  }

  pan(dxPx, dyPx, heightPx) {
    const { r, u } = this.basis();
    const perPx = (2 * this.distance * Math.tan(rad(this.fovDeg) / 2)) / heightPx;
    this.target = add(this.target, add(scale(r, -dxPx * perPx), scale(u, dyPx * perPx)));
  }

  zoom(factor) {
    const r = this.sceneRadius;
    this.distance = clamp(this.distance * factor, r * 1e-3, r * 100);
  }

  /** Frames the box [min, max] so the whole bounding sphere fits the view. */
  fit(min, max, aspect) {
    const c = scale(add(min, max), 0.5);
    const r = Math.max(length(sub(max, min)) / 2, 1e-6);
    const vf = rad(this.fovDeg) / 2;
    const hf = Math.atan(Math.tan(vf) * aspect);
    this.target = c;
    this.distance = (r / Math.sin(Math.min(vf, hf))) * 1.02;
  }

  matrices(aspect) {
    const eye = this.eye();
    const r = this.sceneRadius;
    const near = Math.max(this.distance * 0.01, r * 1e-4);
    const far = this.distance + r * 4;
    const view = lookAt(eye, this.target, [0, 1, 0]);
    const proj = perspective(rad(this.fovDeg), aspect, near, far);
    return { eye, view, proj, viewProj: multiply(proj, view) };
  }

  /** A world-space ray through CSS pixel (x, y) of a w×h viewport. */
  ray(x, y, w, h) {
    const { f, r, u } = this.basis();
    const ty = Math.tan(rad(this.fovDeg) / 2);
    const nx = ((2 * x) / w - 1) * ty * (w / h);
    const ny = (1 - (2 * y) / h) * ty;
    return { o: this.eye(), d: normalize(add(f, add(scale(r, nx), scale(u, ny)))) };
  }

  /** The camera in the API's form (`RenderRequest.camera`). */
  toJSON() {
    const round = (v) => v.map((x) => +x.toFixed(5));
    return {
      position: round(this.eye()),
      target: round(this.target),
      up: [0, 1, 0],
      fov_deg: +this.fovDeg.toFixed(3),
    };
  }

  describe() {
    return `yaw ${deg(this.yaw).toFixed(0)}°, pitch ${deg(this.pitch).toFixed(0)}°`;
  }
}
