// The translux viewer: loads a scene's mesh, streams relit per-vertex radiance from the
// server while lights, materials and the transport components are edited, and draws it with
// WebGL2. See docs/viewer.md.

import { MAX_SHADOWED_LIGHTS, Renderer } from "./renderer.js";
import { OrbitCamera } from "./camera.js";
import { Link } from "./link.js";
import { buildGlb } from "./glb.js";
import { encodeHash, decodeHash, COMPONENTS } from "./hashstate.js";
import { token, setToken, takeTokenFromUrl, apiFetch, isDenial, denialMessage } from "./auth.js";
import {
  el, slider, picker, vec3Input, splitColour, joinColour, logPos, fromLogPos, download, fmt,
} from "./ui.js";
import {
  add, sub, scale, normalize, length, project, closestOnLine, rayPlane, dirFromAngles,
  anglesFromDir,
} from "./math.js";

/**
 * The server's named media (GET /api/v1/presets, read by `start`): their names, each one's
 * index of refraction, a dipole's index where neither it nor its preset gives one, and a
 * specular coat's where there is no dipole to take it from.
 */
const PRESETS = [];
const PRESET_ETA = {};
const DEFAULT_ETA = { dipole: NaN, coat: NaN };
const COMPONENT_LABELS = {
  full: "full", direct: "direct", subsurface_only: "subsurface", interreflection_only: "inter-refl.",
  heuristic_a: "heuristic A", heuristic_b: "heuristic B",
};
const COMPONENT_NOTES = {
  full: "B = Bₑ + S(E + F B): everything.",
  direct: "B = Bₑ + ρE: direct light on each patch, nothing scattered on.",
  subsurface_only: "Subsurface scattering of direct light only (S E).",
  interreflection_only: "Inter-reflection without subsurface transport.",
  heuristic_a: "The paper's first heuristic.",
  heuristic_b: "The paper's second heuristic.",
};
const $ = (id) => document.getElementById(id);

// ---- metrics (read by the browser tests and shown in the overlay) ---------------------

const metrics = {
  firstLitMs: null, // performance.now() of the first frame drawn with server radiance
  frames: [], // { seq, t, ms (server), transport, frame (animation) } per radiance frame drawn
  inputs: [], // { seq, t } per state change not yet shown
  latencies: [], // input-to-photon, ms, one per input event
  draws: 0,
  drawTimes: [],
};

// ---- state --------------------------------------------------------------------------

const app = {
  renderer: null,
  camera: new OrbitCamera(),
  scenes: [],
  detail: null,
  mesh: null,
  radiance: null,
  link: null,
  seq: 0,
  shownSeq: 0,
  lastInfo: null,
  selected: 0,
  gizmo: true,
  needDraw: true,
  newFrame: false,
  bbox: null,
  errors: { auth: null, conn: null, link: null, request: null, notice: null, app: null },
  state: {
    scene: null,
    camera: null,
    lights: [],
    env: { on: false, map: "builtin:sky", rotation_deg: 0, scale: 1 },
    materials: {},
    components: "full",
    exposure: 0,
    tone: "filmic",
    cull: true,
    specular: true,
    pixelDirect: true,
    frame: 0, // the animation frame relit (animated scenes)
  },
  // Animated scenes (detail.frames > 1): the viewer mesh of each frame fetched so far, the
  // frame each request asked for, the frame whose mesh is on screen, and playback.
  meshes: new Map(), // frame → Promise of its mesh
  sentFrame: new Map(), // seq → frame
  meshFrame: 0,
  playing: false,
  lastStep: 0,
  frameDirect: false, // whether the radiance on screen left the direct light to the pixels
  sentDirect: new Map(), // seq → whether that request asked for "direct_at": "pixel"
  matUi: {},
  hashProblems: [],
  linkNotes: [], // sentences about the opened link, shown with the hash problems
  autoExposure: true,
  // The scene's translucency preparation (docs/api.md, "Translucency preparation"), watched
  // by `watchTranslucency`: a fresh object per scene, so a poll answered late is dropped.
  prep: { scene: null, info: null },
  prepNote: null, // the note under the material sliders, while the scene has translucent objects
};
window.translux = { app, metrics };

// ---- banners ------------------------------------------------------------------------

function setBanner(kind, message) {
  app.errors[kind] = message;
  const box = $("banners");
  box.replaceChildren();
  for (const k of ["auth", "conn", "link", "app", "request", "notice"]) {
    const m = app.errors[k];
    if (!m) continue;
    const title = {
      auth: "Sign-in", conn: "Connection", link: "Link", app: "Viewer", request: "Server", notice: "Note",
    }[k];
    const close = el("button", { title: "Dismiss", onclick: () => setBanner(k, null) }, "×");
    box.append(el("div", { class: "banner" + (k === "notice" ? " notice" : ""), "data-kind": k, role: "alert" },
      el("span", { class: "msg" }, el("b", {}, title + ": "), m), close));
  }
}

// ---- requests -----------------------------------------------------------------------

function relightRequest() {
  const s = app.state;
  const lights = s.lights.map((l) => ({ ...l }));
  if (s.env.on) {
    lights.push({ type: "environment", map: s.env.map, scale: s.env.scale, rotation_deg: s.env.rotation_deg });
  }
  const req = { lights, components: s.components };
  if (Object.keys(s.materials).length) req.materials = s.materials;
  if (pixelDirectOn()) req.direct_at = "pixel";
  if (frameCount() > 1) req.frame = s.frame;
  return req;
}

/**
 * Whether the direct light of diffuse objects is drawn per pixel: asked for, and every
 * point, spot and directional light gets a shadow map (else the server adds it at the
 * vertices, and the overlay says why).
 */
function pixelDirectOn() {
  return app.state.pixelDirect && app.state.lights.length <= MAX_SHADOWED_LIGHTS;
}

/** A state change that needs a new solve; `t` is the input event's time stamp. */
function changed(t) {
  if (!app.link) return;
  app.seq += 1;
  metrics.inputs.push({ seq: app.seq, t: t ?? performance.now() });
  if (metrics.inputs.length > 2000) metrics.inputs.splice(0, 1000);
  const req = relightRequest();
  app.sentDirect.set(app.seq, req.direct_at === "pixel");
  app.sentFrame.set(app.seq, app.state.frame);
  for (const k of app.sentDirect.keys()) if (k < app.seq - 256) app.sentDirect.delete(k);
  for (const k of app.sentFrame.keys()) if (k < app.seq - 256) app.sentFrame.delete(k);
  app.link.submit(app.seq, req);
  scheduleHash();
  app.needDraw = true;
}

let hashTimer = null;
function scheduleHash() {
  clearTimeout(hashTimer);
  hashTimer = setTimeout(() => {
    app.state.camera = app.camera.toJSON();
    const s = { ...app.state };
    if (app.detail && JSON.stringify(s.lights) === JSON.stringify(defaultLights())) s.lights = null;
    history.replaceState(null, "", encodeHash(s));
  }, 250);
}

// ---- link handlers ------------------------------------------------------------------

function onFrame(radiance, info) {
  if (info.seq < app.shownSeq) return; // an older answer overtaken by a newer one
  // An animated scene: the answer belongs to the frame its request asked for; its mesh
  // (fetched before the request was sent) goes on screen with it.
  const f = app.sentFrame.get(info.seq);
  if (f !== undefined && f !== app.meshFrame && app.meshReady && app.meshReady.has(f)) {
    showMesh(app.meshReady.get(f), f);
  }
  try {
    app.renderer.setRadiance(radiance);
  } catch (e) {
    // The server's mesh changed under us (restarted with another bundle): reload the scene.
    setBanner("app", `${e.message}; reloading the scene`);
    loadScene(app.state.scene, false);
    return;
  }
  app.radiance = radiance;
  app.shownSeq = info.seq;
  app.lastInfo = info;
  app.frameDirect = app.sentDirect.get(info.seq) === true;
  app.newFrame = true;
  app.needDraw = true;
  translucencyAnswered(info.seq);
  if (app.errors.request && info.seq >= (app.errorSeq ?? 0)) setBanner("request", null);
  if (app.errors.app) setBanner("app", null);
  metrics.frames.push({ seq: info.seq, t: performance.now(), ms: info.stats ? info.stats.ms : null, transport: info.transport, frame: f ?? 0 });
  if (metrics.frames.length > 5000) metrics.frames.splice(0, 2500);
  if (app.autoExposure) {
    app.autoExposure = false;
    autoExposure();
  }
}

