//! `translux-precompute SCENE --out DIR [--patches N] [--inverse]`, its shards
//! (`--shard I/K`, then `--merge K`, [`translux_precompute::shard`]), or
//! `translux-precompute BUNDLE --resimulate --materials JSON` (simulated objects walk again
//! in a new medium, [`translux_precompute::resimulate`]).
//!
//! Parses the command line (the precompute's settings are
//! [`translux_precompute::options::PrecomputeOptions`], flattened in), loads the scene, runs
//! [`translux_precompute::pipeline`] and prints the summary. Exit codes: 0 done, 1 failed
//! (the message says why), 2 bad usage.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use translux_precompute::options::PrecomputeOptions;
use translux_precompute::pipeline::{self, PrecomputeParams, human_bytes};
use translux_precompute::scene;
use translux_precompute::shard::{Shard, parse_count};

/// Precompute a translux bundle (patches, viewer mesh, form factors) from a scene.
#[derive(Debug, Parser)]
#[command(name = "translux-precompute", version, next_line_help = true)]
struct Cli {
    /// A scene file (JSON), a glTF 2.0 file (`.gltf`/`.glb`, a whole scene: its objects,
    /// materials, lights and camera) or `builtin:NAME` (cornell, cornell_paper, cornell_checker, bowls, flower, rolling); with
    /// `--resimulate`, a bundle folder.
    scene: String,
    /// Walk the simulated objects named in `--materials` again, in their new media, inside
    /// the bundle SCENE, and rewrite it in place (atomically): a change of scattering (σs,
    /// g, η) without the scene's sources. The bundle's transfer matrix T is dropped.
    #[arg(long, requires = "materials", help_heading = "Input")]
    resimulate: bool,
    /// With `--resimulate`: `{"NAME": {"type": "simulated", ...}, ...}`, JSON or `@FILE`.
    #[arg(long, requires = "resimulate", help_heading = "Input")]
    materials: Option<String>,
    #[command(flatten)]
    options: PrecomputeOptions,
    /// Folder to write the bundle to (replaced atomically if it exists). For an animated
    /// scene, the sequence folder: one bundle per frame and `sequence.json`; a rerun keeps
    /// the frames whose inputs did not change (it resumes).
    #[arg(
        long,
        required_unless_present = "resimulate",
        help_heading = "Output",
        display_order = 0
    )]
    out: Option<PathBuf>,
    /// No progress bars or stage lines.
    #[arg(long, short)]
    quiet: bool,
    /// Compute only shard I of K (0-based: 0/4 to 3/4) of the receiver rows — the form
    /// factors, the environment visibility and, with a hierarchical S, the cuts of its share
    /// of the translucent receivers — into `OUT.parts/part-I-of-K/`, for a job
    /// array on a scheduler. A shard already finished for the same scene and settings is
    /// not computed again; a killed one leaves no part. Hierarchical transport only. For an
    /// animated scene, the I-th share of the frames (consecutive blocks of 8) instead, each
    /// a whole bundle in `OUT/frame-NNNN/`; frames already done for the same inputs are kept.
    #[arg(long, value_name = "I/K", conflicts_with_all = ["merge", "resimulate"])]
    shard: Option<Shard>,
    /// Put the K parts in `OUT.parts/` together — each checked: none missing, from another
    /// split, scene or settings, or damaged — run the remaining stages (the rest of
    /// subsurface, T) and
    /// write the bundle, the same arrays as one run without shards; the parts are removed
    /// after. Give the scene and the same settings as the shards. For an animated scene:
    /// check that every frame is there and made from the current inputs (refusing, with the
    /// `--shard` command that makes it, one missing or stale), then write `sequence.json`.
    #[arg(long, value_name = "K", conflicts_with = "resimulate", value_parser = parse_count)]
    merge: Option<u32>,
}

