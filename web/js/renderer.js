// WebGL2 drawing: the patch mesh with per-vertex linear radiance, exposed and tone mapped in
// the fragment shader (the same curves as the server's render route), and the light gizmos.
//
// Hand-written WebGL2 rather than three.js: one mesh, one colour attribute and a few lines
// need ~300 lines, the served files stay self-contained (no npm build inside `cargo build`),
// and nothing has to be vendored or kept up to date.

import { add, length, lookAt, multiply, normalize, ortho, perspective, scale, sub } from "./math.js";

const MESH_VS = `#version 300 es
layout(location = 0) in vec3 aPos;
layout(location = 1) in vec3 aNormal;
layout(location = 2) in vec3 aRadiance;
layout(location = 3) in vec2 aGloss;
layout(location = 4) in vec3 aAlbedo;
uniform mat4 uViewProj;
out vec3 vRadiance;
out vec3 vNormal;
out vec3 vPos;
out vec2 vGloss;
out vec3 vAlbedo;
void main() {
  vRadiance = aRadiance;
  vGloss = aGloss;
  vAlbedo = aAlbedo;
  vNormal = aNormal;
  vPos = aPos;
  gl_Position = uViewProj * vec4(aPos, 1.0);
}`;

/** Most lights the viewer's specular pass reads (the first ones of the request). */
export const MAX_SPECULAR_LIGHTS = 16;
/** Lights with shadow maps: the first ones; the direct light per pixel needs every light to have one. */
export const MAX_SHADOWED_LIGHTS = 4;
const CUBE_SIZE = 512;
const MAP_SIZE = 1024;

