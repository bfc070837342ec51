//! GPU vs CPU backend on `builtin:cornell_paper`: what the transport costs per relight.
//!
//! Measures, per backend (the CPU, then the wgpu adapter), the paper's Table 1 columns:
//! relight with the transfer matrix T (one relight, batches of 8 and 64: one pass over T per
//! batch), relight with the iterative solver, and a translucency change (S written where
//! the backend solves: on the device with the GPU backend, from its radial terms; on the
//! CPU with the CPU backend); the product over T
//! alone with its achieved bandwidth against a measured copy bandwidth of the same device
//! (for the CPU: a memcpy).
//! Whole-relight times include the shadowed direct light: on the CPU backend on the CPU; on
//! the GPU backend a relight with the solver and the bundle's materials is done whole on the
//! device (direct light, solve, colours: one submission), and the rows say how many
//! submissions and bytes it took, and the viewer's relight (`direct_at: pixel`) beside it.
//! A last row runs 64 clients at once, each dragging its own
//! light, their relights batched as the server's worker pool batches concurrent requests,
//! and gives the relights per second of all of them together.
//!
//! ```sh
//! cargo run --release -p translux-server --example gpu_bench -- --patches 3000
//! cargo run --release -p translux-server --example gpu_bench -- --patches 24640 --no-t
//! ```
//!
//! The bundle (with `--inverse`, unless `--no-t`: T of 24,640 patches is a 44-minute LU) is
//! precomputed once into `target/gpu-bench/cornell-N` (`cornell-N-no-t`); without T the
//! rows that use it are left out.
//! Software adapters (lavapipe) are CPUs: their numbers measure correctness plumbing, not a
//! GPU.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use translux_engine::backend::Backend as _;
use translux_engine::inverse;
use translux_engine::relight;
use translux_engine::scene::Scene;
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;
use translux_proto::bundle::Bundle;
use translux_server::backend::Backend;
use translux_server::gpu::{DenseData, GpuContext, GpuDense, GpuOptions};

struct Args {
    patches: u64,
    reps: usize,
    gpu: bool,
    /// Precompute and measure without T.
    no_t: bool,
}

fn args() -> anyhow::Result<Args> {
    let mut a = Args {
        patches: 24_640,
        reps: 5,
        gpu: true,
        no_t: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        match flag.as_str() {
            "--patches" => a.patches = it.next().context("--patches N")?.parse()?,
            "--reps" => a.reps = it.next().context("--reps N")?.parse()?,
            "--cpu-only" => a.gpu = false,
            "--no-t" => a.no_t = true,
            other => {
                bail!("unknown argument {other:?} (--patches N, --reps N, --cpu-only, --no-t)")
            }
        }
    }
    Ok(a)
}