/// `--resimulate`: walks again, prints what changed.
fn resimulate(cli: &Cli) -> anyhow::Result<()> {
    let text = cli.materials.as_deref().unwrap_or_default();
    let text = match text.strip_prefix('@') {
        Some(file) => std::fs::read_to_string(file).with_context(|| format!("reading {file}"))?,
        None => text.to_string(),
    };
    let materials: std::collections::BTreeMap<String, translux_proto::scene::Material> =
        translux_proto::parse_json(&text).map_err(|e| anyhow::anyhow!("--materials: {e}"))?;
    let changes: Vec<_> = materials.into_iter().collect();
    let quiet = cli.quiet;
    let last = std::sync::atomic::AtomicU64::new(0);
    let report = translux_precompute::resimulate::resimulate(
        std::path::Path::new(&cli.scene),
        &changes,
        &|done, total| {
            // A line per tenth, not per batch.
            let tenth = done * 10 / total.max(1);
            if !quiet && last.fetch_max(tenth, std::sync::atomic::Ordering::Relaxed) < tenth {
                eprintln!("walks: {done} of {total} patches");
            }
        },
        (&translux_engine::stop::Stop::never(), None),
    )
    .map_err(anyhow::Error::msg)
    .with_context(|| format!("re-simulating {}", cli.scene))?;
    println!("translux-precompute: walked again in {}", cli.scene);
    for (name, walks, seconds) in &report.objects {
        println!("  {name:<18} {walks} walks in {seconds:.1} s");
    }
    println!("  walk records       {}", report.records);
    println!("  bundle             {}", human_bytes(report.bundle_bytes));
    if report.dropped_transfer {
        println!("  transfer matrix T  dropped (S changed): precompute with --inverse to have it");
    }
    println!("  total              {:.1} s", report.seconds);
    Ok(())
}

/// An animated scene: one bundle per frame in `out` ([`translux_precompute::sequence`]),
/// all of them, a shard's share of them (`--shard I/K`) or the shards' put together
/// (`--merge K`).
fn sequence(
    cli: &Cli,
    source: &scene::SceneSource,
    out: &std::path::Path,
    params: &PrecomputeParams,
) -> anyhow::Result<()> {
    use translux_precompute::sequence::{
        FrameOutcome, merge_sequence, precompute_sequence, precompute_sequence_shard, shard_frames,
    };
    let quiet = cli.quiet;
    // One line per frame instead of every frame's stage bars.
    let params = &PrecomputeParams {
        progress: false,
        ..params.clone()
    };
    let on_frame = |f: &translux_precompute::sequence::FrameReport, total: u32| {
        if quiet {
            return;
        }
        let what = match &f.outcome {
            FrameOutcome::Computed { patches, bytes } => {
                format!("precomputed, {patches} patches, {}", human_bytes(*bytes))
            }
            FrameOutcome::Resumed => "kept from the last run (same inputs)".into(),
            FrameOutcome::SharedWith(k) => format!("the same scene as frame {k}: shares it"),
        };
        eprintln!(
            "frame {} of {total} ({}): {what} in {:.2} s",
            f.frame + 1,
            f.folder,
            f.seconds
        );
    };
    let (report, what) = if let Some(shard) = cli.shard {
        let report = precompute_sequence_shard(source, out, params, shard, &on_frame)
            .with_context(|| format!("precomputing shard {shard} of {}", cli.scene))?;
        let frames = source.file.animation.map_or(0, |a| a.frames);
        let share = shard_frames(frames, shard);
        if share.is_empty() {
            let block = translux_precompute::sequence::BLOCK_FRAMES;
            println!(
                "translux-precompute: shard {shard} of {} has no frames (its {frames} frames \
                 make {} blocks of {block}, fewer than the {} shards): nothing to do",
                cli.scene,
                frames.div_ceil(block),
                shard.count
            );
            return Ok(());
        }
        let what = format!(
            "shard {shard} of a sequence: frames {} to {} of {frames}",
            share.start,
            share.end - 1
        );
        (report, what)
    } else if let Some(count) = cli.merge {
        let report = merge_sequence(source, out, params, count, &shard_command)
            .with_context(|| format!("merging the {count} shards of {}", cli.scene))?;
        (report, format!("sequence merged from {count} shards"))
    } else {
        let report = precompute_sequence(source, out, params, &on_frame)
            .with_context(|| format!("precomputing {}", cli.scene))?;
        (report, "sequence".to_string())
    };
    let n = report.frames.len().max(1);
    println!(
        "translux-precompute: {} -> {} ({what}, {} frames)",
        cli.scene,
        out.display(),
        report.frames.len()
    );
    println!(
        "  frames             {} precomputed, {} kept from the last run, {} shared with an \
         earlier frame",
        report.computed(),
        report.resumed(),
        report.shared()
    );
    if let Some((mean, max)) = report.seconds_per_frame() {
        println!("  per frame          {mean:.2} s mean, {max:.2} s max");
    }
    println!(
        "  bundles            {} in all, {} per frame",
        human_bytes(report.bytes),
        human_bytes(report.bytes / n as u64)
    );
    println!("  total              {:.1} s", report.seconds);
    Ok(())
}

