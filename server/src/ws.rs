//! `GET /api/v1/scenes/{id}/stream`: the WebSocket stream the viewer relights through.
//! The protocol is documented in `docs/stream.md`; in short:
//!
//! - In: text frames, JSON `{"type":"relight","seq":n,"request":{...}}` (a relight request
//!   as for `POST .../relight`) and `{"type":"config","format":..,"exposure":..,
//!   "tone_map":..}`.
//! - Out: `{"type":"ready",...}` on open; per computed relight one binary frame — a 16-byte
//!   header (`TLXF`, seq as u64 LE, format byte, 3 zero bytes) then the colours as f32, f16
//!   or sRGB 8-bit — followed by a text `{"type":"stats","seq","stats","dropped"}`;
//!   `{"type":"error","seq","error":{"code","message"}}` for a relight that fails.
//! - Latest wins: at most one relight in flight and one pending per stream; a newer request
//!   replaces the pending one (counted in `dropped`), so a dragged light never builds a
//!   queue. Each stream is its own client of the [worker pool](crate::pool).
//! - A message that is not JSON, not an object, has an unknown `type`, a missing or
//!   mistyped `seq`, unknown keys or a bad config value closes the stream (1007 invalid
//!   payload, 1008 unknown type, 1003 binary data) with a reason naming the problem.
//! - Ping every [`ServerParams::ping_interval`](crate::config::ServerParams); a peer that
//!   answers nothing for four intervals is closed. On shutdown the stream finishes its
//!   in-flight and pending relights, then closes with 1001.
//!
//! The loop ([`run_stream`]) is generic over `Sink + Stream` of messages, so anything that
//! speaks axum's [`Message`] can drive it.

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::extract::ws::{CloseFrame, Message, Utf8Bytes, WebSocketUpgrade, close_code};
use axum::extract::{Query, State};
use axum::response::Response;
use futures_util::{Sink, SinkExt, Stream, StreamExt};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use translux_engine::radiosity::Rgb;
use translux_engine::render::{display_rgb8, exposure_scale};
use translux_proto::api::{ErrorBody, RelightRequest, ToneMap};

use crate::error::AppError;
use crate::extract::{BODY_LIMIT, SceneId};
use crate::pool::{Done, Ticket, Work};
use crate::state::{AppState, Scene};
use translux_engine::relight;

/// The frame header's first four bytes.
pub const MAGIC: &[u8; 4] = b"TLXF";
/// Bytes before the colours in a binary frame.
pub const HEADER_LEN: usize = 16;
/// Largest exposure accepted, in stops either way.
pub const MAX_EXPOSURE: f32 = 64.0;
/// A pending request the pool refused (queue full) is tried again after this long.
const RETRY_FULL: Duration = Duration::from_millis(50);
/// Longest close reason (the WebSocket limit is 123 bytes).
const MAX_REASON: usize = 123;

/// How colours are encoded in a binary frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameFormat {
    /// Linear B/π, little-endian f32: 12 bytes per vertex.
    F32,
    /// Linear B/π, little-endian IEEE half: 6 bytes per vertex.
    F16,
    /// Exposed, tone-mapped, sRGB-encoded 8-bit: 3 bytes per vertex.
    Srgb8,
}

impl FrameFormat {
    /// The header's format byte.
    pub fn code(self) -> u8 {
        match self {
            FrameFormat::F32 => 0,
            FrameFormat::F16 => 1,
            FrameFormat::Srgb8 => 2,
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            FrameFormat::F32 => "f32",
            FrameFormat::F16 => "f16",
            FrameFormat::Srgb8 => "srgb8",
        }
    }

    fn parse(s: &str) -> Option<FrameFormat> {
        match s {
            "f32" => Some(FrameFormat::F32),
            "f16" => Some(FrameFormat::F16),
            "srgb8" => Some(FrameFormat::Srgb8),
            _ => None,
        }
    }
}

/// How a stream encodes its frames; set by `?format=` and `config` messages.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameSettings {
    pub format: FrameFormat,
    /// Stops: srgb8 colours are radiance × 2^exposure before the tone curve.
    pub exposure: f32,
    pub tone: ToneMap,
}

