//! translux-server's integration tests, one binary with a module per subject: `cli` (the
//! binary's offline commands and flags), `deploy` (the container set-up), `gpu` (every
//! kernel against its CPU twin, on lavapipe here), `prepare` (translucency preparation in
//! the binary), `shutdown` (SIGTERM with queued
//! relights), `transport` (the relight through the server's code, no sockets) and `ws` (the WebSocket
//! loop driven through channels); `support` holds the shared fixtures.
//!
//! Run one subject with `cargo test -p translux-server --test it gpu::`. One binary links
//! the server, wgpu and their dependencies once instead of once per file.

mod cli;
mod deploy;
mod gpu;
mod prepare;
mod shutdown;
mod support;
mod transport;
mod ws;