function onRequestError(seq, code, message) {
  app.errorSeq = seq ?? app.seq;
  setBanner("request", `${message} (${code})`);
  translucencyAnswered(seq ?? app.seq);
  // The inputs of a refused state will never be shown: they have no latency.
  if (seq != null) metrics.inputs = metrics.inputs.filter((i) => i.seq > seq);
  app.needDraw = true;
}

function onConnection({ state, transport, message }) {
  const chip = $("conn");
  chip.className = "chip " + (state === "open" ? (transport === "rest" ? "rest" : "open") : state);
  chip.textContent = state === "open" ? (transport === "rest" ? "REST (no stream)" : "live stream")
    : state === "offline" ? "offline" : state;
  setBanner("conn", state === "offline" ? message : null);
  $("stage").classList.toggle("offline", state === "offline");
  app.needDraw = true;
}

function onInFlight(busy) {
  $("solving").hidden = !busy;
}

// ---- scenes -------------------------------------------------------------------------

/** GET a JSON answer; a failure throws an Error with the `status` and the server's message. */
async function getJson(url) {
  const res = await apiFetch(url, { headers: { Accept: "application/json" } });
  const body = await res.json().catch(() => null);
  if (!res.ok) {
    const m = body && body.error ? body.error.message : res.statusText;
    throw Object.assign(new Error(`GET ${url} answered ${res.status}: ${m}`), { status: res.status, serverMessage: m });
  }
  return body;
}

// ---- sign-in ------------------------------------------------------------------------

/**
 * The server turned the token (or its absence) down: that is no lost connection, so say
 * what it wants and show the sign-in form instead of retrying.
 */
function askForToken(status, message) {
  if (app.link) app.link.close();
  app.link = null;
  unwatchTranslucency();
  onInFlight(false);
  const chip = $("conn");
  chip.className = "chip offline";
  chip.textContent = status === 401 && !token() ? "sign-in needed" : "token refused";
  $("stage").classList.remove("offline");
  setBanner("conn", null);
  setBanner("auth", denialMessage(status, message));
  $("signin").hidden = false;
  $("token-input").focus();
}

/** Keeps the token for this tab and starts again with it. */
function signIn(ev) {
  ev.preventDefault();
  const input = $("token-input");
  const t = input.value.trim();
  if (!t) return;
  input.value = "";
  setToken(t);
  signedIn();
}

/** A token is in the session (from the form or a pasted link): start again with it. */
function signedIn() {
  $("signin").hidden = true;
  setBanner("auth", null);
  $("conn").className = "chip";
  $("conn").textContent = "connecting…";
  start();
}

// ---- animation ----------------------------------------------------------------------

/** Frames of the scene shown (1 for a still scene). */
function frameCount() {
  return app.detail && app.detail.frames > 1 ? app.detail.frames : 1;
}

/** The mesh URL of frame `f` of scene `id` (`?frame=` only for animated scenes). */
function meshUrl(id, f) {
  const base = `/api/v1/scenes/${encodeURIComponent(id)}/mesh`;
  return frameCount() > 1 ? `${base}?frame=${f}` : base;
}

/** Frame `f`'s viewer mesh, fetched once (frames may differ in topology, so each has its own). */
function meshFor(f) {
  if (!app.meshes.has(f)) {
    const p = getJson(meshUrl(app.state.scene, f)).then((m) => {
      app.meshReady.set(f, m);
      return m;
    });
    p.catch(() => app.meshes.delete(f));
    app.meshes.set(f, p);
  }
  return app.meshes.get(f);
}

function showMesh(mesh, f) {
  app.mesh = mesh;
  app.meshFrame = f;
  app.renderer.setMesh(mesh.positions, mesh.normals, mesh.indices);
  updateSurfaces();
}

/** Shows frame `f`: its mesh is fetched first, then the relight for it is asked for. */
async function setFrame(f, t) {
  const n = frameCount();
  f = ((f % n) + n) % n;
  app.state.frame = f;
  $("frame").value = String(f);
  $("frame-label").textContent = `${f + 1} / ${n}`;
  try {
    await meshFor(f);
  } catch (e) {
    setBanner("app", `Cannot load frame ${f}: ${e.message}`);
    setPlaying(false);
    return;
  }
  if (app.state.frame !== f) return; // overtaken while the mesh loaded
  meshFor((f + 1) % n).catch(() => {}); // the next one, ahead of playback
  changed(t);
}

function setPlaying(on) {
  app.playing = on && frameCount() > 1;
  $("play").textContent = app.playing ? "❚❚" : "▶";
  $("play").setAttribute("aria-pressed", String(app.playing));
  app.lastStep = performance.now();
  app.needDraw = true;
}

/**
 * Playback: the next frame is asked for once the current one is on screen and its time
 * (1 / fps) is up, so a slow server slows the animation down instead of skipping frames.
 */
function stepPlayback(now) {
  if (!app.playing) return;
  const fps = (app.detail && app.detail.fps) || 24;
  const shown = app.sentFrame.get(app.shownSeq);
  if (shown !== app.state.frame || app.shownSeq < app.seq) return;
  if (now - app.lastStep < 1000 / fps) return;
  app.lastStep = now;
  setFrame(app.state.frame + 1);
}

function buildTimeline() {
  const n = frameCount();
  $("timeline").hidden = n <= 1;
  $("frame").max = String(n - 1);
  $("frame").value = String(app.state.frame);
  $("frame-label").textContent = `${app.state.frame + 1} / ${n}`;
  setPlaying(false);
}

function defaultLights() {
  return app.detail.lights.filter((l) => l.type !== "environment");
}

async function loadScene(id, fromHash) {
  if (app.link) app.link.close();
  app.link = null;
  unwatchTranslucency();
  app.radiance = null;
  app.shownSeq = 0;
  app.seq = 0;
  const hash = fromHash ? decodeHash(location.hash).state : {};
  let detail, mesh;
  app.meshes = new Map();
  app.meshReady = new Map();
  app.sentFrame = new Map();
  try {
    detail = await getJson(`/api/v1/scenes/${encodeURIComponent(id)}`);
    app.detail = detail;
    app.state.scene = id;
    const n = frameCount();
    app.state.frame = Number.isInteger(hash.frame) && hash.frame < n ? hash.frame : 0;
    if (hash.frame !== undefined && hash.frame >= n) {
      app.hashProblems.push(`frame=${hash.frame} is out of range (the scene has ${n} frame${n === 1 ? "" : "s"})`);
    }
    mesh = await meshFor(app.state.frame);
  } catch (e) {
    if (isDenial(e.status)) askForToken(e.status, e.serverMessage);
    else setBanner("app", `Cannot load scene “${id}”: ${e.message}`);
    return;
  }
  showMesh(mesh, app.state.frame);
  app.bbox = bbox(mesh.positions);
  app.camera.sceneRadius = length(sub(app.bbox.max, app.bbox.min)) / 2;
  const s = app.state;
  s.scene = id;
  const cam = hash.camera || detail.camera;
  app.camera.setLookAt(cam.position, cam.target, cam.fov_deg);
  s.lights = structuredClone(hash.lights ? hash.lights.filter((l) => l.type !== "environment") : defaultLights());
  const env = (hash.lights || detail.lights).find((l) => l.type === "environment");
  s.env = hash.env || (env ? { on: true, map: env.map, rotation_deg: env.rotation_deg ?? 0, scale: env.scale ?? 1 }
    : { on: false, map: "builtin:sky", rotation_deg: 0, scale: 1 });
  s.materials = hash.materials || {};
  for (const k of ["components", "exposure", "tone", "cull", "specular", "pixelDirect"]) if (hash[k] !== undefined) s[k] = hash[k];
  updateSurfaces();
  app.autoExposure = hash.exposure === undefined;
  app.selected = 0;
  $("scene").value = id;
  watchTranslucency(id, detail.translucency);
  buildPanels();
  buildTimeline();
  app.link = new Link(id, { onFrame, onRequestError, onConnection, onInFlight, onDenied: askForToken, onNotice: (m) => {
    app.restNotice = m;
    setBanner("notice", m);
  } });
  // What the link asked for and did not get stays on screen until dismissed: the first
  // frame clears the viewer's own banner, which would hide it.
  const notes = app.linkNotes.slice();
  if (app.hashProblems.length) notes.push(`Parts of the link were not understood: ${app.hashProblems.join("; ")}.`);
  setBanner("link", notes.length ? notes.join(" ") : null);
  setBanner("app", null);
  app.hashProblems = [];
  app.linkNotes = [];
  changed();
  // A link's translucency override is a first change as much as the slider's.
  if (Object.keys(s.materials).some(isTranslucent)) translucencyChangeSent();
}