const MESH_FS = `#version 300 es
precision highp float;
#define MAX_LIGHTS ${MAX_SPECULAR_LIGHTS}
in vec3 vRadiance;
in vec3 vNormal;
in vec3 vPos;
in vec2 vGloss;            // GGX alpha (0: matte) and eta of the surface's specular coat
in vec3 vAlbedo;           // rho of a diffuse surface whose direct light is drawn per pixel
uniform float uExposure;   // 2^EV
uniform int uTone;         // 0: clamp (sRGB), 1: ACES filmic (Narkowicz 2016)
uniform int uLit;          // 0: no radiance yet, shade the geometry so it can be seen
uniform vec3 uEye;
// The specular pass and the direct light per pixel (engine/src/specular.rs, the same
// model): point, spot and directional lights, the first MAX_SHADOWED shadowed by maps.
uniform int uLightCount;
uniform int uDirect;                    // 1: add rho E / pi where vAlbedo is set
uniform int uSpecular;                  // 1: the specular pass where vGloss is set
uniform int uShadowKind[${MAX_SHADOWED_LIGHTS}];         // 0: none, 1: cube map, 2: 2-D map
uniform vec2 uShadowRange[${MAX_SHADOWED_LIGHTS}];       // cube maps: near and far
uniform mat4 uShadowMat[${MAX_SHADOWED_LIGHTS}];         // 2-D maps: world to clip
uniform float uShadowTexel[${MAX_SHADOWED_LIGHTS}];      // 2-D maps: a texel in scene units
uniform highp samplerCubeShadow uCube0, uCube1, uCube2, uCube3;
uniform highp sampler2DShadow uMap0, uMap1, uMap2, uMap3;
uniform vec4 uLightPos[MAX_LIGHTS];     // xyz position and w = 1, or toward the light and w = 0
uniform vec3 uLightPower[MAX_LIGHTS];   // intensity (W/sr) or irradiance (W/m^2)
uniform vec4 uSpotAxis[MAX_LIGHTS];     // xyz axis, w = 1 for a spot
uniform vec2 uSpotCos[MAX_LIGHTS];      // cos of the inner and outer half-angles
uniform float uToM;                     // metres per scene unit
out vec4 outColour;

const float PI = 3.14159265358979;
float ggxD(float a, float c) {
  if (c <= 0.0) return 0.0;
  float a2 = a * a;
  float k = c * c * (a2 - 1.0) + 1.0;
  return a2 / (PI * k * k);
}
float lambda(float a, float c) {
  float c2 = clamp(c * c, 1e-12, 1.0);
  return 0.5 * (-1.0 + sqrt(1.0 + a * a * (1.0 - c2) / c2));
}
float fresnel(float ci, float eta) {
  ci = clamp(ci, 0.0, 1.0);
  float s2 = (1.0 - ci * ci) / (eta * eta);
  if (s2 >= 1.0) return 1.0;
  float ct = sqrt(1.0 - s2);
  float rs = (ci - eta * ct) / (ci + eta * ct);
  float rp = (eta * ci - ct) / (eta * ci + ct);
  return 0.5 * (rs * rs + rp * rp);
}
float brdf(float a, float eta, vec3 n, vec3 l, vec3 v) {
  float nl = dot(n, l), nv = dot(n, v);
  if (nl <= 0.0 || nv <= 0.0) return 0.0;
  vec3 h = normalize(l + v);
  float g2 = 1.0 / (1.0 + lambda(a, nl) + lambda(a, nv));
  return fresnel(dot(v, h), eta) * ggxD(a, dot(n, h)) * g2 / (4.0 * nl * nv);
}
float spotFalloff(float c, vec2 cosIO) {
  if (c >= cosIO.x) return 1.0;
  if (c <= cosIO.y) return 0.0;
  float t = (c - cosIO.y) / (cosIO.x - cosIO.y);
  return t * t * (3.0 - 2.0 * t);
}
float cubeVis(highp samplerCubeShadow s, vec3 p, vec3 lightPos, vec2 range) {
  vec3 d = p - lightPos;
  vec3 a = abs(d);
  float z = max(a.x, max(a.y, a.z));
  float n = range.x, f = range.y;
  float depth = ((f + n) / (f - n) - 2.0 * f * n / ((f - n) * z)) * 0.5 + 0.5;
  return texture(s, vec4(d, depth));
}
float mapVis(highp sampler2DShadow s, vec3 p, mat4 m) {
  vec4 q = m * vec4(p, 1.0);
  vec3 c = q.xyz / q.w * 0.5 + 0.5;
  if (any(lessThan(c.xy, vec2(0.0))) || any(greaterThan(c.xy, vec2(1.0)))) return 1.0;
  return texture(s, c);
}
// Light i's visibility at the fragment, its position pushed off the surface along the normal
// by about a shadow-map texel (the normal-offset bias).
float visibility(int i, vec3 n, vec3 toLight, float r) {
  if (i >= ${MAX_SHADOWED_LIGHTS}) return 1.0;
  int kind = uShadowKind[i];
  if (kind == 0) return 1.0;
  float slope = sqrt(max(0.0, 1.0 - pow(dot(n, toLight), 2.0)));
  if (kind == 1) {
    float texel = 2.0 * r / ${CUBE_SIZE}.0;
    vec3 p = vPos + n * texel * (1.0 + 2.0 * slope);
    vec3 lp = uLightPos[i].xyz;
    vec2 range = uShadowRange[i];
    if (i == 0) return cubeVis(uCube0, p, lp, range);
    if (i == 1) return cubeVis(uCube1, p, lp, range);
    if (i == 2) return cubeVis(uCube2, p, lp, range);
    return cubeVis(uCube3, p, lp, range);
  }
  vec3 p = vPos + n * uShadowTexel[i] * (1.0 + 2.0 * slope);
  if (i == 0) return mapVis(uMap0, p, uShadowMat[0]);
  if (i == 1) return mapVis(uMap1, p, uShadowMat[1]);
  if (i == 2) return mapVis(uMap2, p, uShadowMat[2]);
  return mapVis(uMap3, p, uShadowMat[3]);
}
// The direct light per pixel (rho E / pi) and the specular pass, from the first
// uLightCount lights.
vec3 pixelLight(vec3 n, vec3 v, bool glossy, bool diffuse) {
  vec3 sum = vec3(0.0);
  for (int i = 0; i < MAX_LIGHTS; i++) {
    if (i >= uLightCount) break;
    vec4 lp = uLightPos[i];
    vec3 l;
    float e;
    float r = 0.0;
    if (lp.w > 0.5) {
      vec3 d = lp.xyz - vPos;
      r = length(d);
      if (r <= 0.0) continue;
      l = d / r;
      float rm = r * uToM;
      e = 1.0 / (rm * rm);
      if (uSpotAxis[i].w > 0.5) e *= spotFalloff(dot(uSpotAxis[i].xyz, -l), uSpotCos[i]);
    } else {
      l = lp.xyz;
      e = 1.0;
    }
    float nl = dot(n, l);
    if (nl <= 0.0 || e <= 0.0) continue;
    e *= visibility(i, n, l, r);
    if (e <= 0.0) continue;
    float f = 0.0;
    if (glossy && dot(n, v) > 0.0) f += brdf(vGloss.x, vGloss.y, n, l, v);
    vec3 c = f * nl * e * uLightPower[i];
    if (diffuse) c += vAlbedo * (nl * e / PI) * uLightPower[i];
    sum += c;
  }
  return sum;
}

float srgbOetf(float v) {
  v = clamp(v, 0.0, 1.0);
  return v <= 0.0031308 ? 12.92 * v : 1.055 * pow(v, 1.0 / 2.4) - 0.055;
}
vec3 aces(vec3 x) {
  x = clamp(x, 0.0, 1e4);
  return clamp((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0);
}
void main() {
  vec3 c;
  if (uLit == 1) {
    vec3 lin = max(vRadiance, vec3(0.0));
    bool glossy = uSpecular == 1 && vGloss.x > 0.0;
    bool diffuse = uDirect == 1 && max(vAlbedo.r, max(vAlbedo.g, vAlbedo.b)) > 0.0;
    if ((glossy || diffuse) && uLightCount > 0) {
      vec3 n = normalize(vNormal);
      vec3 v = normalize(uEye - vPos);
      lin += pixelLight(n, v, glossy, diffuse);
    }
    vec3 x = lin * uExposure;
    c = uTone == 1 ? aces(x) : min(x, vec3(1.0));
  } else {
    vec3 n = normalize(vNormal);
    float k = abs(dot(n, normalize(uEye - vPos)));
    c = vec3(0.05 + 0.12 * k);
  }
  outColour = vec4(srgbOetf(c.r), srgbOetf(c.g), srgbOetf(c.b), 1.0);
}`;