/// Median milliseconds of `reps` runs of `f` (after one warm-up run).
fn time_ms(reps: usize, mut f: impl FnMut(usize)) -> f64 {
    f(usize::MAX);
    let mut t: Vec<f64> = (0..reps.max(1))
        .map(|r| {
            let s = Instant::now();
            f(r);
            s.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

/// A relight request: one point light moved by `r`, a solver, optional marble scale.
fn body(r: usize, solver: &str, marble: Option<f32>) -> String {
    let x = -0.2 + 0.05 * (r % 9) as f32;
    let mat = marble.map_or(String::new(), |s| {
        format!(
            r#","materials":{{"tall_block":{{"type":"translucent","profile":{{"type":"dipole","preset":"marble","scale":{s}}}}}}}"#
        )
    });
    format!(
        r#"{{"solver":"{solver}","lights":[{{"type":"point","position":[{x},0.5,0.1],"intensity":[1,1,1]}}]{mat}}}"#
    )
}

struct Row {
    what: String,
    ms: f64,
    note: String,
}

/// The whole-relight rows for the installed backend.
fn relight_rows(scene: &Scene, reps: usize) -> anyhow::Result<Vec<Row>> {
    let mut rows = Vec::new();
    let plan = |b: &str| -> anyhow::Result<relight::RelightPlan> {
        relight::plan(scene, serde_json::from_str(b)?).map_err(|e| anyhow::anyhow!("{e:?}"))
    };
    let batches: &[usize] = if scene.bundle.transfer().is_some() {
        &[1, 8, 64]
    } else {
        &[]
    };
    for &k in batches {
        let plans: Vec<_> = (0..k)
            .map(|i| plan(&body(i, "inverse", None)))
            .collect::<anyhow::Result<_>>()?;
        let mut solve_ms = 0.0;
        let ms = time_ms(reps, |_| {
            let out = relight::run_batch(scene, &plans);
            solve_ms = out[0].as_ref().map_or(f64::NAN, |o| o.stats.solve_ms);
        });
        rows.push(Row {
            what: format!("relight with T, batch of {k}"),
            ms,
            note: format!(
                "{:.2} ms per relight; transport {solve_ms:.2} ms per batch",
                ms / k as f64
            ),
        });
    }
    for (what, extra) in [
        ("relight with the solver (light moved, warm start)", ""),
        (
            "the viewer's relight (direct_at pixel: the exposure's luminances come back too)",
            r#","direct_at":"pixel""#,
        ),
    ] {
        let mut stats = String::new();
        let ms = time_ms(reps, |r| {
            let b = body(r.min(1000), "iterative", None);
            let b = format!("{}{extra}}}", &b[..b.len() - 1]);
            let p = plan(&b).expect("valid request");
            stats = match relight::run(scene, &p) {
                Ok(o) => solve_note(&o.stats),
                Err(e) => format!("failed: {e:?}"),
            };
        });
        rows.push(Row {
            what: what.into(),
            ms,
            note: stats,
        });
    }
    rows.push(clients(scene, 64, reps)?);
    let mut stats = String::new();
    let ms = time_ms(reps, |r| {
        // A new marble scale each time (a slider moving within ±25%): S is rewritten, never
        // taken from the cache.
        let scale = 0.75 + 0.5 * ((r.min(1000) as f32 * 0.618_034).fract());
        let p = plan(&body(0, "iterative", Some(scale))).expect("valid request");
        match relight::run(scene, &p) {
            Ok(o) => {
                let device = o.stats.device.map_or(String::new(), |d| {
                    format!(
                        "; {} submissions, {} B up, {} B down",
                        d.submissions, d.bytes_up, d.bytes_down
                    )
                });
                stats = format!(
                    "S written {:.1} ms (on the {}), solve {:.1} ms ({} {} it.){device}",
                    o.stats.materials_ms,
                    o.stats.materials_on.as_deref().unwrap_or("?"),
                    o.stats.solve_ms,
                    o.stats.solver,
                    o.stats.iterations
                )
            }
            Err(e) => stats = format!("failed: {e:?}"),
        }
    });
    rows.push(Row {
        what: "translucency change (S written, then solved)".into(),
        ms,
        note: stats,
    });
    Ok(rows)
}

/// A relight's solver, iterations, residual and where it ran.
fn solve_note(s: &translux_proto::api::RelightStats) -> String {
    let device = s.device.map_or("the engine's stages".into(), |d| {
        format!(
            "whole on the device: {} submission(s), {} B up, {} B down",
            d.submissions, d.bytes_up, d.bytes_down
        )
    });
    format!(
        "{} {} it., residual {:.1e}, solve {:.1} ms; {device}",
        s.solver, s.iterations, s.residual, s.solve_ms
    )
}

/// `k` clients at once, each dragging its own light `reps` × 10 steps, their concurrent
/// relights batched as the server's worker pool batches them (one `run_batch` of k a
/// step): the wall time per relight of all of them together (1000 / ms is the aggregate
/// relights per second).
fn clients(scene: &Scene, k: usize, reps: usize) -> anyhow::Result<Row> {
    let steps = 10 * reps.max(1);
    let plans: Vec<Vec<relight::RelightPlan>> = (0..steps)
        .map(|r| {
            (0..k)
                .map(|c| {
                    relight::plan(
                        scene,
                        serde_json::from_str(&body(c + r, "iterative", None))?,
                    )
                    .map_err(|e| anyhow::anyhow!("{e:?}"))
                })
                .collect()
        })
        .collect::<anyhow::Result<_>>()?;
    let mut note = String::new();
    let t = Instant::now();
    for step in &plans {
        let out = relight::run_batch(scene, step);
        if let Some(Ok(o)) = out.first() {
            note = solve_note(&o.stats);
        }
    }
    let ms = t.elapsed().as_secs_f64() * 1e3 / (k * steps) as f64;
    Ok(Row {
        what: format!("{k} clients at once, each dragging a light (batches of {k})"),
        ms,
        note: format!(
            "{:.0} relights/s in all; the last batch's first: {note}",
            1e3 / ms
        ),
    })
}

fn print(title: &str, rows: &[Row]) {
    println!("\n### {title}\n");
    println!("| measurement | ms | notes |");
    println!("| --- | ---: | --- |");
    for r in rows {
        println!("| {} | {:.2} | {} |", r.what, r.ms, r.note);
    }
}

fn main() -> anyhow::Result<()> {
    let a = args()?;
    let dir = bundle(&a)?;
    let scene = Scene::open("cornell", &dir)?;
    let b = &scene.bundle;
    let n = b.patch_areas().len();
    let t_bytes = b.transfer().map_or(0, |t| (t.bits.len() * 2) as u64);
    println!(
        "# GPU benchmark: builtin:cornell_paper, {n} patches, {} vertices",
        b.vertex_positions().len()
    );
    println!(
        "\nnnz(F) {}, nnz(S) {}, T (f16 RGB) {:.1} MiB; CPU threads {}",
        b.form_factors().nnz(),
        b.subsurface().nnz(),
        t_bytes as f64 / (1 << 20) as f64,
        rayon::current_num_threads()
    );
    let mut product_rows = cpu_product_rows(b, a.reps);
    let cpu_rows = relight_rows(&scene, a.reps)?;
    print("CPU backend (rayon)", &cpu_rows);
    if a.gpu {
        gpu_rows(&dir, b, a.reps, &mut product_rows)?;
    }
    if !product_rows.is_empty() {
        print("The product over T alone (R = T − S, f16)", &product_rows);
    }
    Ok(())
}

/// The bundle's folder, precomputed on first use.
fn bundle(a: &Args) -> anyhow::Result<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../target/gpu-bench")
        .join(format!(
            "cornell-{}{}",
            a.patches,
            if a.no_t { "-no-t" } else { "" }
        ));
    if Bundle::open(&dir).map_or(true, |b| b.transfer().is_none() && !a.no_t) {
        eprintln!(
            "precomputing builtin:cornell_paper at {} patches into {}",
            a.patches,
            dir.display()
        );
        let params = PrecomputeParams {
            patches: Some(a.patches),
            inverse: !a.no_t,
            progress: true,
            ..Default::default()
        };
        precompute(&load_scene("builtin:cornell_paper")?, &dir, &params)?;
    }
    Ok(dir)
}

/// The product over T alone on the CPU (the precompute's own kernel), with a memcpy's
/// bandwidth beside it; none without T.
fn cpu_product_rows(b: &Bundle, reps: usize) -> Vec<Row> {
    let Some(t) = b.transfer() else {
        return Vec::new();
    };
    let n = t.n;
    let t_bytes = (t.bits.len() * 2) as f64;
    let host_bw = {
        let src = vec![1u8; 256 << 20];
        let mut dst = vec![0u8; 256 << 20];
        let ms = time_ms(3, |_| dst.copy_from_slice(&src));
        2.0 * src.len() as f64 / (ms * 1e-3) / 1e9
    };
    [1usize, 8, 64]
        .into_iter()
        .map(|k| {
            let v: Vec<f32> = (0..n * 3 * k).map(|i| (i % 7) as f32 * 0.1 + 0.1).collect();
            let mut y = vec![0.0f32; n * 3 * k];
            let ms = time_ms(reps, |_| {
                inverse::apply_stored(t.bits, t.scale, n, &v, k, &mut y)
            });
            Row {
                what: format!("CPU: R·X over T, k = {k}"),
                ms,
                note: format!(
                    "{:.2} GB/s of T (memcpy: {host_bw:.1} GB/s)",
                    t_bytes / (ms * 1e-3) / 1e9
                ),
            }
        })
        .collect()
}

/// The GPU backend's rows (printed), and its product over T alone into `product_rows`.
fn gpu_rows(
    dir: &std::path::Path,
    b: &Bundle,
    reps: usize,
    product_rows: &mut Vec<Row>,
) -> anyhow::Result<()> {
    let ctx = GpuContext::new(&GpuOptions {
        allow_software: true,
        ..Default::default()
    })?;
    let ad = ctx.adapter().clone();
    let bw = ctx.copy_bandwidth(256 << 20, 5)?;
    let mut upload_ms = 0.0;
    if let Some(t) = b.transfer() {
        let n = t.n;
        let t_bytes = (t.bits.len() * 2) as f64;
        let t0 = Instant::now();
        let dense = GpuDense::upload(&ctx, "T", n, n, DenseData::F16(t.bits), Some(t.scale))?;
        upload_ms = t0.elapsed().as_secs_f64() * 1e3;
        for k in [1usize, 8, 64] {
            let v: Vec<f32> = (0..n * 3 * k).map(|i| (i % 7) as f32 * 0.1 + 0.1).collect();
            let mut y = vec![0.0f32; n * 3 * k];
            let ms = time_ms(reps, |_| {
                dense
                    .multiply_interleaved(&ctx, &v, k, &mut y)
                    .expect("GPU product")
            });
            product_rows.push(Row {
                what: format!("GPU: R·X over T, k = {k} (upload and read-back included)"),
                ms,
                note: format!(
                    "{:.2} GB/s of T (device copy: {bw:.1} GB/s); {} blocks",
                    t_bytes / (ms * 1e-3) / 1e9,
                    dense.blocks()
                ),
            });
        }
    }
    let gpu = Backend::on_gpu(ctx);
    // A fresh scene on the GPU backend: no warm starts from the CPU's runs.
    let scene = Scene::open_with("cornell", dir, &gpu.resources())?;
    let t1 = Instant::now();
    let on = gpu.prepare(scene.view());
    let prep_ms = t1.elapsed().as_secs_f64() * 1e3;
    let rows = relight_rows(&scene, reps)?;
    let h = gpu.gpu_health();
    print(
        &format!(
            "GPU backend: {} ({}, {}{}), scene on {}",
            ad.name,
            ad.backend,
            ad.device_type,
            if ad.software {
                ", a software adapter: a CPU"
            } else {
                ""
            },
            if on {
                "the GPU"
            } else {
                "the CPU (did not fit)"
            }
        ),
        &rows,
    );
    println!(
        "\nGPU bytes: {:.1} MiB for the scene (F, S, vectors, T, the whole relight's); upload \
         of F and S {prep_ms:.0} ms, of T {upload_ms:.0} ms; device copy bandwidth {bw:.1} GB/s",
        h.bytes as f64 / (1 << 20) as f64
    );
    Ok(())
}
