//! The WebSocket loop (`translux_server::ws::run_stream`) driven through channels, no
//! socket: the client side is a pair of tokio channels, so the test sees every message the
//! loop sends, in order, and controls time (pings) and shutdown exactly.

use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::extract::ws::{Message, close_code};
use futures_util::{Sink, Stream};
use serde_json::{Value, json};
use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender, unbounded_channel};
use translux_engine::relight;
use translux_proto::api::RelightRequest;
use translux_server::state::Scene;
use translux_server::ws::{FrameSettings, HEADER_LEN, MAGIC, run_stream};
use translux_server::{AppState, ServerParams};

use crate::support::bundle_dir;

/// The server's end of a channel "socket".
struct ChannelSocket {
    from_client: UnboundedReceiver<Message>,
    to_client: UnboundedSender<Message>,
}

impl Stream for ChannelSocket {
    type Item = Result<Message, axum::Error>;
    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        self.from_client.poll_recv(cx).map(|m| m.map(Ok))
    }
}

impl Sink<Message> for ChannelSocket {
    type Error = axum::Error;
    fn poll_ready(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Ready(Ok(()))
    }
    fn start_send(self: Pin<&mut Self>, m: Message) -> Result<(), Self::Error> {
        self.to_client
            .send(m)
            .map_err(|_| axum::Error::new("the test client is gone"))
    }
    fn poll_flush(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Ready(Ok(()))
    }
    fn poll_close(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Ready(Ok(()))
    }
}

/// The client's end, with the loop running on a task.
struct Client {
    send: UnboundedSender<Message>,
    recv: UnboundedReceiver<Message>,
    state: AppState,
    scene: Arc<Scene>,
    task: tokio::task::JoinHandle<()>,
}

impl Client {
    fn start(params: ServerParams) -> Client {
        let scene = Arc::new(Scene::open("cornell", bundle_dir()).expect("bundle opens"));
        let state = AppState::with_params(params);
        let (send, from_client) = unbounded_channel();
        let (to_client, recv) = unbounded_channel();
        let socket = ChannelSocket {
            from_client,
            to_client,
        };
        let task = tokio::spawn(run_stream(
            socket,
            state.clone(),
            scene.clone(),
            FrameSettings::default(),
            state.params().viewer_work,
        ));
        Client {
            send,
            recv,
            state,
            scene,
            task,
        }
    }

    fn text(&self, v: Value) {
        self.send.send(Message::Text(v.to_string().into())).unwrap();
    }

    /// The next message that is not a ping (pings are answered by nobody here: the tests
    /// that need pings answered finish well within the ping interval).
    async fn next(&mut self) -> Message {
        loop {
            let m = tokio::time::timeout(Duration::from_secs(60), self.recv.recv())
                .await
                .expect("the loop said nothing for 60 s")
                .expect("the loop ended without a close message");
            if !matches!(m, Message::Ping(_)) {
                return m;
            }
        }
    }

    async fn json(&mut self) -> Value {
        match self.next().await {
            Message::Text(t) => serde_json::from_str(t.as_str()).unwrap(),
            other => panic!("expected text, got {other:?}"),
        }
    }

    async fn frame(&mut self) -> Vec<u8> {
        match self.next().await {
            Message::Binary(b) => b.to_vec(),
            other => panic!("expected a frame, got {other:?}"),
        }
    }

    /// The close message, then the loop's end.
    async fn closed(mut self) -> (u16, String) {
        let close = match self.next().await {
            Message::Close(Some(c)) => (c.code, c.reason.to_string()),
            other => panic!("expected a close frame, got {other:?}"),
        };
        tokio::time::timeout(Duration::from_secs(10), self.task)
            .await
            .expect("the loop ends after closing")
            .unwrap();
        close
    }
}

const LIGHT: &str =
    r#"{"lights":[{"type":"point","position":[0.1,0.4,0.1],"intensity":[1,0.5,0.2]}]}"#;