function bbox(p) {
  const min = [Infinity, Infinity, Infinity], max = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < p.length; i += 3) {
    for (let k = 0; k < 3; k++) {
      min[k] = Math.min(min[k], p[i + k]);
      max[k] = Math.max(max[k], p[i + k]);
    }
  }
  return { min, max };
}

/** Sets the exposure so the 95th percentile of vertex luminance lands near 0.8. */
function autoExposure() {
  const r = app.radiance;
  if (!r) return;
  // With the direct light per pixel the radiance lacks it: the server says what the whole
  // answer's exposure is, by the same rule.
  const given = app.frameDirect && app.lastInfo && app.lastInfo.stats ? app.lastInfo.stats.auto_exposure : null;
  if (typeof given === "number") {
    app.state.exposure = given;
    if (app.exposureRow) app.exposureRow.set(app.state.exposure);
    scheduleHash();
    return;
  }
  const lum = [];
  for (let i = 0; i < r.length; i += 3) lum.push(0.2126 * r[i] + 0.7152 * r[i + 1] + 0.0722 * r[i + 2]);
  lum.sort((a, b) => a - b);
  const p = lum[Math.floor(lum.length * 0.95)];
  if (p > 0) {
    app.state.exposure = Math.round(Math.log2(0.8 / p) * 10) / 10;
    if (app.exposureRow) app.exposureRow.set(app.state.exposure);
    scheduleHash();
  }
}

// ---- panels -------------------------------------------------------------------------

function buildPanels() {
  buildComponents();
  buildLights();
  buildEnv();
  buildMaterials();
  buildDisplay();
}

function buildComponents() {
  const box = $("components");
  box.replaceChildren(...COMPONENTS.map((c) => el("button", {
    id: `comp-${c}`, role: "radio", class: c === app.state.components ? "on" : "",
    "aria-checked": String(c === app.state.components), title: COMPONENT_NOTES[c],
    onclick: (ev) => {
      app.state.components = c;
      buildComponents();
      changed(ev.timeStamp);
    },
  }, COMPONENT_LABELS[c])));
  $("comp-note").textContent = COMPONENT_NOTES[app.state.components];
}

function lightLabel(l, i) {
  return { point: "Point", spot: "Spot", directional: "Sun" }[l.type] + " " + (i + 1);
}

function lightPower(l) {
  return l.type === "directional" ? l.irradiance : l.intensity;
}

function buildLights() {
  const list = $("lights");
  const lights = app.state.lights;
  if (app.selected >= lights.length) app.selected = lights.length - 1;
  list.replaceChildren(...lights.map((l, i) => {
    const { hex, power } = splitColour(lightPower(l));
    const unit = l.type === "directional" ? "W/m²" : "W/sr";
    return el("li", { class: i === app.selected ? "sel" : "", "data-index": String(i), onclick: () => {
      app.selected = i;
      buildLights();
      app.needDraw = true;
    } },
    el("span", { class: "sw", style: `background:${hex}` }),
    el("span", { class: "name" }, lightLabel(l, i), " ", el("span", { class: "sub" }, `${fmt(power)} ${unit}`)),
    el("button", { class: "del", title: "Remove this light", "aria-label": `Remove ${lightLabel(l, i)}`, onclick: (ev) => {
      ev.stopPropagation();
      lights.splice(i, 1);
      buildLights();
      changed(ev.timeStamp);
    } }, "×"));
  }));
  if (!lights.length) list.append(el("li", { class: "sub" }, "No lights: add one above (or turn on the environment)."));
  buildLightEditor();
}

function buildLightEditor() {
  const box = $("light-editor");
  const l = app.state.lights[app.selected];
  if (!l) {
    box.replaceChildren();
    app.editor = null;
    return;
  }
  const rows = [];
  const refreshList = () => {
    const li = $("lights").children[app.selected];
    if (li) {
      const { hex, power } = splitColour(lightPower(l));
      li.querySelector(".sw").style.background = hex;
      li.querySelector(".sub").textContent = `${fmt(power)} ${l.type === "directional" ? "W/m²" : "W/sr"}`;
    }
  };
  const key = l.type === "directional" ? "irradiance" : "intensity";
  let { hex, power } = splitColour(l[key]);
  const colour = el("input", { type: "color", value: hex, "aria-label": "Light colour" });
  colour.addEventListener("input", (ev) => {
    hex = colour.value;
    l[key] = joinColour(hex, power);
    refreshList();
    changed(ev.timeStamp);
  });
  const range = l.type === "directional" ? [-2, 3] : [-3, 2];
  const pow = slider({
    id: "light-power", label: key === "irradiance" ? "Irradiance" : "Intensity",
    min: range[0], max: range[1], step: 0.01, value: logPos(power || 1e-3),
    format: (v) => fmt(+fromLogPos(v).toPrecision(3)),
    title: key === "irradiance" ? "W/m² on a surface facing the light" : "W/sr",
    oninput: (v, ev) => {
      power = +fromLogPos(v).toPrecision(4);
      l[key] = joinColour(hex, power);
      refreshList();
      changed(ev.timeStamp);
    },
  });
  rows.push(el("div", { class: "row" }, el("span", { class: "lab" }, "Colour"), colour));
  rows.push(pow);
  let posRow = null;
  if (l.position) {
    posRow = vec3Input("Position", l.position, (v) => {
      l.position = v;
      changed();
    });
    rows.push(posRow);
  }
  if (l.direction) {
    const a = anglesFromDir(l.direction);
    const set = (ev) => {
      l.direction = dirFromAngles(a.yaw, a.pitch).map((x) => +x.toFixed(5));
      changed(ev.timeStamp);
    };
    rows.push(slider({ id: "light-yaw", label: "Aim yaw", min: -180, max: 180, step: 1, value: Math.round(a.yaw),
      format: (v) => `${v}°`, oninput: (v, ev) => { a.yaw = v; set(ev); } }));
    rows.push(slider({ id: "light-pitch", label: "Aim pitch", min: -90, max: 90, step: 1, value: Math.round(a.pitch),
      format: (v) => `${v}°`, oninput: (v, ev) => { a.pitch = v; set(ev); } }));
  }
  if (l.type === "spot") {
    let inner, outer;
    inner = slider({ id: "light-inner", label: "Inner cone", min: 0, max: 90, step: 1, value: l.inner_deg,
      format: (v) => `${v}°`, oninput: (v, ev) => {
        l.inner_deg = v;
        if (l.outer_deg < v) { l.outer_deg = v; outer.set(v); }
        changed(ev.timeStamp);
      } });
    outer = slider({ id: "light-outer", label: "Outer cone", min: 1, max: 90, step: 1, value: l.outer_deg,
      format: (v) => `${v}°`, oninput: (v, ev) => {
        l.outer_deg = v;
        if (l.inner_deg > v) { l.inner_deg = v; inner.set(v); }
        changed(ev.timeStamp);
      } });
    rows.push(inner, outer);
  }
  box.replaceChildren(...rows);
  app.editor = { posRow };
}

