//! End-to-end tests of the whole system, one binary with a module per subject: `server`
//! (REST), `stream` (the WebSocket), `sharing` (the worker pool, health, metrics), `team`
//! (tokens, uploads, jobs, logs), `environment` (environment lights), `browser` (the viewer
//! in chromium), `validation` (against Mitsuba 3 and closed forms) and `vertices` (direct
//! light at the viewer's vertices). `support` holds the fixtures the server-facing modules
//! share.
//!
//! Run one subject with `cargo test -p translux-tests --test it validation::`. One binary
//! links the server, wgpu and the precompute once instead of once per file.

mod browser;
mod environment;
mod python_client;
mod server;
mod sharing;
mod stream;
mod support;
mod team;
mod validation;
mod vertices;
