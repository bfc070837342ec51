//! # translux-server
//!
//! In: a folder of bundles written by `translux-precompute` (each sub-folder one bundle,
//! served under its folder name), memory-mapped and verified lazily; uploaded scenes become
//! bundles through precompute jobs. Out: an HTTP and WebSocket API (axum) that relights
//! them per request — lights in (point, spot, directional, environment, emitters), linear
//! per-vertex radiance B/π out — on the GPU through wgpu ([`gpu`], [`backend`]) or on the
//! CPU, with the transfer matrix T when the bundle has it, else the warm-started iterative
//! solve of B = Bₑ + S(E + F B); plus the scene metadata and mesh a client needs, the viewer
//! at `/`, `/healthz`, `/metrics` and the OpenAPI document.
//!
//! | part | modules |
//! | --- | --- |
//! | routes and bodies | [`routes`] (REST; the full list is `docs/api.md` and the generated OpenAPI document, [`openapi`], [`schema`]), [`ws`] (the stream, `docs/stream.md`), [`extract`] (strict JSON bodies, `Accept` negotiation), [`error`] (every failure as `{"error":{"code","message"}}`) |
//! | what it holds | [`state`] (one opened scene per bundle, the pool, the metrics, the shutdown signal), [`config`] (settings from flags, `TRANSLUX_*`, a TOML file) |
//! | a relight | planned and run by the engine: [`translux_engine::relight`] (plan, then run or run a batch), [`translux_engine::environment`] (environment lights) |
//! | sharing one box | [`pool`] (bounded worker pool, fair queue, batching, deadlines), [`metrics`], [`budget`] (memory budget, LRU eviction), [`prepare`] (translucency changes made ready in the background) |
//! | team use | [`team`] (the API wrapped with access control, uploads, jobs, deletion, the budget), [`auth`] (tokens, roles, rate limits), [`upload`] and [`jobs`] (scene uploads in, precompute and resimulation jobs out), [`slurm`] (jobs run on Slurm: `--jobs slurm`) |
//! | backends | [`backend`] (CPU or GPU, chosen at start-up), [`gpu`] (wgpu kernels, one WGSL file each) |
//!
//! The same binary works offline, without HTTP: `translux-server render | export | relight
//! --bundle DIR [--request REQ.json] --out FILE` writes a PNG, a `.glb`/`.ply` with baked
//! colours, or the per-vertex radiance ([`cli`], [`offline`]).
//!
//! Request and answer bodies are the types of [`translux_proto::api`]. Every error is
//! `{"error":{"code","message"}}` with a 4xx/5xx status ([`AppError`]); bad input never
//! panics and never answers 500.
//!
//! ```no_run
//! # async fn demo() -> std::io::Result<()> {
//! let (state, errors) = translux_server::load_bundles(std::path::Path::new("bundles"));
//! for (id, e) in errors {
//!     eprintln!("skipped {id}: {e}");
//! }
//! let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
//! translux_server::serve(listener, state, std::future::pending()).await
//! # }
//! ```

pub mod auth;
pub mod backend;
pub mod budget;
pub mod cli;
pub mod config;
pub mod error;
pub mod extract;
pub mod gpu;
pub mod jobs;
pub mod metrics;
pub mod offline;
pub mod openapi;
pub mod pool;
pub mod prepare;
pub mod routes;
pub mod schema;
pub mod slurm;
pub mod state;
pub mod team;
pub mod upload;
pub mod ws;

use std::future::Future;

pub use config::ServerParams;
pub use error::AppError;
pub use routes::router;
pub use state::{AppState, Scene, SceneState, load_bundles, load_bundles_with};

/// Serves the API for `state` on `listener` until `shutdown` completes, then shuts down
/// gracefully: stops accepting connections, lets every request in flight finish (their
/// queued relights are computed; lamp walks stop and are answered 503 `cancelled`), closes
/// WebSocket streams once their work is done (1001),
/// and stops the worker pool after it has answered every job it accepted.
pub async fn serve(
    listener: tokio::net::TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let app = router(state.clone());
    serve_router(listener, state, app, shutdown).await
}

/// How long a client may take to send a request's head; a connection that sends half a
/// header and stops is closed after this (hyper's header-read timeout).
pub const HEADER_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(15);
/// The longest pause allowed between two pieces of a request body (an upload that stalls
/// is answered 408 and closed, instead of holding a connection forever).
pub const BODY_IDLE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);
/// After shutdown begins, requests in flight get this long to finish; connections still
/// open then are closed, so a stop always ends.
pub const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(20);