function addLight(type, t) {
  if (!app.bbox) return; // no scene on screen yet
  const c = scale(add(app.bbox.min, app.bbox.max), 0.5);
  const above = [c[0], app.bbox.min[1] + (app.bbox.max[1] - app.bbox.min[1]) * 0.8, c[2]];
  const light = type === "point" ? { type, position: above, intensity: [0.5, 0.5, 0.5] }
    : type === "spot" ? { type, position: above, intensity: [2, 2, 2], direction: [0, -1, 0], inner_deg: 20, outer_deg: 35 }
      : { type: "directional", direction: normalize([-0.4, -1, -0.3]), irradiance: [2, 2, 2] };
  if (light.position) light.position = light.position.map((x) => +x.toFixed(4));
  app.state.lights.push(light);
  app.selected = app.state.lights.length - 1;
  buildLights();
  changed(t);
}

function buildEnv() {
  const e = app.state.env;
  const on = el("input", { type: "checkbox", id: "env-on", checked: e.on });
  on.addEventListener("change", (ev) => {
    e.on = on.checked;
    changed(ev.timeStamp);
  });
  const rot = slider({ id: "env-rot", label: "Rotation", min: -180, max: 180, step: 1, value: e.rotation_deg,
    format: (v) => `${v}°`, oninput: (v, ev) => { e.rotation_deg = v; if (e.on) changed(ev.timeStamp); } });
  const sc = slider({ id: "env-scale", label: "Strength", min: -2, max: 1, step: 0.01, value: logPos(e.scale),
    format: (v) => fmt(+fromLogPos(v).toPrecision(3)), oninput: (v, ev) => {
      e.scale = +fromLogPos(v).toPrecision(4);
      if (e.on) changed(ev.timeStamp);
    } });
  $("env").replaceChildren(
    el("label", { class: "row" }, el("span", { class: "lab" }, "Map"), on,
      el("span", {}, "sky (", el("code", {}, e.map), ")")),
    rot, sc);
}

// Per translucent object: which profile is scaled (the scene's or a preset) and by how much.
function describeProfile(p) {
  if (p.type === "dipole") return p.preset ? `dipole ${p.preset}` : "dipole (σ values)";
  return p.type;
}

/** An object's caption: the media it is drawn with, the picked ones where a preset is picked. */
function materialCaption(o, u) {
  if (o.material.type === "simulated") {
    const m = o.material;
    return `simulated ${m.preset ?? "(σ values)"}, σa ×${u.scale.toFixed(2)}`;
  }
  if (o.material.type === "translucent") {
    return u.choice === "scene" ? describeProfile(o.material.profile) : `dipole ${u.choice}`;
  }
  const media = o.material.materials.map((p, k) => (u.media[k] === "scene" ? describeProfile(p) : u.media[k]));
  return `heterogeneous: ${media.join(", ")}`;
}

function materialOverride(name) {
  const o = app.detail.objects.find((x) => x.name === name);
  const u = app.matUi[name];
  const scaled = (p) => (p.type === "dipole" ? { ...p, scale: +((p.scale ?? 1) * u.scale).toPrecision(4) } : p);
  // The scene's specular coat stays with the new medium.
  const coat = (m) => (o.material.specular ? { ...m, specular: o.material.specular } : m);
  if (o.material.type === "simulated") {
    // Absorption only: the walks are re-weighted for the new σa, never re-run. Never below
    // the floor the walks were stored for (rounding could undershoot it).
    if (u.scale === 1) return null;
    const { sigma_a: a, sigma_a_min: lo } = o.absorption;
    return { ...o.material, sigma_a: a.map((x, c) => Math.max(+(x * u.scale).toPrecision(5), lo[c])) };
  }
  if (o.material.type === "translucent") {
    const base = u.choice === "scene" ? o.material.profile : { type: "dipole", preset: u.choice };
    if (u.choice === "scene" && u.scale === 1) return null;
    return coat({ type: "translucent", profile: scaled(base) });
  }
  const media = o.material.materials.map((p, k) => (u.media[k] === "scene" ? p : { type: "dipole", preset: u.media[k] }));
  if (u.media.every((m) => m === "scene") && u.scale === 1) return null;
  return coat({ type: "heterogeneous", materials: media.map(scaled), pattern: o.material.pattern });
}

function applyMaterial(name, t) {
  const m = materialOverride(name);
  if (m) app.state.materials[name] = m;
  else delete app.state.materials[name];
  updateSurfaces();
  changed(t);
  if (isTranslucent(name)) translucencyChangeSent();
}

// ---- translucency preparation -----------------------------------------------------------
//
// What a scene's first translucency change needs (S's radial terms)
// the server makes in the background; until it is made, that change takes seconds to
// minutes. The scene detail's `translucency.state` says where it stands: `none`, `pending`,
// `preparing`, `ready` or `failed`. The viewer asks for the detail again while the state
// can still change by itself (pending, preparing), and once after a change the server
// answered before it was ready (that change made it), and shows the state in a note under
// the material sliders.

const PREP_POLL_MS = 1500; // while preparing, and the first wait while pending
const PREP_POLL_MAX_MS = 10000; // pending waits grow to this (`--prepare-translucency off` stays pending)
const PREP_READY_MS = 4000; // how long "ready" shows after the viewer saw it become so

/** Whether `name` is a translucent object (its changes need the preparation). */
function isTranslucent(name) {
  const o = app.detail && app.detail.objects.find((x) => x.name === name);
  return !!o && o.material.type === "translucent";
}

/** Starts watching scene `id`'s preparation from its detail's `translucency`. */
function watchTranslucency(id, info) {
  unwatchTranslucency();
  app.prep = { scene: id, info: info ?? null, timer: null, delay: PREP_POLL_MS, changeSeq: 0, readyShown: false };
  schedulePrepPoll();
}

/** Stops the polling (another scene, a sign-in); a poll still under way is dropped. */
function unwatchTranslucency() {
  const p = app.prep;
  clearTimeout(p.timer);
  clearTimeout(p.readyTimer);
  app.prep = { scene: null, info: null };
  showPrep();
}

const prepState = () => (app.prep.info ? app.prep.info.state : "none");

/** The next poll, after `delay` ms (the current wait by default) while the state can change. */
function schedulePrepPoll(delay) {
  const p = app.prep;
  clearTimeout(p.timer);
  p.timer = null;
  const s = prepState();
  if (p.scene && (delay !== undefined || s === "pending" || s === "preparing")) {
    p.timer = setTimeout(() => pollPrep(p), delay ?? p.delay);
  }
}

async function pollPrep(p) {
  p.timer = null;
  let detail;
  try {
    detail = await getJson(`/api/v1/scenes/${encodeURIComponent(p.scene)}`);
  } catch (e) {
    if (app.prep !== p) return;
    // A refused token is the stream's to report, a scene gone the next load's; anything
    // else (the server away) is tried again, later.
    if (e.status >= 400 && e.status < 500) return;
    p.delay = Math.min(p.delay * 2, PREP_POLL_MAX_MS);
    schedulePrepPoll();
    return;
  }
  if (app.prep !== p) return; // another scene since
  const before = prepState();
  p.info = detail.translucency ?? null;
  const s = prepState();
  p.delay = s === "pending" ? Math.min(p.delay * 1.5, PREP_POLL_MAX_MS) : PREP_POLL_MS;
  if (s === "ready" && before !== "ready") {
    p.readyShown = true;
    clearTimeout(p.readyTimer);
    p.readyTimer = setTimeout(() => {
      p.readyShown = false;
      if (app.prep === p) showPrep();
    }, PREP_READY_MS);
  }
  showPrep();
  schedulePrepPoll();
}

