//! # translux-server
//!
//! In: a folder of bundles written by `translux-precompute` (each sub-folder one bundle,
//! served under its folder name), opened and memory-mapped once at start-up. Out: an HTTP
//! API (axum) that relights them per request — lights in, linear per-vertex radiance B/π
//! out — plus the scene metadata and viewer mesh a client needs to show it, and the viewer
//! page at `/`. This version relights on the CPU (shadowed direct light from point, spot and
//! directional lights, then the diffuse solve B = Bₑ + ρ(E + F B)).
//!
//! | route | answer |
//! | --- | --- |
//! | `GET /` | the viewer page (`web/index.html`) |
//! | `GET /healthz` | status, backend, GPU availability, scene ids |
//! | `GET /api/v1/scenes` | `{"scenes":[{"id","name","patches","vertices","objects"}]}` |
//! | `GET /api/v1/scenes/{id}` | counts, objects and materials, default lights, camera, F info |
//! | `GET /api/v1/scenes/{id}/mesh` | flat `positions`, `normals`, `indices`, object ranges |
//! | `POST /api/v1/scenes/{id}/relight` | JSON (`Accept: application/json`) or n×3 LE `f32` |
//! | `POST /api/v1/scenes/{id}/render` | `image/png`: the relit scene from a camera ([`picture`]) |
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

pub mod cli;
pub mod error;
pub mod extract;
pub mod offline;
pub mod picture;
pub mod relight;
pub mod routes;
pub mod state;

use std::future::Future;

pub use error::AppError;
pub use routes::router;
pub use state::{AppState, Scene, load_bundles};

/// Serves the API for `state` on `listener` until `shutdown` completes, then lets requests in
/// flight finish (graceful shutdown).
pub async fn serve(
    listener: tokio::net::TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    axum::serve(listener, router(state))
        .with_graceful_shutdown(shutdown)
        .await
}