impl Default for FrameSettings {
    fn default() -> Self {
        FrameSettings {
            format: FrameFormat::F32,
            exposure: 0.0,
            tone: ToneMap::Srgb,
        }
    }
}

/// A binary frame: header, then one value per channel per vertex in the mesh's order.
pub fn encode_frame(seq: u64, settings: &FrameSettings, radiance: &[Rgb]) -> Vec<u8> {
    let per_value = match settings.format {
        FrameFormat::F32 => 4,
        FrameFormat::F16 => 2,
        FrameFormat::Srgb8 => 1,
    };
    let mut out = Vec::with_capacity(HEADER_LEN + radiance.len() * 3 * per_value);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&seq.to_le_bytes());
    out.extend_from_slice(&[settings.format.code(), 0, 0, 0]);
    match settings.format {
        FrameFormat::F32 => {
            for v in radiance.iter().flatten() {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        FrameFormat::F16 => {
            for v in radiance.iter().flatten() {
                out.extend_from_slice(&half::f16::from_f32(*v).to_le_bytes());
            }
        }
        FrameFormat::Srgb8 => {
            let scale = exposure_scale(settings.exposure);
            for v in radiance {
                out.extend_from_slice(&display_rgb8(*v, scale, settings.tone));
            }
        }
    }
    out
}

/// `?format=` on the stream's URL; other parameters (an access token) are left to others.
#[derive(Debug, Deserialize)]
pub struct StreamQuery {
    format: Option<String>,
}

/// `GET /api/v1/scenes/{id}/stream`: checks the scene (404, 503 while loading) and the
/// format, then upgrades. A plain GET without the upgrade headers is 426.
#[utoipa::path(
    get,
    path = "/api/v1/scenes/{id}/stream",
    tag = "scenes",
    summary = "WebSocket stream: relight messages in, binary colour frames out.",
    description = "The protocol is in docs/stream.md: JSON relight messages in, one binary \
                   frame of per-vertex colours out per message (the latest wins). Browsers, \
                   which cannot set headers on a WebSocket, pass a token as `access_token`.",
    params(
        crate::schema::SceneIdParam,
        ("format" = Option<String>, Query,
         description = "The frames' encoding: `f32` (default), `f16` or `srgb8`."),
    ),
    responses(
        (status = 101, description = "Switching to the WebSocket protocol."),
        (status = 400, description = "`bad_request`: a bad query; `invalid`: an unknown `format`.", body = ErrorBody),
        (status = 404, description = "`not_found`: no such scene.", body = ErrorBody),
        (status = 426, description = "`upgrade_required`: a plain GET without the WebSocket upgrade headers.", body = ErrorBody),
        (status = 503, description = "`loading`: the scene is still loading (`Retry-After: 1`).", body = ErrorBody),
    )
)]
pub async fn stream(
    State(state): State<AppState>,
    SceneId(id): SceneId,
    identity: Option<axum::Extension<crate::auth::Identity>>,
    query: Result<Query<StreamQuery>, axum::extract::rejection::QueryRejection>,
    upgrade: Result<WebSocketUpgrade, axum::extract::ws::rejection::WebSocketUpgradeRejection>,
) -> Result<Response, AppError> {
    let work_limit = state.params().work_limit(&identity);
    let scene = state.lookup(&id)?;
    let Query(query) =
        query.map_err(|e| AppError::bad_request(format!("bad query: {}", e.body_text())))?;
    let mut settings = FrameSettings::default();
    if let Some(f) = &query.format {
        settings.format = FrameFormat::parse(f).ok_or_else(|| {
            AppError::invalid(format!(
                "format must be \"f32\", \"f16\" or \"srgb8\", got {f:?}"
            ))
        })?;
    }
    let upgrade = upgrade.map_err(|e| {
        AppError::new(
            axum::http::StatusCode::UPGRADE_REQUIRED,
            "upgrade_required",
            format!(
                "this route is a WebSocket stream; connect with a WebSocket client \
                 (Upgrade: websocket): {}",
                e.body_text()
            ),
        )
    })?;
    Ok(upgrade
        .max_message_size(BODY_LIMIT)
        .on_upgrade(move |socket| async move {
            run_stream(socket, state, scene, settings, work_limit).await;
        }))
}

