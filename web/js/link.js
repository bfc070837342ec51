// The viewer's connection to one scene on the server: relight requests out, per-vertex
// radiance in, latest wins.
//
// Transport: the WebSocket stream `GET /api/v1/scenes/{id}/stream` (docs/stream.md: JSON text
// frames out; a binary "TLXF" frame with the radiance then a JSON stats frame in). When the
// server has no such route (its answer to a plain GET is the router's 404), the link relights
// over `POST /api/v1/scenes/{id}/relight` with binary f32 answers instead, and says so through
// `onNotice`: the fallback is shown, never silent.
//
// Latest wins: at most one request is in flight; a newer state replaces the pending one, so
// dragging never builds a queue. A lost connection is retried with exponential back-off
// (0.5 s doubling to 8 s); after reconnecting, the newest state is sent again.
//
// On a team server (docs/team.md) every request carries the tab's token (auth.js). A 401 or
// 403 is not a lost connection: retrying cannot help, so the link stops and hands the
// answer to `onDenied`, and the viewer asks for a token.

import { apiFetch, withAccessToken, isDenial } from "./auth.js";

const MAGIC = "TLXF";
const BACKOFF_MS = [500, 1000, 2000, 4000, 8000];
const HEARTBEAT_MS = 2000;

export class Link {
  /**
   * `handlers`: onFrame(radiance: Float32Array, info: {seq, stats, dropped, transport}),
   * onRequestError(seq, code, message), onConnection({state, transport, message}),
   * onNotice(message|null), onInFlight(bool), onDenied(status, message).
   */
  constructor(sceneId, handlers) {
    this.sceneId = sceneId;
    this.h = handlers;
    this.base = "/api/v1/scenes/" + encodeURIComponent(sceneId);
    this.transport = null; // "stream" | "rest" while connected
    this.state = "connecting"; // "connecting" | "open" | "offline" | "denied" | "closed"
    this.latest = null; // { seq, request }: the newest state, resent after a reconnect
    this.pending = null; // not yet sent
    this.inFlight = null; // { seq, t0 }
    this.attempt = 0;
    this.timer = null;
    this.ws = null;
    this.frame = null; // radiance waiting for its stats frame
    this.connect();
  }

  /** Asks for `request` (a RelightRequest) under sequence number `seq`; latest wins. */
  submit(seq, request) {
    this.latest = { seq, request };
    this.pending = this.latest;
    this.pump();
  }

  close() {
    this.state = "closed";
    clearTimeout(this.timer);
    clearInterval(this.heartbeat);
    if (this.ws) {
      this.ws.onclose = null;
      this.ws.close(1000, "viewer closed the scene");
    }
  }

  // ---- connection ---------------------------------------------------------------------

  setState(state, message) {
    this.state = state;
    this.h.onConnection({ state, transport: this.transport, message: message || null });
  }

  connect() {
    if (this.state === "closed") return;
    clearTimeout(this.timer);
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const url = withAccessToken(`${proto}//${location.host}${this.base}/stream?format=f32`);
    let opened = false;
    let ws;
    try {
      ws = new WebSocket(url);
    } catch (e) {
      this.lost(`cannot open the WebSocket: ${e.message}`);
      return;
    }
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => {
      opened = true;
    };
    ws.onmessage = (ev) => this.onMessage(ev);
    ws.onclose = (ev) => {
      if (this.ws !== ws || this.state === "closed") return;
      this.ws = null;
      this.frame = null;
      if (this.inFlight) this.requeue();
      if (!opened) {
        this.probe();
      } else {
        const why = ev.reason ? `: ${ev.reason}` : "";
        this.lost(`the stream closed (code ${ev.code}${why})`);
      }
    };
  }

  /** The WebSocket did not open: find out why with a plain GET of the stream route. */
  async probe() {
    let res, body = null;
    try {
      res = await apiFetch(`${this.base}/stream`, { headers: { Accept: "application/json" } });
      body = await res.json().catch(() => null);
    } catch (e) {
      this.lost(`the server does not answer (${e.message})`);
      return;
    }
    if (this.state === "closed") return;
    const msg = body && body.error ? body.error.message : res.statusText;
    if (isDenial(res.status)) {
      this.denied(res.status, msg);
    } else if (res.status === 404 && /^no route/.test(msg)) {
      this.startRest(
        `Streaming is unavailable: GET ${this.base}/stream answered 404 (“${msg}”). ` +
          `Relighting over POST ${this.base}/relight instead (one request at a time).`,
      );
    } else if (res.status === 404) {
      this.lost(`the server no longer serves this scene: ${msg}`);
    } else {
      this.lost(`the stream did not open (GET answered ${res.status}: ${msg})`);
    }
  }

  lost(message) {
    if (this.state === "closed") return;
    clearInterval(this.heartbeat);
    this.transport = null;
    const delay = BACKOFF_MS[Math.min(this.attempt, BACKOFF_MS.length - 1)];
    this.attempt += 1;
    this.setState(
      "offline",
      `Lost the connection: ${message}. Reconnecting in ${(delay / 1000).toFixed(1)} s (attempt ${this.attempt}).`,
    );
    this.h.onInFlight(false);
    this.timer = setTimeout(() => this.connect(), delay);
  }