/** A translucency change was sent (`app.seq`): until answered, it may be making the preparation. */
function translucencyChangeSent() {
  const s = prepState();
  if (s === "none" || s === "ready") return;
  app.prep.changeSeq = app.seq;
  showPrep();
}

/** Request `seq` was answered (or refused): a translucency change sent before it is done. */
function translucencyAnswered(seq) {
  const p = app.prep;
  if (!p.changeSeq || seq < p.changeSeq) return;
  p.changeSeq = 0;
  showPrep();
  schedulePrepPoll(0); // it made what it needed: the state has likely moved
}

function showPrep() {
  const note = app.prepNote;
  if (!note) return;
  const p = app.prep;
  const s = prepState();
  let text = "", kind = "";
  if (p.changeSeq && s !== "ready" && s !== "none") {
    text = "First translucency change: preparing S, this can take a while…";
    kind = "busy";
  } else if (s === "preparing") {
    text = "Preparing translucency… (the first change will be fast in a moment)";
    kind = "busy";
  } else if (s === "pending") {
    text = "Translucency not prepared yet: the first change will prepare it, which can take a while.";
  } else if (s === "failed") {
    text = `Translucency preparation failed: ${p.info.message || "no reason given"}. ` +
      "The first change will do the work itself (slower).";
    kind = "err";
  } else if (s === "ready" && p.readyShown) {
    const secs = p.info.seconds;
    text = `Translucency ready${typeof secs === "number" ? ` (prepared in ${secs.toFixed(1)} s)` : ""}.`;
    kind = "ok";
  }
  note.className = "note prep" + (kind ? " " + kind : "");
  note.dataset.state = s;
  note.hidden = !text;
  note.replaceChildren(...(kind === "busy" ? [el("span", { class: "spin" })] : []), text);
}

/** A material's specular coat as [alpha, eta], or null: the rule of `Gloss::of`. */
function glossOf(m) {
  const spec = m && m.specular;
  if (!spec) return null;
  const profile = m.type === "translucent" ? m.profile
    : m.type === "thin_sheet" ? m.reflectance
      : m.type === "heterogeneous" ? m.materials[0] : null;
  const dipoleEta = (p) => p.eta ?? PRESET_ETA[p.preset] ?? DEFAULT_ETA.dipole;
  // A simulated medium's eta follows the same rule (profile::eta_of).
  const mediumEta = m.type === "simulated" ? dipoleEta(m)
    : profile && profile.type === "dipole" ? dipoleEta(profile) : null;
  return [spec.roughness * spec.roughness, spec.eta ?? mediumEta ?? DEFAULT_ETA.coat];
}

/**
 * Each vertex's coat, and its albedo for the direct light per pixel (diffuse objects only:
 * `per_pixel_direct` in engine/src/relight.rs), from its object's material (the override
 * where there is one).
 */
function updateSurfaces() {
  if (!app.detail || !app.mesh) return;
  const n = app.mesh.positions.length / 3;
  const gloss = new Float32Array(n * 2);
  const albedo = new Float32Array(n * 3);
  const idx = app.mesh.indices;
  for (const part of app.mesh.objects) {
    const o = app.detail.objects.find((x) => x.name === part.name);
    if (!o) continue;
    const m = app.state.materials[o.name] || o.material;
    const g = glossOf(m);
    const end = 3 * (part.first_triangle + part.triangle_count);
    for (let i = 3 * part.first_triangle; i < end; i++) {
      if (g) gloss.set(g, 2 * idx[i]);
      if (m.type === "diffuse") albedo.set(m.albedo, 3 * idx[i]);
    }
  }
  app.renderer.setGloss(gloss);
  app.renderer.setAlbedo(albedo);
  app.needDraw = true;
}

/** The UI state of an object from its override in the URL (or none). */
function matUiFrom(o, override) {
  const fromProfile = (p, orig) => {
    if (!p || JSON.stringify(p) === JSON.stringify(orig)) return { choice: "scene", scale: 1 };
    if (p.type === "dipole" && p.preset && PRESETS.includes(p.preset)) {
      const { scale: s, ...rest } = p;
      if (JSON.stringify(rest) === JSON.stringify({ type: "dipole", preset: p.preset })) {
        return { choice: p.preset, scale: s ?? 1 };
      }
    }
    if (p.type === "dipole" && orig.type === "dipole") {
      const { scale: s, ...rest } = p;
      const { scale: s0, ...rest0 } = orig;
      if (JSON.stringify(rest) === JSON.stringify(rest0)) return { choice: "scene", scale: (s ?? 1) / (s0 ?? 1) };
    }
    return { choice: "scene", scale: 1 };
  };
  if (o.material.type === "simulated") {
    const a = override && override.type === "simulated" && override.sigma_a;
    return { scale: a ? +(a[0] / o.absorption.sigma_a[0]).toPrecision(4) : 1 };
  }
  if (o.material.type === "translucent") {
    const p = override && override.type === "translucent" ? override.profile : null;
    return fromProfile(p, o.material.profile);
  }
  const media = o.material.materials.map((p, k) => {
    const q = override && override.type === "heterogeneous" ? override.materials[k] : null;
    return fromProfile(q, p);
  });
  return { media: media.map((m) => m.choice), scale: media.find((m) => m.scale !== 1)?.scale ?? 1 };
}

function buildMaterials() {
  const box = $("materials");
  const rows = [];
  app.matUi = {};
  for (const o of app.detail.objects) {
    const kind = o.material.type;
    if (kind === "simulated" && o.absorption) {
      rows.push(absorptionRow(o));
      continue;
    }
    if (kind !== "translucent" && kind !== "heterogeneous") continue;
    const u = matUiFrom(o, app.state.materials[o.name]);
    app.matUi[o.name] = u;
    const caption = el("span", { class: "kind" }, materialCaption(o, u));
    const parts = [el("div", { class: "oname" }, o.name, " ", caption)];
    const presetOptions = (orig) => [["scene", `scene: ${describeProfile(orig)}`], ...PRESETS.map((p) => [p, p])];
    const scalable = () => (kind === "translucent"
      ? (u.choice !== "scene" || o.material.profile.type === "dipole")
      : o.material.materials.some((p, k) => u.media[k] !== "scene" || p.type === "dipole"));
    const sl = slider({
      id: `mat-${o.name}-scale`, label: "Translucency", min: -3, max: 3, step: 0.05, value: Math.log2(u.scale),
      format: (v) => `×${Math.pow(2, v).toFixed(2)}`,
      title: "Scales the dipole's mean free path (the profile's `scale`): right is more translucent",
      oninput: (v, ev) => {
        u.scale = +Math.pow(2, v).toPrecision(4);
        applyMaterial(o.name, ev.timeStamp);
      },
    });
    // After a medium is picked: the slider's state, and the caption names the medium shown.
    const syncScalable = () => {
      sl.input.disabled = !scalable();
      sl.title = sl.input.disabled ? "Only dipole profiles can be scaled; pick a preset" : "";
      caption.textContent = materialCaption(o, u);
    };
    if (kind === "translucent") {
      parts.push(picker({
        id: `mat-${o.name}-preset`, label: "Medium", value: u.choice, options: presetOptions(o.material.profile),
        title: "Jensen et al. 2001's measured media",
        onchange: (v) => { u.choice = v; syncScalable(); applyMaterial(o.name); },
      }));
    } else {
      o.material.materials.forEach((p, k) => parts.push(picker({
        id: `mat-${o.name}-medium${k}`, label: `Medium ${k + 1}`, value: u.media[k], options: presetOptions(p),
        onchange: (v) => { u.media[k] = v; syncScalable(); applyMaterial(o.name); },
      })));
    }
    parts.push(sl);
    syncScalable();
    rows.push(el("div", { class: "obj", "data-object": o.name }, parts));
  }
  if (!rows.length) rows.push(el("p", { class: "note" }, "This scene has no translucent objects."));
  app.prepNote = app.detail.objects.some((o) => o.material.type === "translucent")
    ? el("p", { class: "note prep", id: "translucency-note", role: "status", hidden: true })
    : null;
  box.replaceChildren(...rows, ...(app.prepNote ? [app.prepNote] : []));
  showPrep();
}