/// Why a stream closes: the close code and the reason sent with it.
#[derive(Debug, Clone, PartialEq)]
pub struct Close {
    pub code: u16,
    pub reason: String,
}

impl Close {
    fn new(code: u16, reason: impl Into<String>) -> Close {
        Close {
            code,
            reason: reason.into(),
        }
    }
}

/// A client message, checked.
#[derive(Debug)]
pub enum ClientMessage {
    /// A relight: its seq and either the parsed request or why it is not a valid request
    /// (answered with an error message; the stream stays open).
    Relight {
        seq: u64,
        request: Result<RelightRequest, String>,
    },
    Config {
        format: Option<FrameFormat>,
        exposure: Option<f32>,
        tone: Option<ToneMap>,
    },
}

/// Parses a text message; `Err` closes the stream with the code and reason.
pub fn parse_message(text: &str) -> Result<ClientMessage, Close> {
    // A key given twice would be lost in the `Value` below: refused first, as in REST bodies.
    translux_proto::check_unique_keys(text)
        .map_err(|e| Close::new(close_code::INVALID, format!("the message: {e}")))?;
    let value: Value = serde_json::from_str(text).map_err(|e| {
        Close::new(
            close_code::INVALID,
            format!("the message is not valid JSON: {e}"),
        )
    })?;
    let Value::Object(mut obj) = value else {
        return Err(Close::new(
            close_code::INVALID,
            "the message must be a JSON object with a \"type\"",
        ));
    };
    let kind = match obj.remove("type") {
        Some(Value::String(s)) => s,
        Some(_) => {
            return Err(Close::new(
                close_code::INVALID,
                "\"type\" must be a string: \"relight\" or \"config\"",
            ));
        }
        None => {
            return Err(Close::new(
                close_code::INVALID,
                "the message lacks \"type\" (\"relight\" or \"config\")",
            ));
        }
    };
    let unknown = |obj: &serde_json::Map<String, Value>, allowed: &[&str]| {
        obj.keys()
            .find(|k| !allowed.contains(&k.as_str()))
            .map(|k| {
                Close::new(
                    close_code::INVALID,
                    format!(
                        "{kind} message: unknown field {k:?} (expected {})",
                        allowed.join(", ")
                    ),
                )
            })
    };
    match kind.as_str() {
        "relight" => {
            if let Some(c) = unknown(&obj, &["seq", "request"]) {
                return Err(c);
            }
            let seq = match obj.get("seq") {
                Some(v) => v.as_u64().ok_or_else(|| {
                    Close::new(
                        close_code::INVALID,
                        format!("relight message: \"seq\" must be an unsigned integer, got {v}"),
                    )
                })?,
                None => {
                    return Err(Close::new(
                        close_code::INVALID,
                        "relight message lacks \"seq\" (an unsigned integer)",
                    ));
                }
            };
            let request = match obj.remove("request") {
                None => Ok(RelightRequest::default()),
                Some(v) => translux_proto::parse_json::<RelightRequest>(&v.to_string())
                    .map_err(|e| format!("request: {e}")),
            };
            Ok(ClientMessage::Relight { seq, request })
        }
        "config" => {
            if let Some(c) = unknown(&obj, &["format", "exposure", "tone_map"]) {
                return Err(c);
            }
            let bad = |field: &str, rule: &str, v: &Value| {
                Close::new(
                    close_code::INVALID,
                    format!("config message: \"{field}\" must be {rule}, got {v}"),
                )
            };
            let format = match obj.get("format") {
                None => None,
                Some(v) => Some(
                    v.as_str()
                        .and_then(FrameFormat::parse)
                        .ok_or_else(|| bad("format", "\"f32\", \"f16\" or \"srgb8\"", v))?,
                ),
            };
            let exposure = match obj.get("exposure") {
                None => None,
                Some(v) => {
                    let rule = format!("a number of stops in [-{MAX_EXPOSURE}, {MAX_EXPOSURE}]");
                    let x = v.as_f64().ok_or_else(|| bad("exposure", &rule, v))?;
                    // as_f64 never yields NaN or infinity (JSON has neither).
                    if x.abs() > MAX_EXPOSURE as f64 {
                        return Err(bad("exposure", &rule, v));
                    }
                    Some(x as f32)
                }
            };
            let tone = match obj.get("tone_map") {
                None => None,
                Some(v) => Some(
                    v.as_str()
                        .and_then(|s| s.parse::<ToneMap>().ok())
                        .ok_or_else(|| bad("tone_map", "\"srgb\" or \"filmic\"", v))?,
                ),
            };
            Ok(ClientMessage::Config {
                format,
                exposure,
                tone,
            })
        }
        other => Err(Close::new(
            close_code::POLICY,
            format!("unknown message type {other:?}; expected \"relight\" or \"config\""),
        )),
    }
}

