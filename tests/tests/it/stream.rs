//! The WebSocket stream (`GET /api/v1/scenes/{id}/stream`, docs/stream.md) against a real
//! server on 127.0.0.1:0: latest wins while a light is dragged, the three frame formats,
//! errors that keep the stream open, bad messages that close it with a reason, pings, and
//! closing on shutdown.

use std::time::Duration;

use crate::support::*;
use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};
use translux_server::ServerParams;

type Ws = WebSocketStream<MaybeTlsStream<TcpStream>>;

/// Long enough for anything this small scene does; a hang fails instead of stalling CI.
const WAIT: Duration = Duration::from_secs(60);

async fn connect(s: &TestServer, query: &str) -> (Ws, Value) {
    let url = s.ws_url(&format!("/api/v1/scenes/{ID}/stream{query}"));
    let (mut ws, _) = tokio_tungstenite::connect_async(url)
        .await
        .expect("upgrade");
    let ready = next_text(&mut ws).await;
    assert_eq!(ready["type"], "ready", "{ready}");
    (ws, ready)
}

/// The next message that is not a ping or pong.
async fn next(ws: &mut Ws) -> Message {
    loop {
        let m = tokio::time::timeout(WAIT, ws.next())
            .await
            .expect("a message in time")
            .expect("the stream is open")
            .expect("a message");
        if !matches!(m, Message::Ping(_) | Message::Pong(_)) {
            return m;
        }
    }
}

async fn next_text(ws: &mut Ws) -> Value {
    match next(ws).await {
        Message::Text(t) => serde_json::from_str(t.as_str()).unwrap(),
        other => panic!("expected text, got {other:?}"),
    }
}

async fn send(ws: &mut Ws, v: &Value) {
    ws.send(Message::text(v.to_string())).await.unwrap();
}

fn relight_msg(seq: u64, request: &Value) -> Value {
    json!({"type": "relight", "seq": seq, "request": request})
}

/// A decoded binary frame.
struct Frame {
    seq: u64,
    format: u8,
    payload: Vec<u8>,
}

fn decode(bytes: &[u8]) -> Frame {
    assert!(bytes.len() >= 16, "frame of {} bytes", bytes.len());
    assert_eq!(&bytes[0..4], b"TLXF");
    assert_eq!(&bytes[13..16], &[0, 0, 0]);
    Frame {
        seq: u64::from_le_bytes(bytes[4..12].try_into().unwrap()),
        format: bytes[12],
        payload: bytes[16..].to_vec(),
    }
}

/// The binary frame and the stats message that answer a relight.
async fn answer(ws: &mut Ws) -> (Frame, Value) {
    let frame = match next(ws).await {
        Message::Binary(b) => decode(&b),
        Message::Text(t) => panic!("expected a frame, got {t}"),
        other => panic!("expected a frame, got {other:?}"),
    };
    let stats = next_text(ws).await;
    assert_eq!(stats["type"], "stats", "{stats}");
    assert_eq!(stats["seq"], frame.seq, "{stats}");
    (frame, stats)
}

/// Reads until the close frame: its code and reason.
async fn close_of(ws: &mut Ws) -> (u16, String) {
    loop {
        match next(ws).await {
            Message::Close(Some(f)) => return (u16::from(f.code), f.reason.as_str().to_string()),
            Message::Close(None) => panic!("closed without a code"),
            _ => {}
        }
    }
}

#[tokio::test]
async fn a_dragged_light_gets_the_last_moves_colours_in_far_fewer_frames() {
    let s = TestServer::cornell(ServerParams::default()).await;
    let (mut ws, ready) = connect(&s, "").await;
    let vertices = ready["vertex_count"].as_u64().unwrap() as usize;
    assert_eq!(ready["scene"], ID);
    assert_eq!(ready["format"], "f32");

    // 100 moves as fast as the socket takes them; the last one differs in colour too, so
    // its answer cannot be mistaken for any earlier one's.
    let moves: Vec<Value> = (0..100)
        .map(|k| {
            let x = -0.2 + 0.4 * k as f32 / 99.0;
            let colour = if k == 99 {
                [0.2, 0.2, 3.0]
            } else {
                [1.0, 1.0, 1.0]
            };
            light_at(x, colour)
        })
        .collect();
    for (k, m) in moves.iter().enumerate() {
        send(&mut ws, &relight_msg(k as u64 + 1, m)).await;
    }
    let mut frames = 0;
    let mut last_seq = 0;
    let (frame, stats) = loop {
        let (frame, stats) = answer(&mut ws).await;
        frames += 1;
        assert!(frame.seq > last_seq, "frames arrive in request order");
        last_seq = frame.seq;
        if frame.seq == 100 {
            break (frame, stats);
        }
    };
    // Every request was answered or dropped, never queued: far fewer frames than moves.
    let dropped = stats["dropped"].as_u64().unwrap();
    assert_eq!(frames + dropped, 100, "frames {frames}, dropped {dropped}");
    assert!(frames <= 20, "{frames} frames for 100 moves");
    assert_eq!(frame.format, 0);
    let got = floats(&frame.payload);
    assert_eq!(got.len(), vertices * 3);
    let want = reference(&moves[99]);
    assert_close(&got, &want, SOLVER_TOL, "the last move's colours");
    let before = reference(&moves[98]);
    assert!(
        rel_diff(&got, &before) > 0.2,
        "the last frame is the last move's"
    );
    assert_eq!(stats["stats"]["lights"], 1);

    // Nothing else is pending: the next message is the answer to a new request.
    send(&mut ws, &relight_msg(500, &json!({}))).await;
    let (frame, _) = answer(&mut ws).await;
    assert_eq!(frame.seq, 500);
    ws.close(None).await.unwrap();
    s.stop().await;
}

