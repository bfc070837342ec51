//! Load generator for a running `translux-server` (what `bench/server.sh` runs).
//!
//! What it measures, on loopback:
//! - `rest`: closed-loop clients (each sends a relight, waits for the answer, sends the
//!   next) at each concurrency level for a fixed time; requests/s and p50/p90/p99 latency.
//!   Each request moves one point light along a path, as a script sweeping a light would,
//!   so no two consecutive requests are the same.
//! - `drag`: one WebSocket stream that sends a light move every 16 ms (a 60 Hz drag) for a
//!   fixed time; frames/s received, latency from a move's send to its frame (p50/p99), and
//!   how many moves were superseded (latest wins).
//!
//! ```sh
//! cargo run --release -p translux-server --example load -- \
//!     --url http://127.0.0.1:8090 --scene cornell rest --clients 1,8,64 --seconds 10
//! cargo run --release -p translux-server --example load -- \
//!     --url http://127.0.0.1:8090 --scene cornell drag --seconds 10
//! ```
//!
//! Prints one Markdown table row per run.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

fn usage() -> ! {
    eprintln!(
        "usage: load [--url URL] [--scene ID] rest [--clients 1,8,64] [--seconds S]\n       \
         load [--url URL] [--scene ID] drag [--seconds S] [--interval-ms 16] [--format f32]"
    );
    std::process::exit(2)
}

/// A light on a circle under the ceiling of the Cornell box, at step `k`.
fn request(k: u64) -> Value {
    let a = k as f32 * 0.05;
    json!({"lights": [{"type": "point",
        "position": [0.18 * a.cos(), 0.45, 0.18 * a.sin()],
        "intensity": [0.8, 0.8, 0.8]}]})
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let k = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[k]
}