/// This command line with `--merge K` turned into `--shard I/K`: what makes shard `s`.
fn shard_command(s: Shard) -> String {
    let mut words = vec!["translux-precompute".to_string()];
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        if a == "--merge" {
            args.next();
        } else if !a.starts_with("--merge=") {
            words.push(quoted(&a));
        }
    }
    words.push(format!("--shard {s}"));
    words.join(" ")
}

/// `word` as a shell reads it back.
fn quoted(word: &str) -> String {
    let plain = !word.is_empty()
        && word
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_./:=@%+,".contains(c));
    if plain {
        word.to_string()
    } else {
        format!("'{}'", word.replace('\'', r"'\''"))
    }
}

/// `--shard I/K`: computes the part, prints what it holds.
fn print_part(
    name: &str,
    loaded: &scene::LoadedScene,
    out: &std::path::Path,
    params: &PrecomputeParams,
    shard: Shard,
) -> anyhow::Result<()> {
    let r = pipeline::precompute_shard(loaded, out, params, shard)
        .with_context(|| format!("precomputing shard {shard} of {name}"))?;
    if !r.computed {
        println!(
            "translux-precompute: shard {shard} of {name} is already in {} (same scene and \
             settings): nothing to do",
            r.dir.display()
        );
        return Ok(());
    }
    println!(
        "translux-precompute: shard {shard} of {name} -> {}",
        r.dir.display()
    );
    println!(
        "  receiver rows      {}..{} ({} entries of F)",
        r.rows.start, r.rows.end, r.entries
    );
    println!("  part               {}", human_bytes(r.bytes));
    println!(
        "  stage times        form factors {:.2} s, environment {:.2} s, subsurface cuts {:.2} s",
        r.form_factor_seconds, r.environment_seconds, r.subsurface_seconds
    );
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    if cli.resimulate {
        return resimulate(&cli);
    }
    let out = cli.out.clone().context("--out DIR is required")?;
    let params = PrecomputeParams {
        progress: !cli.quiet,
        ..cli.options.params().map_err(anyhow::Error::msg)?
    };
    cli.options
        .build_global_thread_pool()
        .map_err(anyhow::Error::msg)?;
    let t0 = Instant::now();
    let source = scene::read_scene(&cli.scene)?;
    let animated = source.file.animation.is_some();
    let loaded = if animated {
        None
    } else {
        Some(scene::resolve_scene(
            source.file.clone(),
            &source.base_dir,
            source.name.clone(),
            source.source.clone(),
        )?)
    };
    let load_s = t0.elapsed().as_secs_f64();
    let Some(loaded) = loaded else {
        return sequence(&cli, &source, &out, &params);
    };
    if let Some(shard) = cli.shard {
        return print_part(&cli.scene, &loaded, &out, &params, shard);
    }
    let report = match cli.merge {
        Some(count) => pipeline::precompute_merge(&loaded, &out, &params, count),
        None => pipeline::precompute(&loaded, &out, &params),
    }
    .with_context(|| format!("precomputing {}", cli.scene))?;

    let turned = loaded
        .objects
        .iter()
        .filter(|o| o.reoriented)
        .map(|o| o.name.as_str())
        .collect();
    print!(
        "{}",
        Summary {
            scene: &cli.scene,
            out: &out,
            report: &report,
            turned,
            load_s,
        }
    );
    Ok(())
}