/// An sRGB 8-bit value from linear `v` (IEC 61966-2-1), written out here independently.
fn srgb8(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0) as f64;
    let e = if v <= 0.0031308 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (e * 255.0) as f32
}

/// Narkowicz's ACES fit x(2.51x + 0.03) / (x(2.43x + 0.59) + 0.14), clamped to [0, 1].
fn aces(x: f32) -> f32 {
    let x = x.max(0.0) as f64;
    ((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)).clamp(0.0, 1.0) as f32
}

#[tokio::test]
async fn frames_decode_in_all_three_formats_and_f32_equals_the_rest_relight() {
    let s = TestServer::cornell(ServerParams::default()).await;
    let request = light_at(0.1, [2.0, 1.5, 1.0]);
    let rest = s.relight_ok(&request).await;
    assert_close(&rest, &reference(&request), SOLVER_TOL, "REST vs library");

    // f32 (the default), then f16 and srgb8 by the query, then by config messages.
    let (mut ws, _) = connect(&s, "").await;
    send(&mut ws, &relight_msg(1, &request)).await;
    let (f, _) = answer(&mut ws).await;
    assert_eq!((f.seq, f.format), (1, 0));
    assert_eq!(floats(&f.payload), rest, "f32 frame vs REST binary");

    let (mut ws16, ready) = connect(&s, "?format=f16").await;
    assert_eq!(ready["format"], "f16");
    send(&mut ws16, &relight_msg(2, &request)).await;
    let (f, _) = answer(&mut ws16).await;
    assert_eq!((f.seq, f.format), (2, 1));
    assert_eq!(f.payload.len(), rest.len() * 2);
    for (k, (h, want)) in f.payload.chunks_exact(2).zip(&rest).enumerate() {
        let got = half::f16::from_le_bytes([h[0], h[1]]).to_f32();
        // Half precision: 11 significant bits, subnormals below 6.1e-5.
        assert!(
            (got - want).abs() <= want.abs() / 1024.0 + 6e-8,
            "f16 value {k}: {got} vs {want}"
        );
    }

    let (mut ws8, _) = connect(&s, "?format=srgb8").await;
    send(&mut ws8, &relight_msg(3, &request)).await;
    let (f, _) = answer(&mut ws8).await;
    assert_eq!((f.seq, f.format), (3, 2));
    assert_eq!(f.payload.len(), rest.len());
    for (k, (&b, &want)) in f.payload.iter().zip(&rest).enumerate() {
        let expect = srgb8(want);
        assert!(
            (b as f32 - expect).abs() <= 0.51,
            "srgb8 value {k}: {b} vs {expect}"
        );
    }
    // Exposure and the filmic curve by a config message, on the same stream.
    send(
        &mut ws8,
        &json!({"type": "config", "exposure": 1.5, "tone_map": "filmic"}),
    )
    .await;
    send(&mut ws8, &relight_msg(4, &request)).await;
    let (f, _) = answer(&mut ws8).await;
    assert_eq!((f.seq, f.format), (4, 2));
    let scale = 2f32.powf(1.5);
    let mut differs = 0;
    for (k, (&b, &want)) in f.payload.iter().zip(&rest).enumerate() {
        let expect = srgb8(aces(want * scale));
        assert!(
            (b as f32 - expect).abs() <= 0.51,
            "filmic value {k}: {b} vs {expect}"
        );
        differs += usize::from((expect - srgb8(want)).abs() > 2.0);
    }
    assert!(
        differs > rest.len() / 10,
        "exposure and filmic change the bytes"
    );
    // And back to f32 by config.
    send(&mut ws8, &json!({"type": "config", "format": "f32"})).await;
    send(&mut ws8, &relight_msg(5, &request)).await;
    let (f, _) = answer(&mut ws8).await;
    assert_eq!((f.seq, f.format), (5, 0));
    assert_eq!(floats(&f.payload), rest);
    s.stop().await;
}

