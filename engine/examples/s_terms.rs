//! Times the two parts of a translucency change on the CPU that S's radial terms serve:
//! the reduction of a bundle's S to radial terms, what a scene's first translucency change
//! spends before it writes S (`engine::smatrix::terms_of_bundle`); and, with `--rewrite`, a
//! translucency slider's steps: S's rows of every dipole object rewritten in place from its
//! terms (`engine::smatrix::rewrite_with_terms`), what every later change spends before
//! its solve.
//!
//! In: a bundle folder, how many times (default 3 reductions, or 12 slider steps),
//! `--rewrite`, and `--receiver-theta X` (the receiver-side cut's θ_r,
//! `SubsurfaceParams::receiver_theta`; 0 keeps every receiver's own links). Out: one line
//! per reduction (wall time, entries, terms, links from patches, node-to-node links, MiB
//! held), then the entries and their terms by how many terms an entry has; with
//! `--rewrite`, one reduction, then one line per step (the scale, wall time, each object's
//! part of it, the entries written), the median and fastest step, a hash of
//! S's values after the last step (equal for two builds that write the same S bit for bit),
//! S's stored entries, and the median of 12 products of S̃ with a batch of 3 RGB
//! right-hand sides (the solver's products per iteration). The steps
//! are the drag `table1` times (0.9, 1, 1.137, 1.274, …), every dipole object scaled alike.
//! Run it under `/usr/bin/time` for the CPU time, which this 2-core VM's neighbours disturb
//! less than the wall time.
//!
//! ```sh
//! cargo run --release -p translux-engine --example s_terms -- BUNDLE_DIR [TIMES] [--rewrite] [--receiver-theta X]
//! ```

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use translux_engine::smatrix::{self, SParams};
use translux_engine::sterms::{STerms, Scratch};
use translux_engine::transport;
use translux_proto::bundle::Bundle;
use translux_proto::scene::{Material, Profile};

const USAGE: &str = "usage: s_terms BUNDLE_DIR [TIMES] [--rewrite] [--receiver-theta X]";

fn main() -> ExitCode {
    let (mut dir, mut times, mut rewrite) = (None, None, false);
    let mut params = SParams::default();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        if a == "--rewrite" {
            rewrite = true;
        } else if a == "--receiver-theta" {
            match args.next().map(|t| t.parse::<f32>()) {
                Some(Ok(t)) if (0.0..=1.0).contains(&t) => params.quadrature.receiver_theta = t,
                other => {
                    eprintln!("--receiver-theta takes a number from 0 to 1, got {other:?}");
                    return ExitCode::from(2);
                }
            }
        } else if dir.is_none() {
            dir = Some(PathBuf::from(a));
        } else if times.is_none() {
            match a.parse::<u32>() {
                Ok(t) if (1..=100).contains(&t) => times = Some(t),
                _ => {
                    eprintln!("TIMES must be a whole number from 1 to 100, got {a:?}");
                    return ExitCode::from(2);
                }
            }
        } else {
            eprintln!("{USAGE}");
            return ExitCode::from(2);
        }
    }
    let Some(dir) = dir else {
        eprintln!("{USAGE}");
        return ExitCode::from(2);
    };
    let bundle = match Bundle::open(&dir) {
        Ok(b) => b,
        Err(e) => {
            eprintln!("cannot open the bundle {}: {e}", dir.display());
            return ExitCode::FAILURE;
        }
    };
    let times = times.unwrap_or(if rewrite { 12 } else { 3 });
    println!(
        "| reduction | seconds | entries | terms | links | node-to-node links | MiB |\n\
         |---|---|---|---|---|---|---|"
    );
    let mut terms = None;
    for k in 1..=if rewrite { 1 } else { times } {
        let start = Instant::now();
        let t = smatrix::terms_of_bundle(&bundle, &params.quadrature);
        let (links, pairs) = t.links();
        println!(
            "| {k} | {:.2} | {} | {} | {links} | {pairs} | {:.0} |",
            start.elapsed().as_secs_f64(),
            t.entries(),
            t.terms(),
            t.bytes() as f64 / (1u64 << 20) as f64
        );
        terms = Some(t);
    }
    if let Some(t) = &terms {
        println!("\n| terms per entry | entries | terms |\n|---|---|---|");
        for (b, (e, n)) in t.term_histogram().into_iter().enumerate() {
            let lo = 1usize << b;
            let span = if b == 5 {
                format!("{lo}+")
            } else {
                format!("{lo}–{}", 2 * lo - 1)
            };
            println!("| {span} | {e} | {n} |");
        }
    }
    match terms {
        Some(t) if rewrite => slider(&bundle, &params, &t, times),
        _ => ExitCode::SUCCESS,
    }
}

