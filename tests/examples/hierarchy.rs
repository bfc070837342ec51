//! Hierarchical F against dense F on one scene, as a table (the numbers of issue #17).
//!
//! ```text
//! cargo run --release -p translux-tests --example hierarchy -- \
//!     [--scene builtin:cornell_paper] [--patches 24640] [--accuracy 0.25,0.15] [--lights 16] \
//!     [--samples 8] [--cone 60] [--links one-sided,two-sided] [--no-dense [--rows 200]]
//! ```
//!
//! Per transport: F precompute time, entries per patch, F's bytes, occlusion rays, relight
//! time with the warm solver (CPU, this machine), and against the dense exact solve
//! (residual 1e-7) with random point and spot lights: per-vertex relative error, median and
//! 90th percentile, lit and shadowed vertices apart; the operator's error on a constant, a
//! smooth random field and a cluster indicator; the largest row-sum difference.
//!
//! With `--no-dense` (scenes where dense F does not fit), no dense bundle is made: instead
//! `--rows` receivers spread over the scene get their exact dense row
//! (`formfactor::dense_row`, the dense code's own rule), and the hierarchical rows are
//! compared with them: row sums and the operator on the same three fields, on those rows.
//! The process's peak memory is printed at the end.
//!
//! `--scene cornell+bunny` is the Cornell box with the whole scanned bunny
//! (`../shared/data/stanford-bunny.obj`, 69,451 triangles) in place of the short box, every
//! object diffuse (the marble block too: S at a million patches is the hierarchical-S
//! issue's, not this benchmark's); any other `--scene` is loaded as `translux-precompute`
//! loads it.

use std::time::Instant;

use anyhow::Context;
use glam::Vec3;
use rayon::prelude::*;
use translux_engine::linalg::{Rgb, SparseScatter};
use translux_engine::radiosity::{self, BundleLighting};
use translux_engine::raycast::Occluder;
use translux_engine::solver::SolveParams;
use translux_engine::transport::Transport;
use translux_precompute::formfactor::{FormFactorParams, dense_row};
use translux_precompute::hierarchy::HierarchyParams;
use translux_precompute::patch;
use translux_precompute::pipeline::{FormFactorMethod, PrecomputeParams, precompute};
use translux_proto::bundle::Bundle;
use translux_proto::light::Light;
use translux_tests::compare;

struct Args {
    scene: String,
    patches: u64,
    accuracy: Vec<f32>,
    samples: u32,
    cone: f32,
    lights: usize,
    no_dense: bool,
    rows: usize,
    /// Two-sided links (nodes receive too) for each entry.
    two_sided: Vec<bool>,
}

fn args() -> anyhow::Result<Args> {
    let mut a = Args {
        scene: "builtin:cornell_paper".into(),
        patches: 24_640,
        accuracy: vec![HierarchyParams::default().accuracy],
        lights: 16,
        samples: HierarchyParams::default().node_samples,
        cone: HierarchyParams::default().cone_deg,
        no_dense: false,
        rows: 200,
        two_sided: vec![false],
    };
    let mut it = std::env::args().skip(1);
    while let Some(k) = it.next() {
        let mut v = || it.next().with_context(|| format!("{k} needs a value"));
        match k.as_str() {
            "--scene" => a.scene = v()?,
            "--patches" => a.patches = v()?.parse()?,
            "--lights" => a.lights = v()?.parse()?,
            "--samples" => a.samples = v()?.parse()?,
            "--cone" => a.cone = v()?.parse()?,
            "--no-dense" => a.no_dense = true,
            "--rows" => a.rows = v()?.parse()?,
            "--links" => {
                a.two_sided = v()?
                    .split(',')
                    .map(|s| match s.trim() {
                        "one-sided" => Ok(false),
                        "two-sided" => Ok(true),
                        other => anyhow::bail!("--links takes one-sided or two-sided, got {other}"),
                    })
                    .collect::<anyhow::Result<_>>()?
            }
            "--accuracy" => {
                a.accuracy = v()?
                    .split(',')
                    .map(|s| s.trim().parse::<f32>())
                    .collect::<Result<_, _>>()?
            }
            other => anyhow::bail!("unknown argument {other}"),
        }
    }
    Ok(a)
}

