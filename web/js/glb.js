// Binary glTF 2.0 (.glb) of the relit mesh, built in the browser with the layout that
// `translux-server export` writes (precompute/src/export.rs): POSITION (with min/max), unit
// NORMAL (a zero normal becomes +Z), COLOR_0 as linear float RGB = tone(L · 2^EV) without the
// sRGB OETF (glTF vertex colours are linear), u32 indices, a white unlit material
// (KHR_materials_unlit), single-sided.

import { toneMap } from "./math.js";

/**
 * `mesh`: { positions, normals, indices } (flat arrays); `radiance`: Float32Array, 3 per
 * vertex; `exposure`: EV stops; `tone`: "srgb" | "filmic". Returns a Uint8Array.
 */
export function buildGlb(mesh, radiance, exposure, tone, generator) {
  const n = mesh.positions.length / 3;
  const f = mesh.indices.length;
  if (radiance.length !== n * 3) {
    throw new Error(`radiance has ${radiance.length / 3} entries for ${n} vertices`);
  }
  const scale = Math.pow(2, exposure);
  const pos = new Float32Array(mesh.positions);
  const nor = new Float32Array(n * 3);
  const col = new Float32Array(n * 3);
  const min = [Infinity, Infinity, Infinity], max = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < n; i++) {
    const nx = mesh.normals[3 * i], ny = mesh.normals[3 * i + 1], nz = mesh.normals[3 * i + 2];
    const l = Math.hypot(nx, ny, nz);
    if (l > 0 && Number.isFinite(l)) {
      nor[3 * i] = nx / l; nor[3 * i + 1] = ny / l; nor[3 * i + 2] = nz / l;
    } else {
      nor[3 * i + 2] = 1;
    }
    for (let k = 0; k < 3; k++) {
      const p = pos[3 * i + k];
      if (p < min[k]) min[k] = p;
      if (p > max[k]) max[k] = p;
      col[3 * i + k] = toneMap(radiance[3 * i + k] * scale, tone);
    }
  }
  const idx = new Uint32Array(mesh.indices);
  const vbytes = n * 12;
  const bin = new Uint8Array(3 * vbytes + f * 4);
  bin.set(new Uint8Array(pos.buffer), 0);
  bin.set(new Uint8Array(nor.buffer), vbytes);
  bin.set(new Uint8Array(col.buffer), 2 * vbytes);
  bin.set(new Uint8Array(idx.buffer), 3 * vbytes);
  const view = (offset, length, target) => ({ buffer: 0, byteOffset: offset, byteLength: length, target });
  const gltf = {
    asset: { version: "2.0", generator },
    extensionsUsed: ["KHR_materials_unlit"],
    scene: 0,
    scenes: [{ nodes: [0] }],
    nodes: [{ mesh: 0 }],
    meshes: [{
      primitives: [{
        attributes: { POSITION: 0, NORMAL: 1, COLOR_0: 2 },
        indices: 3,
        material: 0,
        mode: 4,
      }],
    }],
    materials: [{
      pbrMetallicRoughness: { baseColorFactor: [1, 1, 1, 1], metallicFactor: 0, roughnessFactor: 1 },
      extensions: { KHR_materials_unlit: {} },
      doubleSided: false,
    }],
    buffers: [{ byteLength: bin.length }],
    bufferViews: [
      view(0, vbytes, 34962),
      view(vbytes, vbytes, 34962),
      view(2 * vbytes, vbytes, 34962),
      view(3 * vbytes, f * 4, 34963),
    ],
    accessors: [
      { bufferView: 0, componentType: 5126, count: n, type: "VEC3", min, max },
      { bufferView: 1, componentType: 5126, count: n, type: "VEC3" },
      { bufferView: 2, componentType: 5126, count: n, type: "VEC3" },
      { bufferView: 3, componentType: 5125, count: f, type: "SCALAR" },
    ],
  };
  let json = new TextEncoder().encode(JSON.stringify(gltf));
  const jsonLen = (json.length + 3) & ~3;
  const binLen = (bin.length + 3) & ~3;
  const total = 12 + 8 + jsonLen + 8 + binLen;
  const out = new Uint8Array(total);
  const dv = new DataView(out.buffer);
  dv.setUint32(0, 0x46546c67, true); // "glTF"
  dv.setUint32(4, 2, true);
  dv.setUint32(8, total, true);
  dv.setUint32(12, jsonLen, true);
  dv.setUint32(16, 0x4e4f534a, true); // "JSON"
  out.set(json, 20);
  out.fill(0x20, 20 + json.length, 20 + jsonLen); // JSON padded with spaces
  const b = 20 + jsonLen;
  dv.setUint32(b, binLen, true);
  dv.setUint32(b + 4, 0x004e4942, true); // "BIN\0"
  out.set(bin, b + 8); // zero padding is already there
  return out;
}