/// What `translux-precompute` prints after a bundle is written: its counts, F, S, T, the
/// bundle and the stage times ([`std::fmt::Display`], a section per method).
struct Summary<'a> {
    scene: &'a str,
    out: &'a std::path::Path,
    report: &'a pipeline::PrecomputeReport,
    /// Objects whose winding the loader turned over.
    turned: Vec<&'a str>,
    /// Seconds spent reading the scene.
    load_s: f64,
}

impl std::fmt::Display for Summary<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.counts(f)?;
        self.form_factors(f)?;
        self.subsurface(f)?;
        self.transfer(f)?;
        self.bundle(f)
    }
}

impl Summary<'_> {
    /// The scene, the output and the counts.
    fn counts(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = self.report;
        writeln!(
            f,
            "translux-precompute: {} -> {}",
            self.scene,
            self.out.display()
        )?;
        writeln!(f, "  patches            {}", r.patch_count)?;
        writeln!(f, "  viewer vertices    {}", r.vertex_count)?;
        writeln!(f, "  source triangles   {}", r.occluder_count)?;
        if !self.turned.is_empty() {
            writeln!(
                f,
                "  orientation        turned over: {} (see the notes above; \"orientation\" in \
                 the scene file decides)",
                self.turned.join(", ")
            )?;
        }
        Ok(())
    }

    /// F: its entries (and cluster tree), row sums, threshold and rays.
    fn form_factors(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = self.report;
        let ff = &r.form_factors;
        let n = r.patch_count as f64;
        match &r.hierarchy {
            None => writeln!(
                f,
                "  nnz(F)             {} ({:.1}% of N²), dense",
                r.nnz_f,
                100.0 * r.nnz_f as f64 / (n * n).max(1.0)
            )?,
            Some(h) => {
                writeln!(
                    f,
                    "  nnz(F)             {} ({:.1} per patch: {} to clusters, {} to patches), \
                     hierarchical F̃ = C·P, accuracy {}",
                    r.nnz_f,
                    r.nnz_f as f64 / n.max(1.0),
                    h.node_entries,
                    h.patch_entries,
                    h.accuracy
                )?;
                // Dense F stores 8 bytes per entry (column, value) plus the row pointers.
                let dense_bytes = h.dense_equivalent * 8 + (r.patch_count as u64 + 1) * 8;
                let bytes =
                    r.nnz_f * 8 + (r.patch_count as u64 + 1) * 8 + n as u64 * 4 + h.nodes * 8;
                writeln!(
                    f,
                    "  cluster tree       {} nodes, depth {}; F̃ {} against {} for dense F \
                     ({:.1}% of N² pairs in view of the cut)",
                    h.nodes,
                    h.depth,
                    human_bytes(bytes),
                    human_bytes(dense_bytes),
                    100.0 * h.dense_equivalent as f64 / (n * n).max(1.0)
                )?;
            }
        }
        writeln!(
            f,
            "  F row sums         mean {:.4}, min {:.4}, max {:.4}",
            ff.row_sum_mean,
            ff.row_sum_min.max(0.0),
            ff.row_sum_max
        )?;
        if ff.threshold > 0.0 {
            writeln!(
                f,
                "  threshold          {} dropped {:.4}% of the power",
                ff.threshold,
                100.0 * ff.dropped_energy
            )?;
        }
        writeln!(
            f,
            "  occlusion rays     {} ({:.2} M rays/s over the F stage)",
            ff.rays,
            r.rays_per_second / 1e6
        )
    }

    /// S: its entries, then a line or two per translucent object.
    fn subsurface(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let ss = &self.report.subsurface;
        if ss.links > 0 {
            writeln!(
                f,
                "  nnz(S)             {} (optical distances stored: {}, {} of them links to \
                 cluster nodes; pair by pair: {})",
                ss.nnz, ss.distance_nnz, ss.links, ss.pairwise_distances
            )?;
        } else {
            writeln!(
                f,
                "  nnz(S)             {} (optical distances stored: {})",
                ss.nnz, ss.distance_nnz
            )?;
        }
        for o in &ss.objects {
            Self::object(f, o)?;
        }
        Ok(())
    }

    /// One translucent object's line: its walks when simulated, else its paths and voxels.
    fn object(
        f: &mut std::fmt::Formatter<'_>,
        o: &translux_proto::bundle::SubsurfaceObject,
    ) -> std::fmt::Result {
        if let Some(sim) = &o.simulation {
            return writeln!(
                f,
                "    {:<16} simulated: {} walks ({} scattering events), noise {:.2}% median / \
                 {:.2}% max, {} records, {} entries of S, {} lost, {} cut, max column energy \
                 {:.3}, {:.2} s",
                o.name,
                sim.walks,
                sim.events,
                100.0 * sim.noise_median,
                100.0 * sim.noise_max,
                sim.records,
                o.entries,
                sim.lost,
                sim.cut,
                o.max_column_energy,
                o.seconds
            );
        }
        writeln!(
            f,
            "    {:<16} {} paths, r ≤ {:.4} (scene units), {} voxels ({} inside, size {:.4}), \
             max column energy {:.3}{}, {:.2} s",
            o.name,
            o.method,
            o.truncation_radius,
            o.voxels,
            o.interior_voxels,
            o.voxel_size,
            o.max_column_energy,
            if o.scaled_columns > 0 {
                format!(" ({} columns scaled to 1)", o.scaled_columns)
            } else {
                String::new()
            },
            o.seconds
        )?;
        if o.links > 0 {
            writeln!(
                f,
                "    {:<16} hierarchical S: {} entries, {} of them links to cluster nodes",
                "", o.entries, o.links
            )?;
        }
        if let Some(w) = &o.warning {
            writeln!(f, "    warning: {w}")?;
        }
        Ok(())
    }

    /// T, when computed: its storage, time and the f16 error.
    fn transfer(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let Some(t) = &self.report.transfer else {
            return Ok(());
        };
        let n = self.report.patch_count as u64;
        writeln!(
            f,
            "  transfer T         {} ({}), {:.2} s, LU residual {:.1e}",
            human_bytes(translux_engine::inverse::stored_bytes(n)),
            t.storage,
            t.seconds,
            t.lu_residual
        )?;
        writeln!(
            f,
            "    f16 error        entries: median {:.2e}, max {:.2e}; relight (default \
             lights): max {:.2e}, norm {:.2e}",
            t.median_rel_error, t.max_rel_error, t.relight_max_rel_error, t.relight_rel_error
        )
    }

    /// The bundle's size, the stage times and the memory.
    fn bundle(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = self.report;
        writeln!(
            f,
            "  bundle             {} ({} bytes)",
            human_bytes(r.bundle_bytes),
            r.bundle_bytes
        )?;
        writeln!(f, "  stage times        load {:.2} s", self.load_s)?;
        for s in &r.stages {
            writeln!(f, "                     {} {:.2} s", s.stage, s.seconds)?;
        }
        writeln!(f, "  memory estimate    {}", human_bytes(r.memory_estimate))?;
        if let Some(rss) = r.peak_rss {
            writeln!(f, "  peak memory (RSS)  {}", human_bytes(rss))?;
        }
        Ok(())
    }
}
