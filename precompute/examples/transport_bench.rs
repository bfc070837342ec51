//! Measures the transport solvers on precomputed bundles and prints a table: Jacobi vs
//! BiCGSTAB (iterations, products, ms; cold and warm), relight with the stored T, and k
//! right-hand sides at once.
//!
//! `cargo run --release -p translux-precompute --example transport_bench -- BUNDLE...`
//! (bundles made with `translux-precompute ... --inverse` also time T).

use std::time::Instant;

use anyhow::Context;
use translux_engine::transport::{Transport, subsurface_operator};

use translux_engine::inverse;
use translux_engine::radiosity::{self, Method, Rgb, SolveParams};
use translux_engine::solver::solve_system;
use translux_proto::bundle::Bundle;

fn best_ms(reps: usize, mut f: impl FnMut()) -> f64 {
    (0..reps)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() -> anyhow::Result<()> {
    let paths: Vec<String> = std::env::args().skip(1).collect();
    if paths.is_empty() {
        anyhow::bail!("usage: transport_bench BUNDLE... (folders written by translux-precompute)");
    }
    println!(
        "| bundle | patches | method | iterations | products | ms (cold) | warm iterations | ms (warm) |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- |");
    let mut t_rows = Vec::new();
    for path in paths {
        let b = Bundle::open(std::path::Path::new(&path))
            .with_context(|| format!("opening the bundle {path:?}"))?;
        let n = b.patch_areas().len();
        let lights = b.manifest().lights.clone();
        let e = radiosity::BundleLighting::new(&b)
            .irradiance(&lights)
            .with_context(|| format!("the default lights of {path:?}"))?;
        // A nearby light for the warm start: every E 3% brighter.
        let e2: Vec<Rgb> = e.iter().map(|x| x.map(|v| v * 1.03)).collect();
        let f = Transport::of(&b);
        // A hierarchical S (the default) has node columns: its operator pulls their means.
        let s_op = subsurface_operator(&b, b.subsurface());
        let s = s_op.as_ref();
        let be = b.patch_emission();
        // (Gauss-Seidel needs a diagonal S; these scenes are translucent.)
        for method in [Method::Jacobi, Method::BiCgStab, Method::Auto] {
            let p = SolveParams {
                method,
                ..Default::default()
            };
            let (x, st) = radiosity::solve(&f, s, be, &e, &p, None)
                .with_context(|| format!("{} on {path:?}", method.as_str()))?;
            let cold = best_ms(3, || {
                radiosity::solve(&f, s, be, &e, &p, None).unwrap();
            });
            let (_, wst) = radiosity::solve(&f, s, be, &e2, &p, Some(&x))
                .with_context(|| format!("{} warm on {path:?}", method.as_str()))?;
            let warm = best_ms(3, || {
                radiosity::solve(&f, s, be, &e2, &p, Some(&x)).unwrap();
            });
            println!(
                "| {path} | {n} | {} | {} | {} | {cold:.1} | {} | {warm:.1} |",
                method.as_str(),
                st.iterations,
                st.products,
                wst.iterations
            );
        }
        // Four right-hand sides at once vs four solves.
        let k = 4;
        let mut rhs1 = vec![[0.0f32; 3]; n];
        s.apply(&e, &mut rhs1);
        let stacked: Vec<f32> = (0..n)
            .flat_map(|j| std::iter::repeat_n(rhs1[j], k).flatten())
            .collect();
        let p = SolveParams::default();
        let batch = best_ms(3, || {
            solve_system(&f, s, &stacked, 3 * k, &p, None).unwrap();
        });
        let one = best_ms(3, || {
            solve_system(&f, s, bytemuck::cast_slice(&rhs1), 3, &p, None).unwrap();
        });
        let mut t_ms = None;
        let mut t4_ms = None;
        if let Some(t) = b.transfer() {
            let mut v = vec![0.0f32; n * 3];
            f.apply_multi(bytemuck::cast_slice(be), &mut v, 3, &mut Default::default());
            let v: Vec<f32> = v
                .iter()
                .zip(bytemuck::cast_slice::<Rgb, f32>(&e))
                .map(|(a, b)| a + b)
                .collect();
            let mut y = vec![0.0f32; n * 3];
            t_ms = Some(best_ms(5, || {
                inverse::apply_stored(t.bits, t.scale, n, &v, 1, &mut y);
                let mut sv = vec![0.0f32; n * 3];
                s.apply_multi(&v, &mut sv, 3);
            }));
            let v4: Vec<f32> = (0..n)
                .flat_map(|j| {
                    std::iter::repeat_n(&v[3 * j..3 * j + 3], k)
                        .flatten()
                        .copied()
                })
                .collect();
            let mut y4 = vec![0.0f32; n * 3 * k];
            t4_ms = Some(best_ms(5, || {
                inverse::apply_stored(t.bits, t.scale, n, &v4, k, &mut y4);
            }));
        }
        t_rows.push((path, n, one, batch, t_ms, t4_ms));
    }
    println!();
    println!(
        "| bundle | patches | solve (auto) 1 rhs ms | solve (auto) 4 rhs ms, one batch | T relight ms | T 4 rhs ms |"
    );
    println!("| --- | --- | --- | --- | --- | --- |");
    for (path, n, one, batch, t, t4) in t_rows {
        let show = |x: Option<f64>| x.map_or("—".to_string(), |v| format!("{v:.1}"));
        println!(
            "| {path} | {n} | {one:.1} | {batch:.1} | {} | {} |",
            show(t),
            show(t4)
        );
    }
    Ok(())
}