// Shadow maps: depth only.
const DEPTH_VS = `#version 300 es
layout(location = 0) in vec3 aPos;
uniform mat4 uViewProj;
void main() {
  gl_Position = uViewProj * vec4(aPos, 1.0);
}`;
const DEPTH_FS = `#version 300 es
precision mediump float;
void main() {}`;

// The cube map faces in GL's order (+X, -X, +Y, -Y, +Z, -Z): view direction and up.
const CUBE_FACES = [
  [[1, 0, 0], [0, -1, 0]], [[-1, 0, 0], [0, -1, 0]], [[0, 1, 0], [0, 0, 1]],
  [[0, -1, 0], [0, 0, -1]], [[0, 0, 1], [0, -1, 0]], [[0, 0, -1], [0, -1, 0]],
];

// Gizmo lines and handles: positions with display colours (already sRGB), no depth test.
const LINE_VS = `#version 300 es
layout(location = 0) in vec3 aPos;
layout(location = 1) in vec4 aColour;
uniform mat4 uViewProj;
uniform float uPointSize;
out vec4 vColour;
void main() {
  vColour = aColour;
  gl_Position = uViewProj * vec4(aPos, 1.0);
  gl_PointSize = uPointSize;
}`;

const LINE_FS = `#version 300 es
precision mediump float;
in vec4 vColour;
uniform int uRound;
out vec4 outColour;
void main() {
  if (uRound == 1) {
    vec2 p = gl_PointCoord * 2.0 - 1.0;
    float r = dot(p, p);
    if (r > 1.0) discard;
    // A dark ring around a bright disc: visible on light and dark walls alike.
    outColour = r > 0.55 ? vec4(0.05, 0.05, 0.06, 1.0) : vColour;
  } else {
    outColour = vColour;
  }
}`;