async fn rest(url: &str, scene: &str, clients: usize, seconds: f64) {
    let client = reqwest::Client::builder()
        .pool_max_idle_per_host(clients)
        .build()
        .expect("HTTP client");
    let endpoint = Arc::new(format!("{url}/api/v1/scenes/{scene}/relight"));
    let start = Instant::now();
    let end = start + Duration::from_secs_f64(seconds);
    let tasks: Vec<_> = (0..clients)
        .map(|c| {
            let client = client.clone();
            let endpoint = endpoint.clone();
            tokio::spawn(async move {
                let mut latencies = Vec::new();
                let mut errors: HashMap<u16, u64> = HashMap::new();
                let mut k = c as u64 * 1000;
                while Instant::now() < end {
                    let t = Instant::now();
                    let r = client
                        .post(endpoint.as_str())
                        .header("content-type", "application/json")
                        .header("accept", "application/octet-stream")
                        .body(request(k).to_string())
                        .send()
                        .await;
                    k += 1;
                    match r {
                        Ok(r) if r.status().is_success() => {
                            let _ = r.bytes().await;
                            latencies.push(t.elapsed().as_secs_f64() * 1e3);
                        }
                        Ok(r) => {
                            *errors.entry(r.status().as_u16()).or_default() += 1;
                            let _ = r.bytes().await;
                        }
                        Err(_) => *errors.entry(0).or_default() += 1,
                    }
                }
                (latencies, errors)
            })
        })
        .collect();
    let mut all = Vec::new();
    let mut errors: HashMap<u16, u64> = HashMap::new();
    for t in tasks {
        let (l, e) = t.await.expect("client task");
        all.extend(l);
        for (k, v) in e {
            *errors.entry(k).or_default() += v;
        }
    }
    let elapsed = start.elapsed().as_secs_f64();
    all.sort_by(f64::total_cmp);
    let errs = if errors.is_empty() {
        "0".to_string()
    } else {
        let mut e: Vec<_> = errors.into_iter().collect();
        e.sort();
        e.iter()
            .map(|(k, v)| format!("{v}×{k}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    println!(
        "| {clients} | {} | {:.1} | {:.1} | {:.1} | {:.1} | {errs} |",
        all.len(),
        all.len() as f64 / elapsed,
        percentile(&all, 0.5),
        percentile(&all, 0.9),
        percentile(&all, 0.99),
    );
}

async fn drag(url: &str, scene: &str, seconds: f64, interval: Duration, format: &str) {
    let ws_url = format!(
        "{}/api/v1/scenes/{scene}/stream?format={format}",
        url.replacen("http", "ws", 1)
    );
    let (ws, _) = tokio_tungstenite::connect_async(ws_url)
        .await
        .expect("WebSocket upgrade");
    let (mut tx, mut rx) = ws.split();
    let sent: Arc<std::sync::Mutex<HashMap<u64, Instant>>> = Default::default();
    let moves = (seconds / interval.as_secs_f64()).round() as u64;
    let sender = {
        let sent = sent.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(interval);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
            for seq in 1..=moves {
                tick.tick().await;
                let msg = json!({"type": "relight", "seq": seq, "request": request(seq)});
                sent.lock().unwrap().insert(seq, Instant::now());
                if tx.send(Message::text(msg.to_string())).await.is_err() {
                    break;
                }
            }
            tx
        })
    };
    let start = Instant::now();
    let mut latencies = Vec::new();
    let mut dropped = 0;
    // When the latest frame arrived, and its size.
    let mut last_frame: (Instant, usize);
    loop {
        let m = tokio::time::timeout(Duration::from_secs(30), rx.next())
            .await
            .expect("a message within 30 s")
            .expect("stream open")
            .expect("message");
        match m {
            Message::Binary(b) => {
                let seq = u64::from_le_bytes(b[4..12].try_into().expect("header"));
                last_frame = (Instant::now(), b.len());
                if let Some(t) = sent.lock().unwrap().get(&seq) {
                    latencies.push(t.elapsed().as_secs_f64() * 1e3);
                }
                if seq == moves {
                    break;
                }
            }
            Message::Text(t) => {
                let v: Value = serde_json::from_str(t.as_str()).expect("JSON");
                match v["type"].as_str() {
                    Some("stats") => dropped = v["dropped"].as_u64().unwrap_or(0),
                    Some("error") => eprintln!("error: {v}"),
                    _ => {}
                }
            }
            _ => {}
        }
    }
    let mut tx = sender.await.expect("sender");
    let _ = tx.close().await;
    let (last_at, frame_bytes) = last_frame;
    let elapsed = (last_at - start).as_secs_f64();
    let frames = latencies.len();
    latencies.sort_by(f64::total_cmp);
    println!(
        "| {format} | {:.0} | {moves} | {frames} | {dropped} | {:.1} | {:.1} | {:.1} | {:.1} | {frame_bytes} |",
        interval.as_secs_f64() * 1e3,
        frames as f64 / elapsed,
        percentile(&latencies, 0.5),
        percentile(&latencies, 0.99),
        latencies.last().copied().unwrap_or(f64::NAN),
    );
}

#[tokio::main]
async fn main() {
    let mut args = std::env::args().skip(1).peekable();
    let mut url = "http://127.0.0.1:8080".to_string();
    let mut scene = "cornell".to_string();
    let mut mode = None;
    let mut clients = vec![1usize, 8, 64];
    let mut seconds = 10.0;
    let mut interval = Duration::from_millis(16);
    let mut format = "f32".to_string();
    while let Some(a) = args.next() {
        let mut value = || args.next().unwrap_or_else(|| usage());
        match a.as_str() {
            "--url" => url = value(),
            "--scene" => scene = value(),
            "--clients" => {
                clients = value()
                    .split(',')
                    .map(|c| c.parse().unwrap_or_else(|_| usage()))
                    .collect()
            }
            "--seconds" => seconds = value().parse().unwrap_or_else(|_| usage()),
            "--interval-ms" => {
                interval = Duration::from_millis(value().parse().unwrap_or_else(|_| usage()))
            }
            "--format" => format = value(),
            "rest" | "drag" => mode = Some(a),
            _ => usage(),
        }
    }
    match mode.as_deref() {
        Some("rest") => {
            println!("| clients | requests | req/s | p50 ms | p90 ms | p99 ms | errors |");
            println!("| --- | --- | --- | --- | --- | --- | --- |");
            for c in clients {
                rest(&url, &scene, c, seconds).await;
            }
        }
        Some("drag") => {
            println!(
                "| format | move every ms | moves | frames | dropped | frames/s | p50 ms | p99 ms | max ms | frame bytes |"
            );
            println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
            drag(&url, &scene, seconds, interval, &format).await;
        }
        _ => usage(),
    }
}