/**
 * A simulated object's row: an absorption slider (σa ×1/16 … ×8, the lower end the walks'
 * floor), re-weighting the stored walks; its medium's scattering stays as precomputed.
 */
function absorptionRow(o) {
  const u = matUiFrom(o, app.state.materials[o.name]);
  app.matUi[o.name] = u;
  const caption = el("span", { class: "kind" }, materialCaption(o, u));
  const { sigma_a: a, sigma_a_min: lo } = o.absorption;
  // The lowest factor every channel allows, on the slider's grid of 0.05.
  const raw = Math.log2(Math.max(...lo.map((l, c) => (a[c] > 0 ? l / a[c] : 0))));
  const min = Math.max(-4, Math.ceil(raw / 0.05 - 1e-6) * 0.05);
  const sl = slider({
    id: `mat-${o.name}-absorption`, label: "Absorption", min: +min.toFixed(2), max: 3, step: 0.05,
    value: Math.log2(u.scale),
    format: (v) => `×${Math.pow(2, v).toFixed(2)}`,
    title: "Scales the medium's σa; the stored walks are re-weighted, not re-run. Left is more translucent",
    oninput: (v, ev) => {
      u.scale = +Math.pow(2, v).toPrecision(4);
      caption.textContent = materialCaption(o, u);
      applyMaterial(o.name, ev.timeStamp);
    },
  });
  return el("div", { class: "obj", "data-object": o.name }, [el("div", { class: "oname" }, o.name, " ", caption), sl]);
}

function buildDisplay() {
  const s = app.state;
  app.exposureRow = slider({ id: "exposure", label: "Exposure", min: -10, max: 10, step: 0.1, value: s.exposure,
    format: (v) => `${v > 0 ? "+" : ""}${v.toFixed(1)} EV`, oninput: (v) => {
      s.exposure = v;
      app.needDraw = true;
      scheduleHash();
    } });
  const auto = el("button", { id: "auto-exposure", title: "Expose for the brightest 5% of the mesh", onclick: () => {
    autoExposure();
    app.needDraw = true;
  } }, "Auto");
  const tone = picker({ id: "tone", label: "Tone map", value: s.tone,
    options: [["filmic", "filmic (ACES fit)"], ["srgb", "sRGB (clip)"]], onchange: (v) => {
      s.tone = v;
      app.needDraw = true;
      scheduleHash();
    } });
  const cull = el("input", { type: "checkbox", id: "cull", checked: s.cull });
  cull.addEventListener("change", () => {
    s.cull = cull.checked;
    app.needDraw = true;
    scheduleHash();
  });
  const crisp = el("input", { type: "checkbox", id: "pixel-direct", checked: s.pixelDirect });
  crisp.addEventListener("change", () => {
    s.pixelDirect = crisp.checked;
    changed();
  });
  const spec = el("input", { type: "checkbox", id: "specular", checked: s.specular });
  spec.addEventListener("change", () => {
    s.specular = spec.checked;
    app.needDraw = true;
    scheduleHash();
  });
  const giz = el("input", { type: "checkbox", id: "gizmo", checked: app.gizmo });
  giz.addEventListener("change", () => {
    app.gizmo = giz.checked;
    app.needDraw = true;
  });
  app.gizmoBox = giz;
  app.exposureRow.append(auto);
  $("display").replaceChildren(
    app.exposureRow,
    tone,
    el("label", { class: "row" }, el("span", { class: "lab" }, "Near walls"), cull, "hide back faces (see inside)"),
    el("label", { class: "row" }, el("span", { class: "lab" }, "Crisp light"), crisp, `direct light per pixel, shadow maps (up to ${MAX_SHADOWED_LIGHTS} lights)`),
    el("label", { class: "row" }, el("span", { class: "lab" }, "Highlights"), spec, "specular pass (glossy materials)"),
    el("label", { class: "row" }, el("span", { class: "lab" }, "Gizmo"), giz, "show light handles"),
  );
}

// ---- gizmo --------------------------------------------------------------------------

const AXES = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
const AXIS_COLOURS = [[0.95, 0.33, 0.33, 1], [0.45, 0.86, 0.4, 1], [0.35, 0.6, 1, 1]];

function handleLength() {
  return app.camera.sceneRadius * 0.22;
}

/** Screen-space handles of the lights: centres, axis tips and spot aim tips (CSS pixels). */
function handles(viewProj, w, h) {
  const out = [];
  app.state.lights.forEach((l, i) => {
    if (!l.position) return;
    const c = project(viewProj, l.position, w, h);
    if (c.w <= 0) return;
    out.push({ kind: "centre", i, x: c.x, y: c.y });
    if (i !== app.selected) return;
    const L = handleLength();
    AXES.forEach((a, k) => {
      const tip = project(viewProj, add(l.position, scale(a, L)), w, h);
      if (tip.w > 0) out.push({ kind: "axis", i, k, x: tip.x, y: tip.y, x0: c.x, y0: c.y });
    });
    if (l.direction) {
      const tip = project(viewProj, add(l.position, scale(normalize(l.direction), L * 1.3)), w, h);
      if (tip.w > 0) out.push({ kind: "aim", i, x: tip.x, y: tip.y });
    }
  });
  return out;
}

function segDist(px, py, x0, y0, x1, y1) {
  const dx = x1 - x0, dy = y1 - y0;
  const t = Math.max(0, Math.min(1, ((px - x0) * dx + (py - y0) * dy) / (dx * dx + dy * dy || 1)));
  return Math.hypot(px - (x0 + t * dx), py - (y0 + t * dy));
}

function pick(x, y) {
  if (!app.gizmo) return null;
  const { w, h } = cssSize();
  const { viewProj } = app.camera.matrices(w / h);
  let best = null;
  for (const hd of handles(viewProj, w, h)) {
    let d = Math.hypot(x - hd.x, y - hd.y);
    let limit = hd.kind === "centre" ? 14 : 11;
    if (hd.kind === "axis") {
      // The whole shaft, but the centre disc wins near the light.
      d = Math.min(d, segDist(x, y, hd.x0, hd.y0, hd.x, hd.y) + 3);
      limit = 8;
    }
    const score = d - (hd.kind === "centre" ? 4 : 0);
    if (d <= limit && (!best || score < best.score)) best = { ...hd, score };
  }
  return best;
}

function gizmoGeometry() {
  const lines = [];
  const points = [[], [], []]; // light discs, axis tips, selected disc
  const L = handleLength();
  const push = (arr, p, c) => arr.push(p[0], p[1], p[2], c[0], c[1], c[2], c[3]);
  app.state.lights.forEach((l, i) => {
    const { hex } = splitColour(lightPower(l));
    const col = [1, 3, 5].map((j) => parseInt(hex.slice(j, j + 2), 16) / 255).concat(1);
    if (l.position) {
      push(i === app.selected ? points[2] : points[0], l.position, col);
      if (l.direction) {
        const tip = add(l.position, scale(normalize(l.direction), L * 1.3));
        const yellow = [1, 0.82, 0.35, i === app.selected ? 1 : 0.55];
        push(lines, l.position, yellow);
        push(lines, tip, yellow);
        if (i === app.selected) push(points[1], tip, yellow);
      }
      if (i === app.selected) {
        AXES.forEach((a, k) => {
          const tip = add(l.position, scale(a, L));
          push(lines, l.position, AXIS_COLOURS[k]);
          push(lines, tip, AXIS_COLOURS[k]);
          push(points[1], tip, AXIS_COLOURS[k]);
        });
      }
    }
  });
  return {
    lines: new Float32Array(lines),
    points: [
      { data: new Float32Array(points[0]), size: 16 },
      { data: new Float32Array(points[1]), size: 10 },
      { data: new Float32Array(points[2]), size: 22 },
    ],
  };
}