/// [`serve`] with a router built on `state` by the caller (the team routes of
/// [`team::app`] around [`router`]).
///
/// The accept loop is written here rather than with `axum::serve`, which offers no
/// header-read timeout: HTTP/1.1 connections (with upgrades, for WebSockets) from hyper's
/// own builder with [`HEADER_TIMEOUT`], the body idle timeout of `tower-http`, a write
/// timeout ([`ServerParams::write_timeout`], `tokio-io-timeout`), and a graceful stop
/// bounded by [`SHUTDOWN_GRACE`].
pub async fn serve_router(
    listener: tokio::net::TcpListener,
    state: AppState,
    app: axum::Router,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    use axum::extract::ConnectInfo;
    use hyper_util::rt::{TokioIo, TokioTimer};
    use tower::ServiceExt;

    let app = routes::with_request_log(app, state.clone()).layer(
        tower_http::timeout::RequestBodyTimeoutLayer::new(BODY_IDLE_TIMEOUT),
    );
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut connections = tokio::task::JoinSet::new();
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        tokio::select! {
            () = &mut shutdown => break,
            Some(_) = connections.join_next(), if !connections.is_empty() => {}
            accepted = listener.accept() => {
                let (stream, addr) = match accepted {
                    Ok(x) => x,
                    Err(e) => {
                        // Out of file descriptors and the like: wait a little, keep serving.
                        tracing::warn!("accepting a connection failed: {e}");
                        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                        continue;
                    }
                };
                let _ = stream.set_nodelay(true);
                // A write that makes no progress for this long fails, and hyper drops the
                // connection with the answer it held.
                let mut stream = tokio_io_timeout::TimeoutStream::new(stream);
                stream.set_write_timeout(Some(state.params().write_timeout));
                let stream = Box::pin(stream);
                let app = app.clone();
                let mut stop = stop_rx.clone();
                connections.spawn(async move {
                    let service = hyper::service::service_fn(
                        move |mut req: hyper::Request<hyper::body::Incoming>| {
                            req.extensions_mut().insert(ConnectInfo(addr));
                            app.clone().oneshot(req.map(axum::body::Body::new))
                        },
                    );
                    let mut builder = hyper::server::conn::http1::Builder::new();
                    builder.timer(TokioTimer::new()).header_read_timeout(HEADER_TIMEOUT);
                    let conn = builder
                        .serve_connection(TokioIo::new(stream), service)
                        .with_upgrades();
                    let mut conn = std::pin::pin!(conn);
                    let mut stopping = false;
                    loop {
                        tokio::select! {
                            result = conn.as_mut() => {
                                if let Err(e) = result {
                                    tracing::debug!("connection from {addr}: {e}");
                                }
                                break;
                            }
                            changed = stop.wait_for(|s| *s), if !stopping => {
                                stopping = true;
                                if changed.is_ok() {
                                    conn.as_mut().graceful_shutdown();
                                }
                            }
                        }
                    }
                });
            }
        }
    }
    drop(listener);
    state.begin_shutdown();
    state.pool().stop_long_work();
    let _ = stop_tx.send(true);
    let drained = tokio::time::timeout(SHUTDOWN_GRACE, async {
        while connections.join_next().await.is_some() {}
    })
    .await;
    if drained.is_err() {
        tracing::warn!(
            "{} connections still open {} s after the stop began; closing them",
            connections.len(),
            SHUTDOWN_GRACE.as_secs()
        );
        connections.abort_all();
    }
    let pool = state.pool().clone();
    let _ = tokio::task::spawn_blocking(move || pool.join()).await;
    Ok(())
}

/// `GET /api/v1/openapi.json`: this document, OpenAPI 3.1, generated from the server's
/// routes and body types ([`openapi`]). It sits at the crate root because the document
/// names every route, this one included: the routes' module lists it, and the document's
/// module lists the routes.
#[utoipa::path(
    get,
    path = "/api/v1/openapi.json",
    tag = "operations",
    responses((status = 200, description = "The OpenAPI document.", body = Object))
)]
pub(crate) async fn openapi_document() -> axum::response::Response {
    use axum::response::IntoResponse;
    (
        [(
            axum::http::header::CONTENT_TYPE,
            axum::http::HeaderValue::from_static("application/json"),
        )],
        openapi::json(),
    )
        .into_response()
}