fn relight_message(seq: u64) -> Value {
    json!({"type": "relight", "seq": seq, "request": serde_json::from_str::<Value>(LIGHT).unwrap()})
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_relight_goes_through_the_loop_as_a_frame_and_its_stats() {
    let mut c = Client::start(ServerParams::default());
    let ready = c.json().await;
    let vertices = c.scene.bundle.vertex_positions().len();
    assert_eq!(ready["type"], "ready", "{ready}");
    assert_eq!(ready["vertex_count"], vertices as u64, "{ready}");
    assert_eq!(ready["format"], "f32", "{ready}");

    c.text(relight_message(5));
    let frame = c.frame().await;
    assert_eq!(&frame[..4], MAGIC);
    assert_eq!(u64::from_le_bytes(frame[4..12].try_into().unwrap()), 5);
    assert_eq!(frame[12], 0, "f32 frame");
    assert_eq!(frame.len(), HEADER_LEN + vertices * 12);
    // The colours are the library's relight of the same request, to the solver's tolerance.
    let req: RelightRequest = serde_json::from_str(LIGHT).unwrap();
    let want = relight::run(&c.scene, &relight::plan(&c.scene, req).unwrap()).unwrap();
    let got: Vec<f32> = frame[HEADER_LEN..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    let want: Vec<f32> = want.radiance.iter().flatten().copied().collect();
    let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(scale > 0.0);
    for (g, w) in got.iter().zip(&want) {
        assert!((g - w).abs() <= 1e-2 * scale, "{g} against {w}");
    }
    let stats = c.json().await;
    assert_eq!(stats["type"], "stats", "{stats}");
    assert_eq!(stats["seq"], 5, "{stats}");
    assert_eq!(stats["dropped"], 0, "{stats}");

    // A config message changes the next frame's encoding.
    c.text(json!({"type": "config", "format": "srgb8"}));
    c.text(relight_message(6));
    let frame = c.frame().await;
    assert_eq!(frame[12], 2, "srgb8 frame");
    assert_eq!(frame.len(), HEADER_LEN + vertices * 3);
    assert_eq!(c.json().await["seq"], 6);

    // A request the planner refuses is answered as an error and the stream stays open.
    c.text(json!({"type": "relight", "seq": 7, "request": {"lights": [
        {"type": "point", "position": [0, 0.4, 0], "intensity": [-1, 1, 1]}]}}));
    let error = c.json().await;
    assert_eq!(
        (error["type"].as_str(), error["seq"].as_u64()),
        (Some("error"), Some(7)),
        "{error}"
    );

    // Binary messages are not part of the protocol: closed with 1003 and a reason.
    c.send.send(Message::Binary(vec![1, 2, 3].into())).unwrap();
    let (code, reason) = c.closed().await;
    assert_eq!(code, close_code::UNSUPPORTED);
    assert!(reason.contains("binary"), "{reason}");
}

/// Time is paused: the runtime jumps to each ping, so four unanswered intervals pass at once.
#[tokio::test(start_paused = true)]
async fn a_client_that_never_answers_pings_is_closed() {
    let params = ServerParams {
        ping_interval: Duration::from_secs(5),
        ..Default::default()
    };
    let mut c = Client::start(params);
    assert_eq!(c.json().await["type"], "ready");
    let mut pings = 0;
    let close = loop {
        match c.recv.recv().await.expect("a message") {
            Message::Ping(_) => pings += 1,
            Message::Close(Some(f)) => break (f.code, f.reason.to_string()),
            other => panic!("unexpected {other:?}"),
        }
    };
    assert!(pings >= 4, "{pings} pings before closing");
    assert_eq!(close.0, close_code::AWAY);
    assert!(close.1.contains("no answer to pings"), "{}", close.1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_closes_the_stream_with_going_away() {
    let mut c = Client::start(ServerParams::default());
    assert_eq!(c.json().await["type"], "ready");
    c.text(relight_message(1));
    c.frame().await;
    assert_eq!(c.json().await["type"], "stats");
    c.state.begin_shutdown();
    let (code, reason) = c.closed().await;
    assert_eq!(code, close_code::AWAY);
    assert!(reason.contains("shutting down"), "{reason}");
}