// ---- input --------------------------------------------------------------------------

function cssSize() {
  const c = app.renderer.canvas;
  return { w: c.clientWidth, h: c.clientHeight };
}

let drag = null;

function onPointerDown(ev) {
  const canvas = app.renderer.canvas;
  canvas.focus();
  canvas.setPointerCapture(ev.pointerId);
  const x = ev.offsetX, y = ev.offsetY;
  const hit = ev.button === 0 && !ev.shiftKey ? pick(x, y) : null;
  if (hit) {
    const l = app.state.lights[hit.i];
    if (app.selected !== hit.i) {
      app.selected = hit.i;
      buildLights();
    }
    const { w, h } = cssSize();
    const ray = app.camera.ray(x, y, w, h);
    const { f } = app.camera.basis();
    drag = { mode: hit.kind, i: hit.i, k: hit.k, start: [...l.position], x, y };
    if (hit.kind === "axis") {
      drag.s0 = closestOnLine(l.position, AXES[hit.k], ray.o, ray.d);
    } else if (hit.kind === "aim") {
      drag.plane = add(l.position, scale(normalize(l.direction), handleLength() * 1.3));
      drag.normal = f;
    } else {
      const p = rayPlane(ray.o, ray.d, l.position, f);
      drag.offset = p ? sub(l.position, p) : [0, 0, 0];
      drag.normal = f;
    }
  } else {
    drag = { mode: ev.button === 2 || ev.button === 1 || ev.shiftKey ? "pan" : "orbit", x, y };
  }
  canvas.classList.add("dragging");
  app.needDraw = true;
}

function onPointerMove(ev) {
  const x = ev.offsetX, y = ev.offsetY;
  const canvas = app.renderer.canvas;
  if (!drag) {
    canvas.classList.toggle("grab", !!pick(x, y));
    return;
  }
  const { w, h } = cssSize();
  if (drag.mode === "orbit") {
    app.camera.orbit(x - drag.x, y - drag.y);
  } else if (drag.mode === "pan") {
    app.camera.pan(x - drag.x, y - drag.y, h);
  } else {
    const l = app.state.lights[drag.i];
    if (!l) return;
    const ray = app.camera.ray(x, y, w, h);
    if (drag.mode === "axis") {
      const s = closestOnLine(drag.start, AXES[drag.k], ray.o, ray.d);
      if (s !== null && drag.s0 !== null) l.position = add(drag.start, scale(AXES[drag.k], s - drag.s0));
    } else if (drag.mode === "aim") {
      const p = rayPlane(ray.o, ray.d, drag.plane, drag.normal);
      if (p && length(sub(p, l.position)) > 1e-6) l.direction = normalize(sub(p, l.position)).map((v) => +v.toFixed(5));
    } else {
      const p = rayPlane(ray.o, ray.d, drag.start, drag.normal);
      if (p) l.position = add(p, drag.offset);
    }
    if (l.position) l.position = l.position.map((v) => +v.toFixed(5));
    if (app.editor && app.editor.posRow && l.position) app.editor.posRow.set(l.position);
    changed(ev.timeStamp);
  }
  drag.x = x;
  drag.y = y;
  app.needDraw = true;
  if (drag.mode === "orbit" || drag.mode === "pan") scheduleHash();
}

function onPointerUp() {
  if (drag && drag.mode === "aim") buildLightEditor();
  drag = null;
  app.renderer.canvas.classList.remove("dragging");
}

function onWheel(ev) {
  ev.preventDefault();
  app.camera.zoom(Math.exp(ev.deltaY * 0.0012));
  app.needDraw = true;
  scheduleHash();
}

function fit() {
  if (!app.bbox) return;
  const { w, h } = cssSize();
  app.camera.fit(app.bbox.min, app.bbox.max, w / h);
  app.needDraw = true;
  scheduleHash();
}

// ---- drawing ------------------------------------------------------------------------

function draw(withGizmo = app.gizmo) {
  const r = app.renderer;
  r.resize();
  const { w, h } = cssSize();
  const m = app.camera.matrices(w / Math.max(h, 1));
  // A scene's detail arrives before its mesh (and bounds): a frame drawn in between has
  // neither gizmo nor highlights.
  const loaded = !!(app.detail && app.bbox);
  r.draw(m, {
    exposure: app.state.exposure,
    tone: app.state.tone,
    cullBackfaces: app.state.cull,
    background: [0.031, 0.035, 0.043],
    gizmo: withGizmo && loaded ? gizmoGeometry() : null,
    highlights: loaded ? {
      lights: app.state.lights,
      unitMm: app.detail.unit_mm,
      specular: highlightsOn(),
      direct: app.frameDirect,
      shadows: app.frameDirect || highlightsOn(),
      bounds: { centre: scale(add(app.bbox.min, app.bbox.max), 0.5), radius: app.camera.sceneRadius },
    } : null,
  });
}

/** The specular pass is drawn as the server's render route draws it (`with_highlights`):
 * on, for components that show direct light leaving the surface. */
function highlightsOn() {
  const c = app.state.components;
  return !!(app.detail && app.state.specular && c !== "subsurface_only" && c !== "interreflection_only");
}

function frame() {
  requestAnimationFrame(frame);
  stepPlayback(performance.now());
  const c = app.renderer.canvas;
  const sizeChanged = c.width !== Math.round(c.clientWidth * Math.min(devicePixelRatio || 1, 2));
  if (!app.needDraw && !sizeChanged) return;
  app.needDraw = false;
  draw();
  const t = performance.now();
  metrics.draws += 1;
  metrics.drawTimes.push(t);
  if (metrics.drawTimes.length > 600) metrics.drawTimes.splice(0, 300);
  if (app.newFrame) {
    app.newFrame = false;
    if (metrics.firstLitMs === null) {
      metrics.firstLitMs = t;
      performance.mark("translux:first-lit-frame");
    }
    // Input-to-photon: every input whose state (or a newer one) is now on screen.
    const keep = [];
    for (const i of metrics.inputs) {
      if (i.seq <= app.shownSeq) metrics.latencies.push(t - i.t);
      else keep.push(i);
    }
    metrics.inputs = keep;
    if (metrics.latencies.length > 5000) metrics.latencies.splice(0, 2500);
  }
  updateStats(t);
}

function rate(times, now, windowMs = 2000) {
  const recent = times.filter((x) => now - x <= windowMs);
  return recent.length / (windowMs / 1000);
}

function updateStats(now) {
  const info = app.lastInfo;
  const s = info && info.stats;
  const f = (v, d = 1) => (v === null || v === undefined ? "—" : Number(v).toFixed(d));
  const lat = metrics.latencies.slice(-20).sort((a, b) => a - b);
  const med = lat.length ? lat[Math.floor(lat.length / 2)] : null;
  const lines = [
    `draw ${rate(metrics.drawTimes, now).toFixed(0)} fps · lit ${rate(metrics.frames.map((x) => x.t), now).toFixed(1)}/s`,
    `server ${f(s && s.ms)} ms  (direct ${f(s && s.direct_ms)}, solve ${f(s && s.solve_ms)}${s && s.materials_ms ? `, S ${f(s.materials_ms)}` : ""})`,
    `solver ${s ? s.solver ?? "n/a over REST" : "—"} · ${s && s.iterations != null ? s.iterations + " it" : "— it"} · residual ${s && s.residual != null ? Number(s.residual).toExponential(1) : "—"}`,
    `shown ${s ? s.components : "—"} · seq ${app.shownSeq}${info && info.dropped != null ? ` · dropped ${info.dropped}` : ""}`,
    `direct light ${app.frameDirect ? "per pixel" : app.state.pixelDirect ? `per vertex (over ${MAX_SHADOWED_LIGHTS} lights)` : "per vertex"}`,
    `input→photon ${f(med, 0)} ms (median of ${lat.length})`,
    app.detail ? `${app.detail.patches} patches · ${app.detail.vertices} vertices` : "",
    frameCount() > 1 ? `frame ${app.meshFrame + 1} of ${frameCount()} at ${app.detail.fps ?? 24} fps${app.playing ? " · playing" : ""}` : "",
  ];
  $("stats").textContent = lines.filter(Boolean).join("\n");
}

