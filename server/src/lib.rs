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
//! | routes and bodies | [`routes`] (REST; the full list is `openapi.json` and `docs/api.md`), [`ws`] (the stream, `docs/stream.md`) |
//! | a relight | [`relight`] (plan, then run or run a batch), [`environment`] (environment lights) |
//! | sharing one box | [`pool`] (bounded worker pool, fair queue, batching, deadlines), [`metrics`], [`budget`] (memory budget, LRU eviction) |
//! | team use | [`auth`] (tokens, roles, rate limits), [`upload`] and [`jobs`] (scene uploads, precompute jobs) |
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
pub mod environment;
pub mod error;
pub mod extract;
pub mod gpu;
pub mod jobs;
pub mod metrics;
pub mod offline;
pub mod picture;
pub mod pool;
pub mod relight;
pub mod routes;
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
/// queued relights are computed), closes WebSocket streams once their work is done (1001),
/// and stops the worker pool after it has answered every job it accepted.
pub async fn serve(
    listener: tokio::net::TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let app = router(state.clone());
    serve_router(listener, state, app, shutdown).await
}

/// [`serve`] with a router built on `state` by the caller (the team routes of
/// [`team::app`] around [`router`]).
pub async fn serve_router(
    listener: tokio::net::TcpListener,
    state: AppState,
    app: axum::Router,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let signal_state = state.clone();
    let result = axum::serve(
        listener,
        app.into_make_service_with_connect_info::<std::net::SocketAddr>(),
    )
    .with_graceful_shutdown(async move {
        shutdown.await;
        signal_state.begin_shutdown();
    })
    .await;
    let pool = state.pool().clone();
    let _ = tokio::task::spawn_blocking(move || pool.join()).await;
    result
}