/// Every dipole object's material with its mean free path × `s`.
fn overrides(bundle: &Bundle, s: f32) -> Vec<(usize, Material)> {
    let objects = &bundle.manifest().objects;
    objects
        .iter()
        .enumerate()
        .filter_map(|(k, o)| {
            let mut m = o.material.clone();
            let Material::Translucent {
                profile: Profile::Dipole { scale, .. },
                ..
            } = &mut m
            else {
                return None;
            };
            *scale = Some(scale.unwrap_or(1.0) * s);
            Some((k, m))
        })
        .collect()
}

/// Times `steps` translucency changes written in place, after an untimed first one.
fn slider(bundle: &Bundle, params: &SParams, terms: &STerms, steps: u32) -> ExitCode {
    let first = overrides(bundle, 0.9);
    if first.is_empty() {
        eprintln!("the bundle has no dipole object to change");
        return ExitCode::FAILURE;
    }
    let mut s = match smatrix::rebuild_with_terms_and_tilt(bundle, &first, params, terms) {
        Ok((s, ..)) => s,
        Err(e) => {
            eprintln!("cannot build S: {e}");
            return ExitCode::FAILURE;
        }
    };
    let mut scratch = Scratch::default();
    // The energy bound's column factors, left out of S's values as a scene's slider
    // leaves them (`smatrix::rewrite_with_terms_deferred`).
    let mut columns = smatrix::ColumnScale::default();
    let (mut before, mut times) = (first, Vec::new());
    println!("\n| step | scale | ms | ms per object | entries |\n|---|---|---|---|---|");
    for k in 0..steps {
        let scale = 1.0 + 0.137 * k as f32;
        let after = overrides(bundle, scale);
        let Some(changed) = smatrix::changed_profiles(&before, &after, terms) else {
            eprintln!("step {k} is not a translucency change");
            return ExitCode::FAILURE;
        };
        let start = Instant::now();
        let reports;
        (s, reports) = match smatrix::rewrite_with_terms_deferred(
            bundle,
            s,
            &mut columns,
            &mut None,
            &after,
            &changed,
            params,
            terms,
            &mut scratch,
        ) {
            Ok(r) => r,
            Err(e) => {
                eprintln!("step {k}: {e}");
                return ExitCode::FAILURE;
            }
        };
        let ms = start.elapsed().as_secs_f64() * 1e3;
        let entries: u64 = reports.iter().map(|r| r.entries).sum();
        let objects: Vec<String> = reports
            .iter()
            .map(|r| format!("{} {:.1}", r.name, r.seconds * 1e3))
            .collect();
        println!(
            "| {} | {scale:.3} | {ms:.1} | {} | {entries} |",
            k + 1,
            objects.join(", ")
        );
        times.push(ms);
        before = after;
    }
    times.sort_by(f64::total_cmp);
    // FNV-1a over the bits of S's values (scaled by the column factors) after the last
    // step: equal between two builds when they write the same S bit for bit.
    let scaled = match columns.apply(s.clone()) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("S's column factors: {e}");
            return ExitCode::FAILURE;
        }
    };
    let hash = scaled
        .view()
        .val()
        .iter()
        .flatten()
        .fold(0xcbf2_9ce4_8422_2325u64, |h, v| {
            (h ^ v.to_bits() as u64).wrapping_mul(0x0100_0000_01b3)
        });
    println!(
        "median {:.1} ms, fastest {:.1} ms over {steps} steps; S after the last: {hash:016x}",
        times[times.len() / 2],
        times[0]
    );
    // S̃'s products as the solver makes them (3 RGB right-hand sides at once).
    let view = s.view();
    let op = transport::subsurface_operator_scaled(bundle, view, columns.factors());
    let n = bundle.patch_areas().len();
    let h: Vec<f32> = (0..n * 9).map(|i| (i % 7) as f32 * 0.1).collect();
    let mut y = vec![0.0f32; n * 9];
    let mut products: Vec<f64> = (0..12)
        .map(|_| {
            let start = Instant::now();
            op.apply_multi(&h, &mut y, 9);
            start.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    products.sort_by(f64::total_cmp);
    println!(
        "S: {} rows, {} stored entries; a product with 3 RGB right-hand sides: median {:.1} ms",
        view.n_rows(),
        view.nnz(),
        products[products.len() / 2]
    );
    ExitCode::SUCCESS
}