  /** The server turned the token down: stop (no retry can help) and let the viewer ask. */
  denied(status, message) {
    if (this.state === "closed") return;
    clearTimeout(this.timer);
    clearInterval(this.heartbeat);
    this.transport = null;
    this.pending = null;
    this.inFlight = null;
    this.state = "denied";
    this.h.onInFlight(false);
    this.h.onDenied(status, message);
  }

  connected(transport, notice) {
    this.transport = transport;
    this.attempt = 0;
    this.setState("open");
    this.h.onNotice(notice || null);
    // Resend the newest state: the answer to the request in flight when the connection
    // dropped is lost, and a restarted server knows nothing of this viewer.
    if (this.latest) this.pending = this.latest;
    this.pump();
  }

  startRest(notice) {
    this.connected("rest", notice);
    clearInterval(this.heartbeat);
    // A REST link learns of a stopped server only when it asks: ask /healthz when idle.
    this.heartbeat = setInterval(async () => {
      if (this.inFlight || this.state !== "open") return;
      try {
        const r = await fetch("/healthz", { cache: "no-store" });
        if (!r.ok) throw new Error(`/healthz answered ${r.status}`);
      } catch (e) {
        if (this.state === "open" && this.transport === "rest") {
          this.lost(`the server does not answer (${e.message})`);
        }
      }
    }, HEARTBEAT_MS);
  }

  requeue() {
    if (!this.pending && this.latest) this.pending = this.latest;
    this.inFlight = null;
  }

  // ---- requests -----------------------------------------------------------------------

  pump() {
    if (this.inFlight || !this.pending || this.state !== "open") return;
    const { seq, request } = this.pending;
    this.pending = null;
    this.inFlight = { seq, t0: performance.now() };
    this.h.onInFlight(true);
    if (this.transport === "stream") {
      this.ws.send(JSON.stringify({ type: "relight", seq, request }));
    } else {
      this.restRelight(seq, request);
    }
  }

  done() {
    this.inFlight = null;
    this.h.onInFlight(!!this.pending);
    this.pump();
  }

  async restRelight(seq, request) {
    let res;
    try {
      res = await apiFetch(`${this.base}/relight`, {
        method: "POST",
        headers: { "Content-Type": "application/json", Accept: "application/octet-stream" },
        body: JSON.stringify(request),
      });
    } catch (e) {
      if (this.state !== "open") return;
      this.requeue();
      this.lost(`the relight request failed (${e.message})`);
      return;
    }
    if (this.state !== "open") return;
    if (!res.ok) {
      const body = await res.json().catch(() => null);
      const err = body && body.error ? body.error : { code: String(res.status), message: res.statusText };
      if (isDenial(res.status)) {
        this.denied(res.status, err.message);
        return;
      }
      this.h.onRequestError(seq, err.code, err.message);
      this.done();
      return;
    }
    const buf = await res.arrayBuffer();
    const stats = restStats(res.headers.get("server-timing"), request);
    const ev = parseFloat(res.headers.get("x-auto-exposure"));
    if (Number.isFinite(ev)) stats.auto_exposure = ev;
    this.h.onFrame(new Float32Array(buf), { seq, stats, dropped: null, transport: "rest" });
    this.done();
  }

  onMessage(ev) {
    if (typeof ev.data !== "string") {
      const buf = ev.data;
      const head = new DataView(buf, 0, 16);
      const magic = String.fromCharCode(...new Uint8Array(buf, 0, 4));
      if (magic !== MAGIC) {
        this.h.onRequestError(null, "protocol", `a binary frame does not start with ${MAGIC}`);
        return;
      }
      const seq = Number(head.getBigUint64(4, true));
      const format = head.getUint8(12);
      if (format !== 0) {
        this.h.onRequestError(seq, "protocol", `asked for f32 radiance, got format ${format}`);
        return;
      }
      this.frame = { seq, radiance: new Float32Array(buf.slice(16)) };
      return;
    }
    let msg;
    try {
      msg = JSON.parse(ev.data);
    } catch {
      this.h.onRequestError(null, "protocol", "the server sent a text frame that is not JSON");
      return;
    }
    if (msg.type === "ready") {
      this.vertexCount = msg.vertex_count;
      this.connected("stream", null);
    } else if (msg.type === "stats") {
      const f = this.frame;
      this.frame = null;
      if (f && f.seq === msg.seq) {
        this.h.onFrame(f.radiance, {
          seq: msg.seq, stats: msg.stats, dropped: msg.dropped, transport: "stream",
        });
      }
      if (this.inFlight && this.inFlight.seq <= msg.seq) this.done();
    } else if (msg.type === "error") {
      const e = msg.error || {};
      this.h.onRequestError(msg.seq, e.code || "error", e.message || JSON.stringify(msg));
      if (this.inFlight && (msg.seq == null || this.inFlight.seq <= msg.seq)) this.done();
    }
  }
}

/** Stats for a REST answer: the binary answer carries only the Server-Timing header. */
function restStats(timing, request) {
  const dur = {};
  for (const part of (timing || "").split(",")) {
    const m = /^\s*([\w-]+)\s*;\s*dur=([\d.]+)/.exec(part);
    if (m) dur[m[1]] = parseFloat(m[2]);
  }
  return {
    solver: null,
    components: request.components || "full",
    iterations: null,
    residual: null,
    ms: dur.total ?? null,
    direct_ms: dur.direct ?? null,
    solve_ms: dur.solve ?? null,
  };
}
