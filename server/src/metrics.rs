//! What `/metrics` reports, in the Prometheus text format (version 0.0.4), through the
//! `prometheus` crate (no default features: no protobuf, no process collector).
//!
//! | metric | type | labels |
//! | --- | --- | --- |
//! | `translux_http_request_duration_seconds` | histogram | `route` (the matched path template), `method`, `status` |
//! | `translux_relights_total` | counter | `outcome`: `ok`, `failed`, `rejected` (queue full), `deadline` (waited too long), `cancelled` (client gone) |
//! | `translux_queue_depth` | gauge | — relights waiting |
//! | `translux_queue_capacity`, `translux_workers` | gauge | — |
//! | `translux_relights_in_flight` | gauge | — relights being computed |
//! | `translux_queue_wait_seconds` | histogram | — time from accepted to computing |
//! | `translux_compute_seconds` | histogram | — one batch's compute time |
//! | `translux_batch_size` | histogram | — relights per batch |
//! | `translux_solver_iterations` | histogram | — per relight |
//! | `translux_gpu_submissions_total` | counter | — command submissions of relights with `stats.device` (done whole on the GPU, or S of their materials written there) |
//! | `translux_gpu_transfer_bytes_total` | counter | `direction`: `up` (host to device), `down` (read back), for those relights |
//! | `translux_ws_connections` | gauge | — open streams |
//! | `translux_ws_frames_total` | counter | `format` |
//! | `translux_ws_dropped_total` | counter | — stream requests superseded before computing |
//! | `translux_scenes` | gauge | `state`: `loading`, `ready`, `failed` |
//! | `translux_resident_memory_bytes`, `translux_mapped_bundle_bytes` | gauge | — |
//! | `translux_build_info` | gauge, always 1 | `version`, `bundle_format` (the bundle version this build reads) |
//!
//! Each [`AppState`](crate::AppState) has its own registry, so several servers in one process
//! (tests) count separately.

use prometheus::{
    Encoder, Histogram, HistogramOpts, HistogramVec, IntCounter, IntCounterVec, IntGauge,
    IntGaugeVec, Opts, Registry, TextEncoder,
};

/// The server's metrics.
#[derive(Debug, Clone)]
pub struct Metrics {
    registry: Registry,
    pub http_duration: HistogramVec,
    pub relights: IntCounterVec,
    pub queue_depth: IntGauge,
    pub queue_capacity: IntGauge,
    pub workers: IntGauge,
    pub in_flight: IntGauge,
    pub queue_wait: Histogram,
    pub compute: Histogram,
    pub batch_size: Histogram,
    pub iterations: Histogram,
    pub ws_connections: IntGauge,
    pub ws_frames: IntCounterVec,
    pub ws_dropped: IntCounter,
    pub scenes: IntGaugeVec,
    pub resident_bytes: IntGauge,
    pub mapped_bytes: IntGauge,
    /// GPU bytes held by the scenes (0 on the CPU backend).
    pub gpu_bytes: IntGauge,
    /// Submissions of the relights with `stats.device`.
    pub gpu_submissions: IntCounter,
    /// Bytes those relights moved, by `direction` (`up`, `down`).
    pub gpu_transfer: IntCounterVec,
    /// 1, labelled with what this build is (so dashboards can tell servers apart).
    pub build_info: IntGaugeVec,
}

