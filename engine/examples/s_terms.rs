//! Times the reduction of a bundle's S to radial terms: what a scene's first translucency
//! change on the CPU spends before it writes S (`engine::smatrix::terms_of_bundle`).
//!
//! In: a bundle folder, and how many times to reduce it (default 3). Out: one line per
//! reduction (wall time, entries, terms, MiB held). Run it under `/usr/bin/time` for the CPU
//! time, which this 2-core VM's neighbours disturb less than the wall time.
//!
//! ```sh
//! cargo run --release -p translux-engine --example s_terms -- BUNDLE_DIR [TIMES]
//! ```

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use translux_engine::smatrix::{self, SParams};
use translux_proto::bundle::Bundle;

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let Some(dir) = args.next().map(PathBuf::from) else {
        eprintln!("usage: s_terms BUNDLE_DIR [TIMES]");
        return ExitCode::from(2);
    };
    let times = match args.next().map(|t| t.parse::<u32>()) {
        None => 3,
        Some(Ok(t)) if (1..=100).contains(&t) => t,
        Some(_) => {
            eprintln!("TIMES must be a whole number from 1 to 100");
            return ExitCode::from(2);
        }
    };
    let bundle = match Bundle::open(&dir) {
        Ok(b) => b,
        Err(e) => {
            eprintln!("cannot open the bundle {}: {e}", dir.display());
            return ExitCode::FAILURE;
        }
    };
    let params = SParams::default();
    println!("| reduction | seconds | entries | terms | MiB |\n|---|---|---|---|---|");
    for k in 1..=times {
        let start = Instant::now();
        let t = smatrix::terms_of_bundle(&bundle, &params.quadrature);
        println!(
            "| {k} | {:.2} | {} | {} | {:.0} |",
            start.elapsed().as_secs_f64(),
            t.entries(),
            t.terms(),
            t.bytes() as f64 / (1u64 << 20) as f64
        );
    }
    ExitCode::SUCCESS
}