#[tokio::test]
async fn a_bad_relight_is_answered_with_an_error_and_the_stream_stays_open() {
    let s = TestServer::cornell(ServerParams::default()).await;
    let (mut ws, _) = connect(&s, "").await;
    let bad =
        json!({"lights": [{"type": "point", "position": [0, 0.5, 0], "intensity": [1, -1, 1]}]});
    send(&mut ws, &relight_msg(7, &bad)).await;
    let e = next_text(&mut ws).await;
    assert_eq!(
        (e["type"].as_str(), e["seq"].as_u64()),
        (Some("error"), Some(7)),
        "{e}"
    );
    assert_eq!(e["error"]["code"], "invalid");
    assert!(
        e["error"]["message"]
            .as_str()
            .unwrap()
            .contains("lights[0].intensity[1]"),
        "{e}"
    );
    send(&mut ws, &relight_msg(8, &json!({"lihgts": []}))).await;
    let e = next_text(&mut ws).await;
    assert_eq!(
        (e["seq"].as_u64(), e["error"]["code"].as_str()),
        (Some(8), Some("bad_request"))
    );
    assert!(
        e["error"]["message"].as_str().unwrap().contains("lihgts"),
        "{e}"
    );
    send(
        &mut ws,
        &relight_msg(
            9,
            &json!({"materials": {"nope": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}}),
        ),
    )
    .await;
    let e = next_text(&mut ws).await;
    assert!(
        e["error"]["message"]
            .as_str()
            .unwrap()
            .contains("materials.nope"),
        "{e}"
    );
    // Still open: a good request is answered.
    send(&mut ws, &relight_msg(10, &json!({}))).await;
    let (f, _) = answer(&mut ws).await;
    assert_eq!(f.seq, 10);
    s.stop().await;
}