// ---- keep and share -----------------------------------------------------------------

function snapshot() {
  draw(false);
  app.renderer.canvas.toBlob((blob) => {
    download(`translux-${app.state.scene}-${app.state.components}.png`, blob);
    app.needDraw = true;
  }, "image/png");
}

async function glb() {
  if (!app.radiance) {
    setBanner("app", "No relit frame yet: the .glb needs the server's radiance");
    return;
  }
  // Vertex colours hold the whole answer: with the direct light drawn per pixel, the
  // server is asked again for it at the vertices.
  let radiance = app.radiance;
  if (app.frameDirect) {
    const { direct_at: _, ...request } = app.link.latest.request;
    try {
      const r = await apiFetch(`/api/v1/scenes/${encodeURIComponent(app.state.scene)}/relight`, {
        method: "POST",
        headers: { "content-type": "application/json", accept: "application/octet-stream" },
        body: JSON.stringify(request),
      });
      if (!r.ok) throw new Error(`${r.status} ${(await r.json().catch(() => null))?.error?.message ?? r.statusText}`);
      radiance = new Float32Array(await r.arrayBuffer());
    } catch (e) {
      setBanner("app", `Cannot make the .glb: the server did not answer the vertex colours (${e.message})`);
      return;
    }
  }
  app.glbRadiance = radiance;
  const bytes = buildGlb(app.mesh, radiance, app.state.exposure, app.state.tone, "translux viewer");
  download(`translux-${app.state.scene}-${app.state.components}.glb`, new Blob([bytes], { type: "model/gltf-binary" }));
}

// ---- boot ---------------------------------------------------------------------------

async function boot() {
  // First of all, so that no later step (nor a failure) leaves the token in the address bar.
  takeTokenFromUrl();
  try {
    app.renderer = new Renderer($("view"));
  } catch (e) {
    setBanner("app", e.message);
    return;
  }
  const canvas = app.renderer.canvas;
  canvas.addEventListener("pointerdown", onPointerDown);
  canvas.addEventListener("pointermove", onPointerMove);
  canvas.addEventListener("pointerup", onPointerUp);
  canvas.addEventListener("pointercancel", onPointerUp);
  canvas.addEventListener("wheel", onWheel, { passive: false });
  canvas.addEventListener("contextmenu", (ev) => ev.preventDefault());
  window.addEventListener("keydown", (ev) => {
    if (ev.target.closest && ev.target.closest("input, select, textarea")) return;
    if (ev.key === "f" || ev.key === "F") fit();
    if (ev.key === "g" || ev.key === "G") {
      app.gizmo = !app.gizmo;
      if (app.gizmoBox) app.gizmoBox.checked = app.gizmo;
      app.needDraw = true;
    }
    if (ev.key === " " && frameCount() > 1) {
      ev.preventDefault();
      setPlaying(!app.playing);
    }
    if ((ev.key === "Delete" || ev.key === "Backspace") && app.state.lights[app.selected]) {
      app.state.lights.splice(app.selected, 1);
      buildLights();
      changed(ev.timeStamp);
    }
  });
  new ResizeObserver(() => { app.needDraw = true; }).observe(canvas);
  $("fit").onclick = fit;
  $("snap").onclick = snapshot;
  $("glb").onclick = glb;
  $("share").onclick = async () => {
    app.state.camera = app.camera.toJSON();
    history.replaceState(null, "", encodeHash(app.state));
    try {
      await navigator.clipboard.writeText(location.href);
      setBanner("notice", "Link to this view copied.");
    } catch {
      setBanner("notice", "The browser refused the clipboard: the link to this view is in the address bar.");
    }
    setTimeout(() => setBanner("notice", app.link && app.link.transport === "rest" ? app.restNotice : null), 2500);
  };
  $("add-point").onclick = (ev) => addLight("point", ev.timeStamp);
  $("add-spot").onclick = (ev) => addLight("spot", ev.timeStamp);
  $("add-dir").onclick = (ev) => addLight("directional", ev.timeStamp);
  $("scene").onchange = () => {
    history.replaceState(null, "", "#scene=" + encodeURIComponent($("scene").value));
    loadScene($("scene").value, false);
  };
  window.addEventListener("hashchange", () => {
    // A pasted link: take the token it carries, then show the view it describes.
    if (takeTokenFromUrl()) {
      signedIn();
      return;
    }
    const { state, problems } = decodeHash(location.hash);
    app.hashProblems = problems;
    if (!state.scene) return;
    if (app.scenes.some((s) => s.id === state.scene)) loadScene(state.scene, true);
    else setBanner("link", `Scene “${state.scene}” does not exist on this server; still showing “${app.state.scene}”.`);
  });
  $("play").onclick = () => setPlaying(!app.playing);
  $("frame").oninput = (ev) => {
    setPlaying(false);
    setFrame(+ev.target.value, ev.timeStamp);
  };
  $("signin").addEventListener("submit", signIn);
  $("panel-toggle").onclick = togglePanel;
  requestAnimationFrame(frame);
  await start();
}

/** A scene's line in the picker: with its id where another scene has the same name. */
function sceneLabel(s, all) {
  const twin = all.some((o) => o !== s && o.name === s.name);
  return `${twin ? `${s.name} (${s.id})` : s.name} · ${s.patches} patches`;
}

/** Lists the scenes and loads the one the URL names, or the first (saying so). */
async function start() {
  const { state: fromHash, problems } = decodeHash(location.hash);
  app.hashProblems = problems;
  app.linkNotes = [];
  let list;
  try {
    const presets = await getJson("/api/v1/presets");
    PRESETS.splice(0, PRESETS.length, ...presets.dipole.map((p) => p.name));
    for (const p of presets.dipole) PRESET_ETA[p.name] = p.eta;
    DEFAULT_ETA.dipole = presets.default_eta;
    DEFAULT_ETA.coat = presets.default_coat_eta;
    list = await getJson("/api/v1/scenes");
  } catch (e) {
    if (isDenial(e.status)) askForToken(e.status, e.serverMessage);
    else setBanner("conn", `Cannot list the scenes: ${e.message}. Reload the page when the server is back.`);
    return;
  }
  app.scenes = list.scenes;
  $("scene").replaceChildren(...list.scenes.map((s) => el("option", { value: s.id, title: `id: ${s.id}` },
    sceneLabel(s, list.scenes))));
  if (!list.scenes.length) {
    setBanner("app", "The server holds no scenes (start it with --bundles DIR or --demo).");
    return;
  }
  let id = list.scenes[0].id;
  let useHash = true;
  if (fromHash.scene && list.scenes.some((s) => s.id === fromHash.scene)) {
    id = fromHash.scene;
  } else if (fromHash.scene) {
    // The rest of the link describes a view of that scene, not of this one.
    app.linkNotes.push(`Scene “${fromHash.scene}” does not exist on this server; showing “${id}” instead.`);
    useHash = false;
  }
  await loadScene(id, useHash);
}

/** On a narrow screen the panel is a drawer under the view, closed until asked for. */
function togglePanel() {
  const open = $("panel").classList.toggle("open");
  $("panel-toggle").setAttribute("aria-expanded", String(open));
  $("panel-toggle").classList.toggle("on", open);
  app.needDraw = true;
}

boot();
