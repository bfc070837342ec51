// Small vector and 4×4 matrix helpers (column-major Float32Array, as WebGL expects).
// Written by hand: a dozen functions do not justify vendoring a math library.

export const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
export const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
export const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
export const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
export const cross = (a, b) => [
  a[1] * b[2] - a[2] * b[1],
  a[2] * b[0] - a[0] * b[2],
  a[0] * b[1] - a[1] * b[0],
];
export const length = (a) => Math.hypot(a[0], a[1], a[2]);
export function normalize(a) {
  const l = length(a);
  return l > 0 ? scale(a, 1 / l) : [0, 0, 0];
}
export const clamp = (x, lo, hi) => Math.min(hi, Math.max(lo, x));

export function perspective(fovyRad, aspect, near, far) {
  const f = 1 / Math.tan(fovyRad / 2);
  const m = new Float32Array(16);
  m[0] = f / aspect;
  m[5] = f;
  m[10] = (far + near) / (near - far);
  m[11] = -1;
  m[14] = (2 * far * near) / (near - far);
  return m;
}

/** An orthographic projection of the box [l, r] × [b, t] × [-n, -f] in view space. */
export function ortho(l, r, b, t, n, f) {
  const m = new Float32Array(16);
  m[0] = 2 / (r - l);
  m[5] = 2 / (t - b);
  m[10] = -2 / (f - n);
  m[12] = -(r + l) / (r - l);
  m[13] = -(t + b) / (t - b);
  m[14] = -(f + n) / (f - n);
  m[15] = 1;
  return m;
}

export function lookAt(eye, target, up) {
  const z = normalize(sub(eye, target));
  let x = normalize(cross(up, z));
  if (length(x) === 0) x = normalize(cross([0, 0, 1], z));
  const y = cross(z, x);
  const m = new Float32Array(16);
  m[0] = x[0]; m[4] = x[1]; m[8] = x[2];
  m[1] = y[0]; m[5] = y[1]; m[9] = y[2];
  m[2] = z[0]; m[6] = z[1]; m[10] = z[2];
  m[12] = -dot(x, eye);
  m[13] = -dot(y, eye);
  m[14] = -dot(z, eye);
  m[15] = 1;
  return m;
}

export function multiply(a, b) {
  const m = new Float32Array(16);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      m[c * 4 + r] = s;
    }
  }
  return m;
}

/** Projects world point p with view-projection m: [x, y] in CSS pixels of a w×h viewport
 *  (y down), depth w (> 0 in front of the camera). */
export function project(m, p, w, h) {
  const x = m[0] * p[0] + m[4] * p[1] + m[8] * p[2] + m[12];
  const y = m[1] * p[0] + m[5] * p[1] + m[9] * p[2] + m[13];
  const cw = m[3] * p[0] + m[7] * p[1] + m[11] * p[2] + m[15];
  return { x: ((x / cw + 1) / 2) * w, y: ((1 - y / cw) / 2) * h, w: cw };
}

/** The point of line (o, d) closest to line (p, e); null when they are parallel. Returns
 *  the parameter t along (o, d). */
export function closestOnLine(o, d, p, e) {
  const w0 = sub(o, p);
  const a = dot(d, d), b = dot(d, e), c = dot(e, e), dd = dot(d, w0), ee = dot(e, w0);
  const den = a * c - b * b;
  if (Math.abs(den) < 1e-12) return null;
  return (b * ee - c * dd) / den;
}

/** Where ray (o, d) meets the plane through p with normal n; null when parallel or behind. */
export function rayPlane(o, d, p, n) {
  const den = dot(d, n);
  if (Math.abs(den) < 1e-9) return null;
  const t = dot(sub(p, o), n) / den;
  return t > 0 ? add(o, scale(d, t)) : null;
}

/** sRGB OETF (IEC 61966-2-1) and its inverse, on [0, 1]. */
export const srgbOetf = (v) => {
  v = clamp(v, 0, 1);
  return v <= 0.0031308 ? 12.92 * v : 1.055 * Math.pow(v, 1 / 2.4) - 0.055;
};
export const srgbEotf = (v) => {
  v = clamp(v, 0, 1);
  return v <= 0.04045 ? v / 12.92 : Math.pow((v + 0.055) / 1.055, 2.4);
};

/** The ACES filmic fit of Narkowicz (2016), as the server's render route uses it. */
export function acesFilmic(x) {
  x = clamp(x, 0, 1e4);
  return clamp((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0, 1);
}

/** Tone curve per channel on exposed linear radiance (0 for NaN and negatives). */
export function toneMap(x, tone) {
  x = x > 0 ? x : 0;
  return tone === "filmic" ? acesFilmic(x) : Math.min(x, 1);
}

export const deg = (r) => (r * 180) / Math.PI;
export const rad = (d) => (d * Math.PI) / 180;

/** A unit direction from yaw (around +Y, 0 = −Z) and pitch (up positive), in degrees. */
export function dirFromAngles(yawDeg, pitchDeg) {
  const y = rad(yawDeg), p = rad(pitchDeg);
  return [Math.cos(p) * Math.sin(y), Math.sin(p), -Math.cos(p) * Math.cos(y)];
}
export function anglesFromDir(d) {
  const n = normalize(d);
  return { yaw: deg(Math.atan2(n[0], -n[2])), pitch: deg(Math.asin(clamp(n[1], -1, 1))) };
}