/// Latency buckets in seconds: 0.5 ms to 60 s.
const SECONDS: &[f64] = &[
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
    60.0,
];

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    /// Counts a relight's stats: its solver iterations, and what it took on the GPU when
    /// the GPU did it whole.
    pub fn relit(&self, stats: &translux_proto::api::RelightStats) {
        self.iterations.observe(stats.iterations as f64);
        if let Some(d) = &stats.device {
            self.gpu_submissions.inc_by(d.submissions as u64);
            self.gpu_transfer
                .with_label_values(&["up"])
                .inc_by(d.bytes_up);
            self.gpu_transfer
                .with_label_values(&["down"])
                .inc_by(d.bytes_down);
        }
    }

    /// Registers every metric in a fresh registry.
    pub fn new() -> Metrics {
        let registry = Registry::new();
        // Registration fails only for duplicate or malformed names, fixed here: a bug.
        fn reg<T: prometheus::core::Collector + Clone + 'static>(r: &Registry, c: T) -> T {
            r.register(Box::new(c.clone()))
                .expect("metric names are unique and valid");
            c
        }
        let h = |name: &str, help: &str, buckets: &[f64]| {
            Histogram::with_opts(HistogramOpts::new(name, help).buckets(buckets.to_vec()))
                .expect("valid histogram")
        };
        let g = |name: &str, help: &str| IntGauge::new(name, help).expect("valid gauge");
        let m = Metrics {
            http_duration: reg(
                &registry,
                HistogramVec::new(
                    HistogramOpts::new(
                        "translux_http_request_duration_seconds",
                        "HTTP request latency by route template, method and status.",
                    )
                    .buckets(SECONDS.to_vec()),
                    &["route", "method", "status"],
                )
                .expect("valid histogram"),
            ),
            relights: reg(
                &registry,
                IntCounterVec::new(
                    Opts::new(
                        "translux_relights_total",
                        "Relights by outcome: ok, failed, rejected (queue full), deadline, cancelled.",
                    ),
                    &["outcome"],
                )
                .expect("valid counter"),
            ),
            queue_depth: reg(
                &registry,
                g("translux_queue_depth", "Relights waiting for a worker."),
            ),
            queue_capacity: reg(
                &registry,
                g(
                    "translux_queue_capacity",
                    "Most relights that may wait; more are answered 429.",
                ),
            ),
            workers: reg(
                &registry,
                g("translux_workers", "Relight worker threads."),
            ),
            in_flight: reg(
                &registry,
                g("translux_relights_in_flight", "Relights being computed."),
            ),
            queue_wait: reg(
                &registry,
                h(
                    "translux_queue_wait_seconds",
                    "Time a relight waited in the queue.",
                    SECONDS,
                ),
            ),
            compute: reg(
                &registry,
                h(
                    "translux_compute_seconds",
                    "Compute time of one batch of relights.",
                    SECONDS,
                ),
            ),
            batch_size: reg(
                &registry,
                h(
                    "translux_batch_size",
                    "Relights of one scene computed together.",
                    &[1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0],
                ),
            ),
            iterations: reg(
                &registry,
                h(
                    "translux_solver_iterations",
                    "Solver iterations per relight.",
                    &[0.0, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0],
                ),
            ),
            ws_connections: reg(
                &registry,
                g("translux_ws_connections", "Open WebSocket streams."),
            ),
            ws_frames: reg(
                &registry,
                IntCounterVec::new(
                    Opts::new(
                        "translux_ws_frames_total",
                        "Colour frames sent on WebSocket streams.",
                    ),
                    &["format"],
                )
                .expect("valid counter"),
            ),
            ws_dropped: reg(
                &registry,
                IntCounter::new(
                    "translux_ws_dropped_total",
                    "Stream relight requests superseded by a newer one before computing.",
                )
                .expect("valid counter"),
            ),
            scenes: reg(
                &registry,
                IntGaugeVec::new(
                    Opts::new("translux_scenes", "Scenes by state: loading, ready, failed."),
                    &["state"],
                )
                .expect("valid gauge"),
            ),
            resident_bytes: reg(
                &registry,
                g(
                    "translux_resident_memory_bytes",
                    "Resident set size of the server process.",
                ),
            ),
            mapped_bytes: reg(
                &registry,
                g(
                    "translux_mapped_bundle_bytes",
                    "Bytes of the bundles mapped by ready scenes.",
                ),
            ),
            gpu_bytes: reg(
                &registry,
                g(
                    "translux_gpu_bytes",
                    "GPU memory held by the scenes' matrices and vectors (0 on the CPU backend).",
                ),
            ),
            gpu_submissions: reg(
                &registry,
                IntCounter::new(
                    "translux_gpu_submissions_total",
                    "Command submissions of the relights done on the GPU (whole, or S of their materials written there).",
                )
                .expect("valid counter"),
            ),
            gpu_transfer: reg(
                &registry,
                IntCounterVec::new(
                    Opts::new(
                        "translux_gpu_transfer_bytes_total",
                        "Bytes the relights done on the GPU wrote (up) and read back (down).",
                    ),
                    &["direction"],
                )
                .expect("valid counter"),
            ),
            build_info: reg(
                &registry,
                IntGaugeVec::new(
                    Opts::new(
                        "translux_build_info",
                        "Always 1; the labels say which build answers.",
                    ),
                    &["version", "bundle_format"],
                )
                .expect("valid gauge"),
            ),
            registry,
        };
        m.build_info
            .with_label_values(&[
                env!("CARGO_PKG_VERSION"),
                &translux_proto::bundle::FORMAT_VERSION.to_string(),
            ])
            .set(1);
        m
    }

    /// Counts a relight's outcome.
    pub fn outcome(&self, outcome: &str, n: u64) {
        self.relights.with_label_values(&[outcome]).inc_by(n);
    }

    /// The text exposition of every metric.
    pub fn render(&self) -> Result<String, String> {
        let mut buf = Vec::new();
        TextEncoder::new()
            .encode(&self.registry.gather(), &mut buf)
            .map_err(|e| e.to_string())?;
        String::from_utf8(buf).map_err(|e| e.to_string())
    }
}

/// The process's resident set size in bytes (Linux: `VmRSS` of `/proc/self/status`);
/// `None` where that is not available.
pub fn resident_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line
        .trim_start_matches("VmRSS:")
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kb * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposition_has_every_family() {
        let m = Metrics::new();
        m.http_duration
            .with_label_values(&["/healthz", "GET", "200"])
            .observe(0.01);
        m.outcome("ok", 2);
        m.ws_frames.with_label_values(&["f32"]).inc();
        m.scenes.with_label_values(&["ready"]).set(1);
        let text = m.render().unwrap();
        for name in [
            "translux_http_request_duration_seconds_bucket{method=\"GET\",route=\"/healthz\",status=\"200\",le=\"0.025\"} 1",
            "translux_relights_total{outcome=\"ok\"} 2",
            "translux_queue_depth 0",
            "# TYPE translux_batch_size histogram",
            "translux_ws_frames_total{format=\"f32\"} 1",
        ] {
            assert!(text.contains(name), "{name} missing from\n{text}");
        }
    }

    #[test]
    fn resident_memory_is_read_on_linux() {
        if cfg!(target_os = "linux") {
            let rss = resident_bytes().unwrap();
            assert!(rss > 1 << 20, "{rss}");
        }
    }
}