/// The reason cut to the protocol's 123 bytes at a character boundary.
fn close_message(close: &Close) -> Message {
    let mut reason = close.reason.as_str();
    if reason.len() > MAX_REASON {
        let mut end = MAX_REASON;
        while !reason.is_char_boundary(end) {
            end -= 1;
        }
        reason = &reason[..end];
    }
    Message::Close(Some(CloseFrame {
        code: close.code,
        reason: Utf8Bytes::from(reason),
    }))
}

fn text(v: &Value) -> Message {
    Message::Text(Utf8Bytes::from(v.to_string()))
}

fn error_message(seq: u64, e: &AppError) -> Message {
    text(&json!({
        "type": "error",
        "seq": seq,
        "error": {"code": e.code, "message": e.message},
    }))
}

/// What a stream is doing.
struct Conn {
    state: AppState,
    scene: Arc<Scene>,
    client: String,
    settings: FrameSettings,
    /// The relight being computed: its seq and the pool's ticket.
    in_flight: Option<(u64, Ticket)>,
    /// The newest request not yet submitted, with the frame it relights.
    pending: Option<(u64, relight::RelightPlan, Arc<Scene>)>,
    /// When to try submitting `pending` again after the queue was full.
    retry_at: Option<tokio::time::Instant>,
    dropped: u64,
    /// The most time one relight's lamp walks may take, by the stream's token or role.
    work_limit: std::time::Duration,
}

impl Conn {
    /// Submits `pending` if nothing is in flight; a full queue keeps it pending and retries
    /// shortly; any other refusal is answered as an error.
    fn pump(&mut self) -> Option<Message> {
        if self.in_flight.is_some() {
            return None;
        }
        let (seq, plan, scene) = self.pending.take()?;
        match self.state.pool().submit(
            scene.engine(),
            Work::Relight(plan.clone()),
            self.client.clone(),
        ) {
            Ok(ticket) => {
                self.in_flight = Some((seq, ticket));
                self.retry_at = None;
                None
            }
            Err(e) if e.code == "queue_full" => {
                self.pending = Some((seq, plan, scene));
                self.retry_at = Some(tokio::time::Instant::now() + RETRY_FULL);
                None
            }
            Err(e) => Some(error_message(seq, &e)),
        }
    }

    /// Handles a checked relight: plan it (errors answered at once), then latest wins.
    fn relight(&mut self, seq: u64, request: Result<RelightRequest, String>) -> Option<Message> {
        let plan = request.map_err(AppError::bad_request).and_then(|r| {
            let scene = self.scene.frame(r.frame)?;
            let plan = relight::RelightPlan {
                work_limit: Some(self.work_limit),
                ..relight::plan(&scene, r).map_err(AppError::from)?
            };
            Ok((plan, scene))
        });
        let (plan, scene) = match plan {
            Ok(p) => p,
            Err(e) => return Some(error_message(seq, &e)),
        };
        if self.pending.replace((seq, plan, scene)).is_some() {
            self.dropped += 1;
            self.state.metrics().ws_dropped.inc();
        }
        self.pump()
    }

    /// The frame and stats (or the error) for a finished relight.
    fn answer(&self, seq: u64, answer: Result<crate::pool::Answer, AppError>) -> Vec<Message> {
        let result = answer.and_then(|a| a.result);
        match result {
            Ok(Done::Relight(out)) => {
                let frame = encode_frame(seq, &self.settings, &out.radiance);
                self.state
                    .metrics()
                    .ws_frames
                    .with_label_values(&[self.settings.format.as_str()])
                    .inc();
                vec![
                    Message::Binary(frame.into()),
                    text(&json!({
                        "type": "stats",
                        "seq": seq,
                        "stats": out.stats,
                        "dropped": self.dropped,
                    })),
                ]
            }
            Ok(Done::Render(_)) => vec![error_message(
                seq,
                &AppError::internal("the pool answered a render to a relight"),
            )],
            Err(e) => vec![error_message(seq, &e)],
        }
    }
}