#[tokio::test]
async fn bad_messages_close_the_stream_with_a_code_and_a_reason() {
    let s = TestServer::cornell(ServerParams::default()).await;
    let cases: &[(Message, u16, &[&str])] = &[
        (Message::text("{not json"), 1007, &["not valid JSON"]),
        (Message::text("[1,2]"), 1007, &["JSON object"]),
        (Message::text(r#"{"seq":1}"#), 1007, &["\"type\""]),
        (
            Message::text(r#"{"type":"dance","seq":1}"#),
            1008,
            &["\"dance\""],
        ),
        (
            Message::text(r#"{"type":"relight","request":{}}"#),
            1007,
            &["lacks \"seq\""],
        ),
        (
            Message::text(r#"{"type":"relight","seq":"1"}"#),
            1007,
            &["\"seq\"", "unsigned integer"],
        ),
        (
            Message::text(r#"{"type":"relight","seq":-3}"#),
            1007,
            &["\"seq\""],
        ),
        (
            Message::text(r#"{"type":"relight","seq":1,"extra":0}"#),
            1007,
            &["\"extra\""],
        ),
        (
            Message::text(r#"{"type":"config","format":"png"}"#),
            1007,
            &["format", "png"],
        ),
        (
            Message::text(r#"{"type":"config","exposure":"bright"}"#),
            1007,
            &["exposure"],
        ),
        (Message::binary(vec![1u8, 2, 3]), 1003, &["binary"]),
    ];
    for (msg, code, needles) in cases {
        let (mut ws, _) = connect(&s, "").await;
        ws.send(msg.clone()).await.unwrap();
        let (got, reason) = close_of(&mut ws).await;
        assert_eq!(got, *code, "{msg:?}: {reason}");
        for n in *needles {
            assert!(reason.contains(n), "{msg:?}: {reason:?} lacks {n:?}");
        }
    }
    s.stop().await;
}

#[tokio::test]
async fn the_stream_route_refuses_unknown_scenes_bad_formats_and_plain_gets() {
    let s = TestServer::cornell(ServerParams::default()).await;
    let url = s.ws_url("/api/v1/scenes/nope/stream");
    match tokio_tungstenite::connect_async(url).await {
        Err(tokio_tungstenite::tungstenite::Error::Http(r)) => {
            assert_eq!(r.status().as_u16(), 404);
            let body = String::from_utf8(r.body().clone().unwrap_or_default()).unwrap();
            assert!(
                body.contains("not_found") && body.contains("nope"),
                "{body}"
            );
        }
        other => panic!("expected 404, got {other:?}"),
    }
    let url = s.ws_url(&format!("/api/v1/scenes/{ID}/stream?format=png"));
    match tokio_tungstenite::connect_async(url).await {
        Err(tokio_tungstenite::tungstenite::Error::Http(r)) => {
            assert_eq!(r.status().as_u16(), 400)
        }
        other => panic!("expected 400, got {other:?}"),
    }
    let (status, code, message) =
        error_of(s.get(&format!("/api/v1/scenes/{ID}/stream")).await).await;
    assert_eq!((status.as_u16(), code.as_str()), (426, "upgrade_required"));
    assert!(message.contains("WebSocket"), "{message}");
    s.stop().await;
}

#[tokio::test]
async fn the_server_pings_and_closes_streams_with_1001_on_shutdown() {
    let params = ServerParams {
        ping_interval: Duration::from_millis(100),
        ..Default::default()
    };
    let s = TestServer::cornell(params).await;
    let (mut ws, _) = connect(&s, "").await;
    let ping = tokio::time::timeout(WAIT, async {
        loop {
            if let Message::Ping(_) = ws.next().await.unwrap().unwrap() {
                return;
            }
        }
    })
    .await;
    assert!(ping.is_ok(), "no ping");
    let metrics = s.metrics().await;
    assert_eq!(metric(&metrics, "translux_ws_connections", &[]), Some(1.0));

    // A relight sent just before shutdown is still answered, then the stream closes with
    // 1001 and the server stops.
    send(&mut ws, &relight_msg(1, &json!({}))).await;
    tokio::time::sleep(Duration::from_millis(1)).await;
    let stop = tokio::spawn(s.stop());
    let (f, _) = answer(&mut ws).await;
    assert_eq!(f.seq, 1);
    let (code, reason) = close_of(&mut ws).await;
    assert_eq!(code, 1001, "{reason}");
    assert!(reason.contains("shutting down"), "{reason}");
    tokio::time::timeout(WAIT, stop)
        .await
        .expect("the server stops once its streams are closed")
        .unwrap();
}

/// A message over the size limit closes the stream with 1009 and a reason (it used to drop
/// the connection, which clients see as 1005 with no reason).
#[tokio::test]
async fn an_oversized_message_closes_with_1009() {
    let s = TestServer::cornell(ServerParams::default()).await;
    let (mut ws, _) = connect(&s, "").await;
    let big = format!(
        "{{\"type\":\"relight\",\"seq\":1,\"pad\":\"{}\"}}",
        "x".repeat(2 << 20)
    );
    ws.send(Message::text(big)).await.unwrap();
    let (code, reason) = close_of(&mut ws).await;
    assert_eq!(code, 1009, "{reason}");
    assert!(reason.contains("too big"), "{reason}");
    s.stop().await;
}

/// A client that sends relights but never reads its socket: once the server's sends have
/// waited four ping intervals the stream is dropped (a blocked send used to keep it, and
/// its worker slot, forever — the ping timeout cannot fire while `send` waits).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_never_reads_is_dropped() {
    let params = ServerParams {
        ping_interval: Duration::from_millis(250),
        ..Default::default()
    };
    let s = TestServer::cornell(params).await;
    let (mut ws, _) = connect(&s, "?format=f32").await;
    // Each answer is a full frame; enough of them fill both sides' socket buffers.
    let mut sent = 0u64;
    let t0 = std::time::Instant::now();
    let dropped = loop {
        let r = tokio::time::timeout(
            Duration::from_secs(2),
            ws.send(Message::text(relight_msg(sent, &json!({})).to_string())),
        )
        .await;
        sent += 1;
        if !matches!(r, Ok(Ok(()))) {
            // Our own send blocked or failed: the server stopped reading too.
            break false;
        }
        let open = metric(&s.metrics().await, "translux_ws_connections", &[]);
        if open == Some(0.0) {
            break true;
        }
        assert!(
            t0.elapsed() < WAIT,
            "the stream was never dropped ({sent} relights sent)"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    };
    if !dropped {
        let t1 = std::time::Instant::now();
        loop {
            if metric(&s.metrics().await, "translux_ws_connections", &[]) == Some(0.0) {
                break;
            }
            assert!(
                t1.elapsed() < WAIT,
                "a client that never reads kept its stream"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
    drop(ws);
    s.stop().await;
}