/// Milliseconds per relight: direct light plus the solve at the server's default
/// tolerance, warm-started from the previous answer, the light moving a little each time.
fn relight_ms(b: &Bundle, lights: &[Light]) -> f64 {
    let lighting = BundleLighting::new(b);
    let f = Transport::of(b);
    let s = SparseScatter(b.subsurface());
    let params = SolveParams::default();
    let mut warm: Option<Vec<Rgb>> = None;
    let reps = 12;
    let mut spent = 0.0;
    for r in 0..reps + 2 {
        let light = match &lights[0] {
            Light::Point {
                position,
                intensity,
            } => Light::Point {
                position: [position[0] + 0.002 * r as f32, position[1], position[2]],
                intensity: *intensity,
            },
            l => l.clone(),
        };
        let t = Instant::now();
        let e = lighting.irradiance(&[light]).expect("point light");
        let (x, _) = radiosity::solve(&f, &s, b.patch_emission(), &e, &params, warm.as_deref())
            .expect("solve");
        if r >= 2 {
            spent += t.elapsed().as_secs_f64();
        }
        warm = Some(x);
    }
    1e3 * spent / reps as f64
}

fn main() -> anyhow::Result<()> {
    let a = args()?;
    let work = tempfile::tempdir()?;
    let loaded = if a.scene == "cornell+bunny" {
        cornell_with_bunny()?
    } else {
        translux_precompute::scene::load_scene(&a.scene)?
    };
    let mut methods = Vec::new();
    if !a.no_dense {
        methods.push(("dense".to_string(), FormFactorMethod::Dense));
    }
    for &accuracy in &a.accuracy {
        for &two_sided in &a.two_sided {
            let sides = if two_sided { ", two-sided" } else { "" };
            methods.push((
                format!("hierarchical η={accuracy}{sides}"),
                FormFactorMethod::Hierarchical(HierarchyParams {
                    accuracy,
                    node_samples: a.samples,
                    cone_deg: a.cone,
                    two_sided,
                }),
            ));
        }
    }
    let mut bundles = Vec::new();
    println!(
        "# {} at {} requested patches, {} threads\n",
        a.scene,
        a.patches,
        rayon::current_num_threads()
    );
    println!(
        "| transport | patches | F time | entries/patch | F bytes | rays | relight (warm) | fps |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for (k, (name, method)) in methods.iter().enumerate() {
        let out = work.path().join(format!("b{k}"));
        let params = PrecomputeParams {
            patches: Some(a.patches),
            transport: *method,
            environment: translux_engine::envvis::EnvVisParams {
                bins: None,
                ..Default::default()
            },
            ..Default::default()
        };
        let report = precompute(&loaded, &out, &params)?;
        let f_s = report
            .stages
            .iter()
            .find(|s| s.stage == "form factors")
            .map_or(0.0, |s| s.seconds);
        let b = Bundle::open(&out)?;
        let ff_bytes: u64 = ["ff_row_ptr", "ff_col", "ff_val", "tree_perm", "tree_range"]
            .iter()
            .filter_map(|n| b.manifest().arrays.get(*n))
            .map(|e| e.bytes)
            .sum();
        let lights = compare::random_lights(&b, 1, 7);
        let ms = relight_ms(&b, &lights);
        println!(
            "| {name} | {} | {f_s:.2} s | {:.0} | {:.1} MiB | {:.1} M | {ms:.1} ms | {:.1} |",
            report.patch_count,
            report.nnz_f as f64 / report.patch_count as f64,
            ff_bytes as f64 / (1 << 20) as f64,
            report.form_factors.rays as f64 / 1e6,
            1e3 / ms
        );
        bundles.push((name.clone(), b, out));
    }
    if a.no_dense {
        exact_rows(&bundles, a.rows);
        println!("\npeak memory (RSS) of this process: {}", peak_rss());
        return Ok(());
    }
    println!(
        "\n| transport | lit median | lit p90 | shadowed median | shadowed p90 | vertices (lit / shadowed) | max row-sum diff | operator error (constant / smooth / cluster) |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    let dense = &bundles[0].1;
    let lights = compare::random_lights(dense, a.lights, 17);
    let dense_sums = Transport::of(dense).row_sums();
    for (name, b, _) in &bundles[1..] {
        let acc = compare::relight_accuracy(dense, b, &lights);
        let sums = Transport::of(b).row_sums();
        let row_diff = dense_sums
            .iter()
            .zip(&sums)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let ops: Vec<String> = compare::fields(b, 3)
            .iter()
            .map(|(_, x)| format!("{:.2e}", compare::operator_error(dense, b, x)))
            .collect();
        println!(
            "| {name} | {:.2}% | {:.2}% | {:.2}% | {:.2}% | {} / {} | {row_diff:.1e} | {} |",
            100.0 * acc.lit.median,
            100.0 * acc.lit.p90,
            100.0 * acc.shadowed.median,
            100.0 * acc.shadowed.p90,
            acc.lit.count,
            acc.shadowed.count,
            ops.join(" / ")
        );
    }
    Ok(())
}

/// The hierarchical bundles' rows against exact dense rows at `count` receivers.
fn exact_rows(bundles: &[(String, Bundle, std::path::PathBuf)], count: usize) {
    println!(
        "\n| transport | rows checked exactly | time for those rows | max row-sum diff | operator error on them (constant / smooth / cluster) |"
    );
    println!("|---|---|---|---|---|");
    for (name, b, _) in bundles {
        // The bundle's patches (in its order) and occluders, as the precompute had them.
        let tris: Vec<[Vec3; 3]> = b
            .patch_corners()
            .iter()
            .map(|c| c.map(Vec3::from))
            .collect();
        let p = patch::subdivide(&[&tris], f32::INFINITY);
        assert_eq!(p.len(), tris.len(), "one patch per stored triangle");
        let occ_tris: Vec<[Vec3; 3]> = b
            .occluder_triangles()
            .iter()
            .map(|c| c.map(Vec3::from))
            .collect();
        let occ = Occluder::new(&occ_tris);
        let n = p.len();
        // Spread over the patch list with a fixed stride and a scrambled offset.
        let rows: Vec<usize> = (0..count.min(n))
            .map(|k| (k * n / count.min(n) + (k * 7919) % (n / count.min(n)).max(1)) % n)
            .collect();
        let t = Instant::now();
        let exact: Vec<Vec<(u32, f32)>> = rows
            .par_iter()
            .map(|&i| dense_row(&p, &occ, &FormFactorParams::default(), i))
            .collect();
        let secs = t.elapsed().as_secs_f64();
        let f = Transport::of(b);
        let sums = f.row_sums();
        let row_diff = rows
            .iter()
            .zip(&exact)
            .map(|(&i, row)| (row.iter().map(|e| e.1 as f64).sum::<f64>() - sums[i]).abs())
            .fold(0.0, f64::max);
        let ops: Vec<String> = compare::fields(b, 3)
            .iter()
            .map(|(_, x)| {
                let rgb: Vec<Rgb> = x.iter().map(|&v| [v; 3]).collect();
                let mut y = vec![[0.0f32; 3]; n];
                f.apply_rgb(&rgb, &mut y);
                let err = compare::relative_l2(rows.iter().zip(&exact).map(|(&i, row)| {
                    let want = row
                        .iter()
                        .map(|&(j, v)| v as f64 * x[j as usize] as f64)
                        .sum();
                    (y[i][0] as f64, want)
                }));
                format!("{err:.2e}")
            })
            .collect();
        println!(
            "| {name} | {} | {secs:.1} s | {row_diff:.1e} | {} |",
            rows.len(),
            ops.join(" / ")
        );
    }
}

/// The process's peak resident memory (Linux `VmHWM`), or "unknown".
fn peak_rss() -> String {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .map(|l| l["VmHWM:".len()..].trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into())
}

/// builtin:cornell_paper with the scanned bunny for the short box, everything diffuse.
fn cornell_with_bunny() -> anyhow::Result<translux_precompute::scene::LoadedScene> {
    use translux_proto::scene::Material;
    let data = translux_tests::scans::data_dir();
    anyhow::ensure!(
        data.join("stanford-bunny.obj").is_file(),
        "{} is missing: the scanned meshes are read from ../shared/data beside the repository",
        data.join("stanford-bunny.obj").display()
    );
    let mut file = translux_precompute::builtin::builtin_scene("cornell_paper")
        .context("builtin cornell_paper")?;
    let short = file
        .objects
        .iter()
        .position(|o| o.name == "short_box")
        .context("cornell has a short box")?;
    // The bunny's feet on the floor where the short box stood.
    let diffuse = Material::Diffuse {
        albedo: [0.75, 0.75, 0.75],
        specular: None,
    };
    file.objects[short] = translux_tests::scans::bunny(0.09, 0.07, 200.0, diffuse);
    for o in &mut file.objects {
        if matches!(o.material, Material::Translucent { .. }) {
            o.material = Material::Diffuse {
                albedo: [0.8, 0.8, 0.8],
                specular: None,
            };
        }
    }
    Ok(translux_precompute::scene::resolve_scene(
        file,
        &data,
        "cornell+bunny".into(),
        "cornell+bunny".into(),
    )?)
}