/// Runs one stream until the client closes it, breaks the protocol, stops answering pings,
/// or the server shuts down.
pub async fn run_stream<S>(
    mut socket: S,
    state: AppState,
    scene: Arc<Scene>,
    settings: FrameSettings,
    work_limit: std::time::Duration,
) where
    S: Stream<Item = Result<Message, axum::Error>> + Sink<Message, Error = axum::Error> + Unpin,
{
    let metrics = state.metrics().clone();
    metrics.ws_connections.inc();
    let id = state.next_stream_id();
    tracing::debug!(scene = %scene.id, stream = id, "stream opened");
    let stall = stall_limit(state.params().ping_interval);
    let outcome = drive(&mut socket, state, scene, settings, (id, work_limit)).await;
    match &outcome {
        Ok(Some(close)) => {
            tracing::debug!(stream = id, code = close.code, reason = %close.reason, "stream closed");
            let _ = send_within(&mut socket, close_message(close), stall).await;
        }
        Ok(None) => tracing::debug!(stream = id, "stream closed by the client"),
        Err(e) => tracing::debug!(stream = id, "stream failed: {e}"),
    }
    let _ = tokio::time::timeout(stall, socket.close()).await;
    metrics.ws_connections.dec();
}

/// How long one send may wait for the client to read: four ping intervals, the same
/// patience as for a client that stops answering pings. A client that never reads would
/// otherwise block the stream's only task in `send`, where no ping timeout can fire.
fn stall_limit(ping_every: std::time::Duration) -> std::time::Duration {
    4 * ping_every
}

/// `socket.send(m)`, failing once it has waited `limit` for the client to take it.
async fn send_within<S>(
    socket: &mut S,
    m: Message,
    limit: std::time::Duration,
) -> Result<(), axum::Error>
where
    S: Sink<Message, Error = axum::Error> + Unpin,
{
    match tokio::time::timeout(limit, socket.send(m)).await {
        Ok(r) => r,
        Err(_) => Err(axum::Error::new(format!(
            "the client read nothing for {} s; dropping the stream",
            limit.as_secs_f32()
        ))),
    }
}

/// Whether a read error is tungstenite's "message (or frame) over the size limit".
fn is_too_big(e: &axum::Error) -> bool {
    // axum wraps tungstenite's `Error::Capacity` without exposing its type; its message
    // is the stable part ("Space limit exceeded: Message too long: …").
    let text = e.to_string();
    text.contains("Space limit exceeded") || text.contains("too long")
}