function compile(gl, vs, fs) {
  const prog = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) {
      throw new Error("shader does not compile: " + gl.getShaderInfoLog(s));
    }
    gl.attachShader(prog, s);
  }
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) {
    throw new Error("shader does not link: " + gl.getProgramInfoLog(prog));
  }
  const uniforms = {};
  const n = gl.getProgramParameter(prog, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) {
    const name = gl.getActiveUniform(prog, i).name;
    uniforms[name] = gl.getUniformLocation(prog, name);
  }
  return { prog, uniforms };
}

export class Renderer {
  constructor(canvas) {
    this.canvas = canvas;
    const gl = canvas.getContext("webgl2", {
      antialias: true,
      // Kept so snapshots and the browser tests read what is shown.
      preserveDrawingBuffer: true,
    });
    if (!gl) {
      throw new Error("this browser has no WebGL2; the viewer needs it to draw the mesh");
    }
    this.gl = gl;
    this.mesh = compile(gl, MESH_VS, MESH_FS);
    this.lines = compile(gl, LINE_VS, LINE_FS);
    this.depth = compile(gl, DEPTH_VS, DEPTH_FS);
    // Shadow maps per shadowed light (made on first use), and 1×1 stand-ins so that every
    // shadow sampler always has a complete depth texture bound.
    this.shadows = [];
    this.shadowKey = null;
    this.shadowFbo = gl.createFramebuffer();
    this.dummyCube = this.depthTexture(gl.TEXTURE_CUBE_MAP, 1);
    this.dummyMap = this.depthTexture(gl.TEXTURE_2D, 1);
    this.meshVao = null;
    this.indexCount = 0;
    this.vertexCount = 0;
    this.lit = false;
    this.gizmoVao = gl.createVertexArray();
    this.gizmoBuf = gl.createBuffer();
    gl.bindVertexArray(this.gizmoVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.gizmoBuf);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 28, 0);
    gl.enableVertexAttribArray(1);
    gl.vertexAttribPointer(1, 4, gl.FLOAT, false, 28, 12);
    gl.bindVertexArray(null);
  }

  /** Uploads a mesh: flat positions, normals (3 per vertex) and triangle indices. */
  setMesh(positions, normals, indices) {
    const gl = this.gl;
    if (this.meshVao) {
      gl.deleteVertexArray(this.meshVao);
      for (const b of this.meshBuffers) gl.deleteBuffer(b);
    }
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const buf = (data, loc, size = 3) => {
      const b = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, b);
      gl.bufferData(gl.ARRAY_BUFFER, data, loc >= 2 ? gl.DYNAMIC_DRAW : gl.STATIC_DRAW);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, size, gl.FLOAT, false, 0, 0);
      return b;
    };
    const n = positions.length / 3;
    const pos = buf(new Float32Array(positions), 0);
    const nor = buf(new Float32Array(normals), 1);
    const rad = buf(new Float32Array(n * 3), 2);
    const gloss = buf(new Float32Array(n * 2), 3, 2);
    const albedo = buf(new Float32Array(n * 3), 4);
    const ib = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, new Uint32Array(indices), gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    this.meshVao = vao;
    this.meshBuffers = [pos, nor, rad, gloss, albedo, ib];
    this.radianceBuf = rad;
    this.glossBuf = gloss;
    this.albedoBuf = albedo;
    this.shadowKey = null;
    this.indexCount = indices.length;
    this.vertexCount = n;
    this.lit = false;
  }

  /** New per-vertex linear radiance (Float32Array, 3 per vertex). */
  setRadiance(radiance) {
    if (radiance.length !== this.vertexCount * 3) {
      throw new Error(
        `the server sent ${radiance.length / 3} vertex colours for a mesh of ${this.vertexCount} vertices`,
      );
    }
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.radianceBuf);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, radiance);
    this.lit = true;
  }

  /** Each vertex's specular coat (Float32Array, GGX alpha and eta per vertex; alpha 0: none). */
  setGloss(gloss) {
    if (gloss.length !== this.vertexCount * 2) {
      throw new Error(`gloss has ${gloss.length / 2} entries for a mesh of ${this.vertexCount} vertices`);
    }
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.glossBuf);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, gloss);
  }

  /** Each vertex's albedo for the direct light per pixel (Float32Array, 3 per vertex; 0: none). */
  setAlbedo(albedo) {
    if (albedo.length !== this.vertexCount * 3) {
      throw new Error(`albedo has ${albedo.length / 3} entries for a mesh of ${this.vertexCount} vertices`);
    }
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.albedoBuf);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, albedo);
  }

  /** A depth texture set up for comparisons (`size`² texels, each face for a cube map). */
  depthTexture(target, size) {
    const gl = this.gl;
    const t = gl.createTexture();
    gl.bindTexture(target, t);
    const faces = target === gl.TEXTURE_CUBE_MAP
      ? [0, 1, 2, 3, 4, 5].map((k) => gl.TEXTURE_CUBE_MAP_POSITIVE_X + k) : [gl.TEXTURE_2D];
    for (const f of faces) {
      gl.texImage2D(f, 0, gl.DEPTH_COMPONENT24, size, size, 0, gl.DEPTH_COMPONENT, gl.UNSIGNED_INT, null);
    }
    gl.texParameteri(target, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(target, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(target, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(target, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    gl.texParameteri(target, gl.TEXTURE_COMPARE_MODE, gl.COMPARE_REF_TO_TEXTURE);
    gl.texParameteri(target, gl.TEXTURE_COMPARE_FUNC, gl.LEQUAL);
    if (size === 1) {
      // A stand-in reads "lit" everywhere: depth 1 passes every comparison.
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.shadowFbo);
      for (const f of faces) {
        gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, f, t, 0);
        gl.clearDepth(1);
        gl.clear(gl.DEPTH_BUFFER_BIT);
      }
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    }
    return t;
  }

  /**
   * Renders the shadow maps of the first MAX_SHADOWED_LIGHTS point, spot and directional
   * lights (a cube map around a point or spot light, an orthographic map over the scene's
   * bounding sphere `bounds` = { centre, radius } for a directional one), unless the lights
   * and mesh are those of the last call.
   */
  updateShadows(lights, bounds) {
    const gl = this.gl;
    const key = JSON.stringify([lights, bounds, this.indexCount]);
    if (key === this.shadowKey || !this.meshVao) return;
    this.shadowKey = key;
    const { prog, uniforms: u } = this.depth;
    gl.useProgram(prog);
    gl.bindVertexArray(this.meshVao);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.shadowFbo);
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LESS);
    gl.disable(gl.CULL_FACE);
    gl.enable(gl.POLYGON_OFFSET_FILL);
    gl.polygonOffset(1.5, 4);
    gl.colorMask(false, false, false, false);
    const R = bounds.radius;
    this.shadows = lights.slice(0, MAX_SHADOWED_LIGHTS).map((l, i) => {
      const old = this.shadows[i];
      if (l.type === "directional") {
        const tex = old && old.kind === 2 ? old.tex : this.depthTexture(gl.TEXTURE_2D, MAP_SIZE);
        const d = normalize(l.direction);
        const eye = sub(bounds.centre, scale(d, 2 * R));
        const up = Math.abs(d[1]) > 0.9 ? [0, 0, 1] : [0, 1, 0];
        const m = multiply(ortho(-R, R, -R, R, 0.5 * R, 3.5 * R), lookAt(eye, bounds.centre, up));
        gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.TEXTURE_2D, tex, 0);
        gl.viewport(0, 0, MAP_SIZE, MAP_SIZE);
        gl.clear(gl.DEPTH_BUFFER_BIT);
        gl.uniformMatrix4fv(u.uViewProj, false, m);
        gl.drawElements(gl.TRIANGLES, this.indexCount, gl.UNSIGNED_INT, 0);
        return { kind: 2, tex, mat: m, texel: (2 * R) / MAP_SIZE };
      }
      const tex = old && old.kind === 1 ? old.tex : this.depthTexture(gl.TEXTURE_CUBE_MAP, CUBE_SIZE);
      const p = l.position;
      const dist = length(sub(p, bounds.centre));
      const near = 1e-3 * R, far = dist + 2 * R;
      const proj = perspective(Math.PI / 2, 1, near, far);
      gl.viewport(0, 0, CUBE_SIZE, CUBE_SIZE);
      CUBE_FACES.forEach(([dir, up], k) => {
        gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.TEXTURE_CUBE_MAP_POSITIVE_X + k, tex, 0);
        gl.clear(gl.DEPTH_BUFFER_BIT);
        gl.uniformMatrix4fv(u.uViewProj, false, multiply(proj, lookAt(p, add(p, dir), up)));
        gl.drawElements(gl.TRIANGLES, this.indexCount, gl.UNSIGNED_INT, 0);
      });
      return { kind: 1, tex, range: [near, far] };
    });
    gl.colorMask(true, true, true, true);
    gl.disable(gl.POLYGON_OFFSET_FILL);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.bindVertexArray(null);
  }

  /** Binds the shadow maps and their uniforms for the mesh program. */
  bindShadows(u, on) {
    const gl = this.gl;
    const kinds = new Int32Array(MAX_SHADOWED_LIGHTS);
    const ranges = new Float32Array(2 * MAX_SHADOWED_LIGHTS);
    const mats = new Float32Array(16 * MAX_SHADOWED_LIGHTS);
    const texels = new Float32Array(MAX_SHADOWED_LIGHTS);
    for (let i = 0; i < MAX_SHADOWED_LIGHTS; i++) {
      const sm = on ? this.shadows[i] : null;
      gl.activeTexture(gl.TEXTURE1 + 2 * i);
      gl.bindTexture(gl.TEXTURE_CUBE_MAP, sm && sm.kind === 1 ? sm.tex : this.dummyCube);
      gl.uniform1i(u[`uCube${i}`], 1 + 2 * i);
      gl.activeTexture(gl.TEXTURE2 + 2 * i);
      gl.bindTexture(gl.TEXTURE_2D, sm && sm.kind === 2 ? sm.tex : this.dummyMap);
      gl.uniform1i(u[`uMap${i}`], 2 + 2 * i);
      if (!sm) continue;
      kinds[i] = sm.kind;
      if (sm.kind === 1) ranges.set(sm.range, 2 * i);
      else {
        mats.set(sm.mat, 16 * i);
        texels[i] = sm.texel;
      }
    }
    gl.activeTexture(gl.TEXTURE0);
    gl.uniform1iv(u["uShadowKind[0]"], kinds);
    gl.uniform2fv(u["uShadowRange[0]"], ranges);
    gl.uniformMatrix4fv(u["uShadowMat[0]"], false, mats);
    gl.uniform1fv(u["uShadowTexel[0]"], texels);
  }

  /** Matches the drawing buffer to the canvas's CSS size × devicePixelRatio. */
  resize() {
    const dpr = Math.min(window.devicePixelRatio || 1, 2);
    const w = Math.max(1, Math.round(this.canvas.clientWidth * dpr));
    const h = Math.max(1, Math.round(this.canvas.clientHeight * dpr));
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
    }
  }

  /**
   * Draws a frame. `view`: { viewProj, eye }; `opts`: { exposure (EV), tone, cullBackfaces,
   * background [r,g,b] display values, gizmo: { lines: Float32Array, points: Float32Array },
   * highlights: null (off) or { lights (the API's lights; environments are skipped), unitMm,
   * specular (bool: the specular pass), direct (bool: the direct light per pixel), shadows
   * (bool), bounds: { centre, radius } } }.
   */
  draw(view, opts) {
    const gl = this.gl;
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    const bg = opts.background;
    gl.clearColor(bg[0], bg[1], bg[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    const hl = opts.highlights;
    if (this.meshVao && hl && hl.shadows) {
      this.updateShadows(hl.lights.filter((l) => l.type !== "environment"), hl.bounds);
      gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    }
    if (this.meshVao) {
      gl.enable(gl.DEPTH_TEST);
      gl.depthFunc(gl.LEQUAL);
      if (opts.cullBackfaces) gl.enable(gl.CULL_FACE);
      else gl.disable(gl.CULL_FACE);
      gl.cullFace(gl.BACK);
      gl.frontFace(gl.CCW);
      const { prog, uniforms: u } = this.mesh;
      gl.useProgram(prog);
      gl.uniformMatrix4fv(u.uViewProj, false, view.viewProj);
      gl.uniform1f(u.uExposure, Math.pow(2, opts.exposure));
      gl.uniform1i(u.uTone, opts.tone === "filmic" ? 1 : 0);
      gl.uniform1i(u.uLit, this.lit ? 1 : 0);
      gl.uniform3fv(u.uEye, view.eye);
      this.setLights(u, opts.highlights);
      gl.bindVertexArray(this.meshVao);
      gl.drawElements(gl.TRIANGLES, this.indexCount, gl.UNSIGNED_INT, 0);
      gl.bindVertexArray(null);
    }
    if (opts.gizmo) this.drawGizmo(view, opts.gizmo);
  }

  /** The specular pass's light uniforms (the same conversions as engine/src/specular.rs). */
  setLights(u, highlights) {
    const gl = this.gl;
    const lights = highlights ? highlights.lights.filter((l) => l.type !== "environment").slice(0, MAX_SPECULAR_LIGHTS) : [];
    this.bindShadows(u, !!(highlights && highlights.shadows));
    gl.uniform1i(u.uDirect, highlights && highlights.direct ? 1 : 0);
    const pos = new Float32Array(4 * MAX_SPECULAR_LIGHTS);
    const power = new Float32Array(3 * MAX_SPECULAR_LIGHTS);
    const axis = new Float32Array(4 * MAX_SPECULAR_LIGHTS);
    const cone = new Float32Array(2 * MAX_SPECULAR_LIGHTS);
    const unit = (v) => {
      const n = Math.hypot(v[0], v[1], v[2]) || 1;
      return [v[0] / n, v[1] / n, v[2] / n];
    };
    lights.forEach((l, i) => {
      if (l.type === "directional") {
        const d = unit(l.direction);
        pos.set([-d[0], -d[1], -d[2], 0], 4 * i);
        power.set(l.irradiance, 3 * i);
      } else {
        pos.set([...l.position, 1], 4 * i);
        power.set(l.intensity, 3 * i);
        if (l.type === "spot") {
          axis.set([...unit(l.direction), 1], 4 * i);
          const rad = Math.PI / 180;
          cone.set([Math.cos(l.inner_deg * rad), Math.cos(l.outer_deg * rad)], 2 * i);
        }
      }
    });
    gl.uniform1i(u.uLightCount, lights.length);
    gl.uniform4fv(u["uLightPos[0]"], pos);
    gl.uniform3fv(u["uLightPower[0]"], power);
    gl.uniform4fv(u["uSpotAxis[0]"], axis);
    gl.uniform2fv(u["uSpotCos[0]"], cone);
    gl.uniform1f(u.uToM, highlights ? highlights.unitMm / 1000 : 1);
    gl.uniform1i(u.uSpecular, highlights && highlights.specular ? 1 : 0);
  }

  drawGizmo(view, gizmo) {
    const gl = this.gl;
    gl.disable(gl.DEPTH_TEST);
    gl.disable(gl.CULL_FACE);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
    const { prog, uniforms: u } = this.lines;
    gl.useProgram(prog);
    gl.uniformMatrix4fv(u.uViewProj, false, view.viewProj);
    gl.bindVertexArray(this.gizmoVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.gizmoBuf);
    if (gizmo.lines.length) {
      gl.bufferData(gl.ARRAY_BUFFER, gizmo.lines, gl.STREAM_DRAW);
      gl.uniform1i(u.uRound, 0);
      gl.drawArrays(gl.LINES, 0, gizmo.lines.length / 7);
    }
    const dpr = this.canvas.width / Math.max(1, this.canvas.clientWidth);
    for (const group of gizmo.points) {
      if (!group.data.length) continue;
      gl.bufferData(gl.ARRAY_BUFFER, group.data, gl.STREAM_DRAW);
      gl.uniform1i(u.uRound, 1);
      gl.uniform1f(u.uPointSize, group.size * dpr);
      gl.drawArrays(gl.POINTS, 0, group.data.length / 7);
    }
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND);
  }

  /** A w×h downsampled copy of the drawing buffer as sRGB bytes (RGBA), for tests. */
  readPixels() {
    const gl = this.gl;
    const w = this.canvas.width, h = this.canvas.height;
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    return { w, h, px };
  }
}
