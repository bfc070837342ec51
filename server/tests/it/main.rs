//! translux-server's integration tests, one binary with a module per subject: `balancer`
//! (two servers behind haproxy running docker/haproxy.cfg), `k8s` (docker/k8s's manifests
//! against the Kubernetes schemas), `cli` (the
//! binary's offline commands and flags), `deploy` (the container set-up), `gpu` (every
//! kernel against its CPU twin, on lavapipe here), `gpu_direct` (the device BVH's shadow
//! rays and direct light against the engine's `Occluder` and `direct_irradiance`), `gpu_relight` (the
//! whole relight on the device: its colour kernel, its answers against the CPU backend, one
//! submission and the bytes it moves), `gpu_sterms` (a translucency change's rows of S written
//! on the device against the CPU's rewrite), `prepare` (translucency preparation in
//! the binary), `shared_folder` (several servers over one bundles folder), `shutdown` (SIGTERM with queued
//! relights), `slurm` (precompute jobs on a munged, slurmctld and slurmd the test starts), `team_cluster` (an upload
//! through haproxy run as a Slurm array and merge: the same bytes as one box, served by both
//! servers), `transport` (the relight through the server's code, no sockets) and `ws` (the WebSocket
//! loop driven through channels); `support` holds the shared fixtures.
//!
//! Run one subject with `cargo test -p translux-server --test it gpu::`. One binary links
//! the server, wgpu and their dependencies once instead of once per file.

mod balancer;
mod cli;
mod deploy;
mod gpu;
mod gpu_direct;
mod gpu_relight;
mod gpu_sterms;
mod k8s;
mod prepare;
mod shared_folder;
mod shutdown;
mod slurm;
mod support;
mod team_cluster;
mod transport;
mod ws;