/// The stream's loop. `Ok(Some(close))`: close with that; `Ok(None)`: the client closed.
async fn drive<S>(
    socket: &mut S,
    state: AppState,
    scene: Arc<Scene>,
    settings: FrameSettings,
    (id, work_limit): (u64, std::time::Duration),
) -> Result<Option<Close>, axum::Error>
where
    S: Stream<Item = Result<Message, axum::Error>> + Sink<Message, Error = axum::Error> + Unpin,
{
    let ping_every = state.params().ping_interval;
    let stall = stall_limit(ping_every);
    let mut shutdown = state.shutdown_watch();
    let mut closing = *shutdown.borrow();
    let mut conn = Conn {
        work_limit,
        state,
        client: format!("stream-{id}"),
        scene,
        settings,
        in_flight: None,
        pending: None,
        retry_at: None,
        dropped: 0,
    };
    let ready = text(&json!({
        "type": "ready",
        "scene": conn.scene.id,
        "vertex_count": conn.scene.bundle.vertex_positions().len(),
        "format": conn.settings.format.as_str(),
    }));
    send_within(socket, ready, stall).await?;
    let mut ping = tokio::time::interval_at(tokio::time::Instant::now() + ping_every, ping_every);
    let mut heard = Instant::now();
    loop {
        if closing && conn.in_flight.is_none() && conn.pending.is_none() {
            return Ok(Some(Close::new(
                close_code::AWAY,
                "the server is shutting down",
            )));
        }
        let retry_at = conn.retry_at;
        tokio::select! {
            answer = async {
                match conn.in_flight.as_mut() {
                    Some((_, ticket)) => ticket.await,
                    None => std::future::pending().await,
                }
            }, if conn.in_flight.is_some() => {
                let (seq, _) = conn.in_flight.take().expect("in flight");
                let answer = answer.map_err(|_| {
                    AppError::internal("a relight worker stopped without answering")
                });
                for m in conn.answer(seq, answer) {
                    send_within(socket, m, stall).await?;
                }
                if let Some(m) = conn.pump() {
                    send_within(socket, m, stall).await?;
                }
            }
            _ = async {
                match retry_at {
                    Some(t) => tokio::time::sleep_until(t).await,
                    None => std::future::pending().await,
                }
            }, if retry_at.is_some() => {
                conn.retry_at = None;
                if let Some(m) = conn.pump() {
                    send_within(socket, m, stall).await?;
                }
            }
            msg = socket.next(), if !closing => {
                heard = Instant::now();
                let Some(msg) = msg else { return Ok(None) };
                let msg = match msg {
                    Ok(m) => m,
                    // A message over the limit: say so with 1009 instead of dropping the
                    // connection (the client would see 1005, no reason).
                    Err(e) if is_too_big(&e) => {
                        return Ok(Some(Close::new(
                            close_code::SIZE,
                            format!("message too big: at most {BODY_LIMIT} bytes"),
                        )));
                    }
                    Err(e) => return Err(e),
                };
                match msg {
                    Message::Text(t) => match parse_message(t.as_str()) {
                        Ok(ClientMessage::Relight { seq, request }) => {
                            if let Some(m) = conn.relight(seq, request) {
                                send_within(socket, m, stall).await?;
                            }
                        }
                        Ok(ClientMessage::Config { format, exposure, tone }) => {
                            let s = &mut conn.settings;
                            s.format = format.unwrap_or(s.format);
                            s.exposure = exposure.unwrap_or(s.exposure);
                            s.tone = tone.unwrap_or(s.tone);
                        }
                        Err(close) => return Ok(Some(close)),
                    },
                    Message::Binary(_) => {
                        return Ok(Some(Close::new(
                            close_code::UNSUPPORTED,
                            "binary messages are not part of the protocol; send JSON text",
                        )));
                    }
                    Message::Close(_) => return Ok(None),
                    Message::Ping(_) | Message::Pong(_) => {}
                }
            }
            _ = ping.tick() => {
                if heard.elapsed() > 4 * ping_every {
                    return Ok(Some(Close::new(
                        close_code::AWAY,
                        format!("no answer to pings for {} s", heard.elapsed().as_secs()),
                    )));
                }
                send_within(socket, Message::Ping(axum::body::Bytes::new()), stall).await?;
            }
            _ = shutdown.changed(), if !closing => {
                closing = true;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn closes(text: &str) -> Close {
        match parse_message(text) {
            Err(c) => c,
            Ok(m) => panic!("{text} parsed as {m:?}"),
        }
    }

    #[test]
    fn bad_messages_close_with_a_reason_naming_the_problem() {
        let c = closes("{nope");
        assert_eq!(c.code, 1007);
        assert!(c.reason.contains("not valid JSON"), "{c:?}");
        assert_eq!(closes("[1]").code, 1007);
        let c = closes(r#"{"seq":1}"#);
        assert!(c.reason.contains("\"type\""), "{c:?}");
        let c = closes(r#"{"type":"dance","seq":1}"#);
        assert_eq!(c.code, 1008);
        assert!(c.reason.contains("dance"), "{c:?}");
        let c = closes(r#"{"type":"relight","request":{}}"#);
        assert!(c.reason.contains("lacks \"seq\""), "{c:?}");
        let c = closes(r#"{"type":"relight","seq":-1}"#);
        assert!(
            c.reason.contains("\"seq\" must be an unsigned integer"),
            "{c:?}"
        );
        let c = closes(r#"{"type":"relight","seq":"3"}"#);
        assert!(c.reason.contains("\"seq\""), "{c:?}");
        let c = closes(r#"{"type":"relight","seq":1,"reqest":{}}"#);
        assert!(c.reason.contains("reqest"), "{c:?}");
        let c = closes(r#"{"type":"config","format":"png"}"#);
        assert!(
            c.reason.contains("format") && c.reason.contains("png"),
            "{c:?}"
        );
        let c = closes(r#"{"type":"config","exposure":100}"#);
        assert!(c.reason.contains("exposure"), "{c:?}");
        let c = closes(r#"{"type":"config","tone_map":"aces"}"#);
        assert!(c.reason.contains("tone_map"), "{c:?}");
        // A key given twice, at the top or inside the request, is never silently dropped.
        let c = closes(r#"{"type":"relight","seq":1,"seq":2}"#);
        assert_eq!(c.code, 1007);
        assert!(
            c.reason.contains("seq") && c.reason.contains("twice"),
            "{c:?}"
        );
        let c = closes(
            r#"{"type":"relight","seq":1,"request":{"materials":{"a":{"type":"diffuse","albedo":[1,1,1]},"a":{"type":"diffuse","albedo":[0,0,0]}}}}"#,
        );
        assert!(
            c.reason.contains("request.materials.a") && c.reason.contains("twice"),
            "{c:?}"
        );
    }

    #[test]
    fn good_messages_parse() {
        let m = parse_message(r#"{"type":"relight","seq":7,"request":{"components":"direct"}}"#)
            .unwrap();
        let ClientMessage::Relight { seq, request } = m else {
            panic!()
        };
        assert_eq!(seq, 7);
        assert_eq!(request.unwrap().components.as_str(), "direct");
        // A request that is not a valid relight request is answered, not closed.
        let m = parse_message(r#"{"type":"relight","seq":8,"request":{"lihgts":[]}}"#).unwrap();
        let ClientMessage::Relight { request, .. } = m else {
            panic!()
        };
        let e = request.unwrap_err();
        assert!(e.contains("lihgts"), "{e}");
        let m = parse_message(
            r#"{"type":"config","format":"srgb8","exposure":-1.5,"tone_map":"filmic"}"#,
        )
        .unwrap();
        let ClientMessage::Config {
            format,
            exposure,
            tone,
        } = m
        else {
            panic!()
        };
        assert_eq!(
            (format, exposure, tone),
            (Some(FrameFormat::Srgb8), Some(-1.5), Some(ToneMap::Filmic))
        );
    }

    #[test]
    fn frames_have_the_header_and_the_colours() {
        let radiance = [[0.25f32, 1.5, 0.0], [2.0, 0.001, 0.5]];
        let mut s = FrameSettings::default();
        let f = encode_frame(0x0102_0304_0506_0708, &s, &radiance);
        assert_eq!(&f[..4], b"TLXF");
        assert_eq!(
            u64::from_le_bytes(f[4..12].try_into().unwrap()),
            0x0102_0304_0506_0708
        );
        assert_eq!(&f[12..16], &[0, 0, 0, 0]);
        assert_eq!(f.len(), 16 + 6 * 4);
        assert_eq!(f32::from_le_bytes(f[20..24].try_into().unwrap()), 1.5);
        s.format = FrameFormat::F16;
        let f = encode_frame(1, &s, &radiance);
        assert_eq!((f[12], f.len()), (1, 16 + 6 * 2));
        // 1.5 in IEEE half is 0x3E00.
        assert_eq!(&f[18..20], &[0x00, 0x3E]);
        s.format = FrameFormat::Srgb8;
        s.exposure = 1.0;
        let f = encode_frame(2, &s, &radiance);
        assert_eq!((f[12], f.len()), (2, 16 + 6));
        // 0.25 × 2 = 0.5 linear → sRGB 0.7354 → 188; 1.5 × 2 clamps to 255.
        assert_eq!(&f[16..19], &[188, 255, 0]);
    }

    #[test]
    fn long_close_reasons_are_cut_at_a_character_boundary() {
        let m = close_message(&Close::new(1007, "é".repeat(100)));
        let Message::Close(Some(f)) = m else { panic!() };
        assert!(f.reason.as_str().len() <= 123);
        assert_eq!(f.reason.as_str().len() % 2, 0);
    }
}
