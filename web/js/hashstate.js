// The view state in the URL hash, so a view can be bookmarked and shared:
//   #scene=cornell&comp=full&ev=-1&tone=filmic&cam=px,py,pz,tx,ty,tz,fov
//    &lights=[...]&mat={...}&env=builtin:sky,rotation,scale&cull=0&spec=0&pd=0&frame=12
// `lights` and `mat` are the API's JSON (RelightRequest.lights and .materials); absent fields
// mean the scene's defaults. Bad values are reported, never silently dropped.

const COMPONENTS = [
  "full", "direct", "subsurface_only", "interreflection_only", "heuristic_a", "heuristic_b",
];

const num = (v) => +(+v).toPrecision(6);

export function encodeHash(s) {
  const p = new URLSearchParams();
  p.set("scene", s.scene);
  p.set("comp", s.components);
  p.set("ev", String(num(s.exposure)));
  p.set("tone", s.tone);
  if (s.camera) {
    const c = s.camera;
    p.set("cam", [...c.position, ...c.target, c.fov_deg].map(num).join(","));
  }
  if (s.lights) p.set("lights", JSON.stringify(s.lights, (k, v) => (typeof v === "number" ? num(v) : v)));
  if (Object.keys(s.materials).length) p.set("mat", JSON.stringify(s.materials));
  if (s.env.on) p.set("env", [s.env.map, num(s.env.rotation_deg), num(s.env.scale)].join(","));
  if (!s.cull) p.set("cull", "0");
  if (s.specular === false) p.set("spec", "0");
  if (s.pixelDirect === false) p.set("pd", "0");
  if (s.frame) p.set("frame", String(s.frame));
  return "#" + p.toString();
}

/** Parses a hash into a partial state; `problems` lists what could not be read. */
export function decodeHash(hash) {
  const out = {};
  const problems = [];
  const p = new URLSearchParams(hash.replace(/^#/, ""));
  if (p.has("scene")) out.scene = p.get("scene");
  if (p.has("comp")) {
    const c = p.get("comp");
    if (COMPONENTS.includes(c)) out.components = c;
    else problems.push(`comp=${c} is not one of ${COMPONENTS.join(", ")}`);
  }
  if (p.has("ev")) {
    const ev = parseFloat(p.get("ev"));
    if (Number.isFinite(ev) && Math.abs(ev) <= 20) out.exposure = ev;
    else problems.push(`ev=${p.get("ev")} must be a number in [-20, 20]`);
  }
  if (p.has("tone")) {
    const t = p.get("tone");
    if (t === "srgb" || t === "filmic") out.tone = t;
    else problems.push(`tone=${t} must be srgb or filmic`);
  }
  if (p.has("cam")) {
    const v = p.get("cam").split(",").map(parseFloat);
    if (v.length === 7 && v.every(Number.isFinite)) {
      out.camera = { position: v.slice(0, 3), target: v.slice(3, 6), fov_deg: v[6] };
    } else {
      problems.push("cam must be 7 numbers: position, target, fov");
    }
  }
  for (const [key, field, check] of [
    ["lights", "lights", Array.isArray],
    ["mat", "materials", (m) => m && typeof m === "object" && !Array.isArray(m)],
  ]) {
    if (!p.has(key)) continue;
    try {
      const v = JSON.parse(p.get(key));
      if (check(v)) out[field] = v;
      else problems.push(`${key} has the wrong shape`);
    } catch (e) {
      problems.push(`${key} is not JSON (${e.message})`);
    }
  }
  if (p.has("env")) {
    const [map, rot, sc] = p.get("env").split(",");
    out.env = { on: true, map: map || "builtin:sky", rotation_deg: parseFloat(rot) || 0, scale: sc === undefined ? 1 : parseFloat(sc) };
  }
  if (p.has("cull")) out.cull = p.get("cull") !== "0";
  if (p.has("spec")) out.specular = p.get("spec") !== "0";
  if (p.has("pd")) out.pixelDirect = p.get("pd") !== "0";
  if (p.has("frame")) {
    const f = Number(p.get("frame"));
    if (Number.isInteger(f) && f >= 0) out.frame = f;
    else problems.push(`frame=${p.get("frame")} must be a whole number from 0`);
  }
  return { state: out, problems };
}

export { COMPONENTS };
