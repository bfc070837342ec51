//! The paper's Table 1 on this machine, and translux against a path tracer.
//!
//! In: the paper's four scenes, built here: the Cornell box (`builtin:cornell_paper`), bowls and
//! the Stanford bunny (`builtin:bowls` with the bunny from `../shared/data/` in place of
//! its blob), the flower (`builtin:flower`, thin sheets, the paper's rose) and two horses on
//! a green floor (`../shared/data/horse.obj`). Out: a Markdown table with the paper's
//! columns (patches, precompute F and S and T times, bundle size, relight-only fps with T,
//! relight and translucency-change fps with the solver), the backend and adapter, the error
//! of each relight against the exact solve, and — with Mitsuba 3 installed — how long
//! Mitsuba's path tracer needs to reach the per-vertex error translux has after one
//! relight. The same results go to `bench/results/table1-DATE.{md,json}`.
//!
//! ```sh
//! cargo run --release -p translux-tests --example table1            # ~15 min on 2 cores
//! cargo run --release -p translux-tests --example table1 -- --quick # ~4 min, small sizes
//! ```
//!
//! `--scenes gallop` (not in the default set) precomputes the animated
//! `examples/scenes/horses-gallop.json` (48 frames, two horses crossing a green floor; the
//! paper's horses are a 48-frame gallop) and reports per-frame precompute, memory and
//! playback relights in a table of its own.
//!
//! Flags (`--help` lists them): `--quick`, `--full` (the paper's polygon counts: Cornell
//! 24,640, the whole bunny and 73,256 patches, the rose at 72,474, two horses at ~63,000),
//! `--scenes cornell,bowls,flower,horses`, `--backend auto|cpu|gpu`, `--no-mitsuba`,
//! `--reps N`, `--out DIR` (default `bench/results`), `--t-max N` (largest patch count for
//! which T is computed; the dense LU is O(N³) and needs 22 N² bytes), `--keep DIR` (bundles
//! are kept in DIR, and a scene whose bundle is already there is relit again without its
//! precompute: for profiling relights of long precomputes; the kept bundle is not checked
//! against the scene, so empty DIR after changing either), and `translux-precompute`'s own
//! settings ([`PrecomputeOptions`]: `--subsurface auto|pairwise|hierarchical`, `--s-accuracy`,
//! `--s-link-near`, `--s-link-variation`, `--transport`, `--accuracy`, ...), with the same
//! names, defaults and checks. `--subsurface auto` is, as there, a hierarchical S where T is
//! not computed (above `--t-max` patches) and pairwise where it is; `--patches N` runs every
//! scene at N patches instead of its sizes; `--inverse` computes T at every size.

//! Sizes: by default the bunny (69k triangles) and the horse (97k) are simplified
//! (`simplify_to`) to keep the run short; `--full` runs the paper's polygon counts, which
//! the hierarchical F (the default transport) makes fit: dense F at 73k patches would
//! need ~20 GB.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Parser;
use serde::Serialize;
use serde_json::{Value, json};
use translux_engine::radiosity::Rgb;
use translux_engine::relight;
use translux_engine::scene::Scene;
use translux_precompute::builtin::builtin_scene;
use translux_precompute::options::{PrecomputeOptions, Subsurface};
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::resolve_scene;
use translux_proto::api::RelightStats;
use translux_proto::bundle::MANIFEST_FILE;
use translux_proto::light::Light;
use translux_proto::scene::{
    ExpTerm, Material, MeshRef, ObjectDesc, PatchDensity, Profile, SceneFile, Shape, Transform,
};
use translux_server::backend::{Backend, BackendChoice};
use translux_tests::{mitsuba, scans};

/// A row of the paper's Table 1 (GTX 590, quad-core i7).
#[derive(Debug, Clone, Serialize)]
struct Paper {
    polys: u64,
    precompute: &'static str,
    memory: &'static str,
    t_fps: f64,
    solver_fps: f64,
    change_fps: f64,
}

/// The paper's Cornell box row (its Table 1).
const CORNELL_PAPER: Paper = Paper {
    polys: 24_640,
    precompute: "4 min + 3 min",
    memory: "800 MB",
    t_fps: 90.0,
    solver_fps: 14.0,
    change_fps: 4.0,
};

struct Spec {
    key: &'static str,
    title: &'static str,
    file: SceneFile,
    base_dir: PathBuf,
    patches: u64,
    note: String,
    paper: Paper,
}

#[derive(Debug, Serialize, Default)]
struct Row {
    scene: String,
    patches: u64,
    note: String,
    f_s: f64,
    s_s: f64,
    t_s: Option<f64>,
    t_note: String,
    precompute_s: f64,
    bundle_mib: f64,
    nnz_f: u64,
    nnz_s: u64,
    t_ms: Option<f64>,
    solver_ms: f64,
    solver_iterations: u32,
    solver_name: String,
    change_ms: Option<f64>,
    change_iterations: Option<u32>,
    change_note: String,
    /// Per vertex channel above 1% of the peak: median and max |x − exact| / exact.
    solver_err_median: f64,
    solver_err_max: f64,
    t_err_median: Option<f64>,
    t_err_max: Option<f64>,
    backend: String,
    mitsuba: Option<MitsubaRow>,
    paper: Option<Paper>,
}

#[derive(Debug, Serialize, Clone)]
struct MitsubaRow {
    points: usize,
    reference_spp: u32,
    reference_noise: f64,
    /// translux's one relight (0.5% solver) against the reference: median per-vertex error.
    translux_error: f64,
    translux_ms: f64,
    /// Mitsuba runs: (spp, median error, render seconds for `points`).
    runs: Vec<(u32, f64, f64)>,
    /// Samples per point Mitsuba needs for translux's error (c/√spp fitted to the runs).
    spp_needed: f64,
    /// Seconds Mitsuba needs for that at every vertex of the mesh (rate of the largest run).
    seconds_needed: f64,
    extrapolated: bool,
}

/// The paper's Table 1 on this machine, and translux against a path tracer (the flags:
/// docs/benchmarks.md).
#[derive(Debug, Parser)]
#[command(name = "table1")]
struct Args {
    /// Small sizes (3,000–10,000 patches), for a quick look.
    #[arg(long, conflicts_with = "full")]
    quick: bool,
    /// The paper's polygon counts, meshes unsimplified where the paper's count allows.
    #[arg(long)]
    full: bool,
    /// Run only these scenes (`gallop`, the animated horses, is not in the default set).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "cornell,bowls,flower,horses",
        value_parser = ["cornell", "bowls", "flower", "horses", "cornell_simulated", "gallop"]
    )]
    scenes: Vec<String>,
    /// Which backend relights (`auto`: a hardware GPU if there is one).
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    backend: BackendChoice,
    /// Without the comparison against Mitsuba 3's path tracer.
    #[arg(long)]
    no_mitsuba: bool,
    /// Timed repetitions of each relight.
    #[arg(long, value_name = "N", default_value_t = 5)]
    reps: usize,
    /// Folder of the results (default: `bench/results`).
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Largest patch count for which T is computed (the dense LU is O(N³) and needs 22 N²
    /// bytes).
    #[arg(long, value_name = "N", default_value_t = 6_100)]
    t_max: u64,
    /// Bundles are kept in DIR, and one already there is relit again instead of
    /// precomputed (for profiling the relight of a scene whose precompute is long; the kept
    /// bundle is not checked against the scene).
    #[arg(long, value_name = "DIR")]
    keep: Option<PathBuf>,
    /// `translux-precompute`'s settings. `--patches N`: every scene at N patches instead of
    /// its sizes; `--inverse`: T at every size, not only up to `--t-max`.
    #[command(flatten)]
    precompute: PrecomputeOptions,
}

impl Args {
    fn parse_checked() -> anyhow::Result<Args> {
        let a = Args::parse();
        if a.precompute.max_edge.is_some() {
            bail!("--max-edge: table1 sizes its scenes by patch count (--patches N)");
        }
        // The settings are checked once, before any scene is built.
        a.precompute.params().map_err(anyhow::Error::msg)?;
        a.precompute
            .build_global_thread_pool()
            .map_err(anyhow::Error::msg)?;
        Ok(a)
    }

    /// The precompute's settings for `patches` patches: T up to `--t-max` patches (or at
    /// every size with `--inverse`) unless S is to be hierarchical, which T cannot have.
    fn params(&self, patches: u64) -> anyhow::Result<PrecomputeParams> {
        let o = &self.precompute;
        let inverse =
            o.inverse || (patches <= self.t_max && o.subsurface != Subsurface::Hierarchical);
        let params = PrecomputeOptions {
            patches: Some(patches),
            inverse,
            ..o.clone()
        }
        .params()
        .map_err(anyhow::Error::msg)?;
        Ok(PrecomputeParams {
            progress: true,
            ..params
        })
    }
}

fn obj(name: &str, file: &str, translate: [f32; 3], rotate: [f32; 3], scale: f32) -> ObjectDesc {
    ObjectDesc {
        keyframes: None,
        name: name.to_owned(),
        mesh: MeshRef::Path(file.to_owned()),
        transform: Some(Transform {
            translate,
            rotate_deg: rotate,
            scale: Some(translux_proto::scene::Scale::Uniform(scale)),
        }),
        material: Material::Translucent {
            profile: Profile::Dipole {
                preset: Some("marble".to_owned()),
                sigma_a: None,
                sigma_s_prime: None,
                eta: None,
                scale: None,
            },
            specular: None,
        },
        crease_deg: Some(60.0),
        simplify_to: None,
        orientation: Default::default(),
    }
}

fn specs(a: &Args) -> anyhow::Result<Vec<Spec>> {
    let q = a.quick;
    let full = a.full;
    let mut out = Vec::new();
    for key in &a.scenes {
        match key.as_str() {
            "cornell" => {
                // With T at the largest size T is affordable at, then at the paper's size.
                for patches in if q {
                    vec![3_000, 6_000]
                } else if full {
                    vec![24_640]
                } else {
                    vec![6_000, 24_640]
                } {
                    out.push(Spec {
                        key: "cornell",
                        title: "Cornell box",
                        file: builtin_scene("cornell_paper").context("builtin cornell_paper")?,
                        base_dir: PathBuf::from("."),
                        patches,
                        note: String::new(),
                        paper: CORNELL_PAPER,
                    });
                }
            }
            "cornell_simulated" => {
                // The tall block's marble as random walks (`"type": "simulated"`): the
                // "translucency change" column is then an absorption change (σa re-weights
                // the stored walks), the only edit a simulated S serves without new walks.
                let mut file = builtin_scene("cornell_paper").context("builtin cornell_paper")?;
                for o in &mut file.objects {
                    if o.name == "tall_block" {
                        o.material = translux_proto::parse_json(
                            r#"{"type": "simulated", "preset": "marble"}"#,
                        )?;
                    }
                }
                for patches in if q { vec![3_000] } else { vec![24_640] } {
                    out.push(Spec {
                        key: "cornell_simulated",
                        title: "Cornell box, simulated block",
                        file: file.clone(),
                        base_dir: PathBuf::from("."),
                        patches,
                        note: "the tall block's S from random walks; the change is σa".into(),
                        paper: CORNELL_PAPER,
                    });
                }
            }
            "bowls" => {
                let mut file = builtin_scene("bowls").context("builtin bowls")?;
                let blob = file
                    .objects
                    .iter()
                    .position(|o| o.name == "blob")
                    .context("bowls has a blob")?;
                let material = file.objects[blob].material.clone();
                // --full: the whole scan (69,451 triangles), 73,256 patches as in the paper.
                let tris = if q {
                    Some(4_000)
                } else if full {
                    None
                } else {
                    Some(14_000)
                };
                // The bunny's feet on the table where the blob stood, facing the bowls.
                let mut bunny = scans::bunny(0.0, 0.13, 180.0, material);
                bunny.simplify_to = tris;
                file.objects[blob] = bunny;
                out.push(Spec {
                    key: "bowls",
                    title: "Bowls and bunny",
                    file,
                    base_dir: scans::data_dir(),
                    patches: if q {
                        10_000
                    } else if full {
                        73_256
                    } else {
                        30_000
                    },
                    note: match tris {
                        Some(t) => format!("bunny simplified 69,451 → {t} triangles"),
                        None => "the whole bunny scan (69,451 triangles)".into(),
                    },
                    paper: Paper {
                        polys: 73_256,
                        precompute: "10 min + 12 min",
                        memory: "2.7 GB",
                        t_fps: 28.0,
                        solver_fps: 3.0,
                        change_fps: 0.25,
                    },
                });
            }
            "flower" => out.push(Spec {
                key: "flower",
                title: "Rose (flower, thin sheets)",
                file: builtin_scene("flower").context("builtin flower")?,
                base_dir: PathBuf::from("."),
                patches: if q {
                    8_000
                } else if full {
                    72_474
                } else {
                    30_000
                },
                note: "8 petals as two-sided thin sheets".into(),
                paper: Paper {
                    polys: 72_474,
                    precompute: "15 min + 20 min",
                    memory: "2.7 GB",
                    t_fps: 33.0,
                    solver_fps: 3.0,
                    change_fps: 0.5,
                },
            }),
            "horses" => {
                // --full: ~63k polygons in all as in the paper (each scan 96,966 → 30,000).
                let tris = if q {
                    3_000
                } else if full {
                    30_000
                } else {
                    9_000
                };
                // horse.obj stands along +Z (hooves at z = −0.0764) and runs along Y:
                // −90° about X stands it on our +Y floor; scaled ×2 (0.31 m tall), side
                // by side.
                let mut objects = vec![ObjectDesc {
                    keyframes: None,
                    name: "floor".into(),
                    mesh: MeshRef::Shape(Shape::Quad { size: [1.6, 1.6] }),
                    transform: None,
                    material: Material::Diffuse {
                        albedo: [0.25, 0.55, 0.2],
                        specular: None,
                    },
                    crease_deg: None,
                    simplify_to: None,
                    orientation: Default::default(),
                }];
                for (name, x, yaw) in [("horse_left", -0.13, 10.0), ("horse_right", 0.13, -15.0)] {
                    let mut h = obj(
                        name,
                        "horse.obj",
                        [x, 0.0764 * 2.0, 0.0],
                        [-90.0, yaw, 0.0],
                        2.0,
                    );
                    h.simplify_to = Some(tris);
                    objects.push(h);
                }
                out.push(Spec {
                    key: "horses",
                    title: "Two horses",
                    file: SceneFile {
                        animation: None,
                        name: Some("horses".into()),
                        objects,
                        lights: vec![Light::Point {
                            position: [0.1, 0.8, 0.5],
                            intensity: [2.0, 2.0, 2.0],
                        }],
                        unit_mm: 1000.0,
                        patches: Some(PatchDensity {
                            target: Some(20_000),
                            max_edge: None,
                        }),
                        camera: None,
                    },
                    base_dir: scans::data_dir(),
                    patches: if q {
                        8_000
                    } else if full {
                        63_000
                    } else {
                        26_000
                    },
                    note: format!("each horse simplified 96,966 → {tris} triangles"),
                    paper: Paper {
                        polys: 63_000,
                        precompute: "9 min + 10 min",
                        memory: "2.4 GB",
                        t_fps: 43.0,
                        solver_fps: 5.0,
                        change_fps: 0.4,
                    },
                });
            }
            // Measured on its own (`measure_gallop`): a sequence, not one bundle.
            "gallop" => {}
            _ => unreachable!("checked by clap"),
        }
    }
    if let Some(n) = a.precompute.patches {
        for s in &mut out {
            s.patches = n;
        }
        out.dedup_by(|x, y| x.key == y.key && x.patches == y.patches);
    }
    Ok(out)
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
    median(&mut t)
}

/// The median (the upper one of an even count) of a non-empty list.
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Sorted iteration counts as "0 ×2, 1 ×7, 2 ×3".
fn iteration_counts(sorted: &[u32]) -> String {
    sorted
        .chunk_by(|a, b| a == b)
        .map(|run| format!("{} ×{}", run[0], run.len()))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The scene's default lights, the point-like ones moved by a few centimetres for rep `r`
/// (a user dragging a light).
fn moved_lights(lights: &[Light], r: usize) -> Vec<Light> {
    let d = 0.01 * ((r % 7) as f32 - 3.0);
    lights
        .iter()
        .map(|l| match l.clone() {
            Light::Point {
                mut position,
                intensity,
            } => {
                position[0] += d;
                Light::Point {
                    position,
                    intensity,
                }
            }
            Light::Spot {
                mut position,
                intensity,
                direction,
                inner_deg,
                outer_deg,
            } => {
                position[0] += d;
                Light::Spot {
                    position,
                    intensity,
                    direction,
                    inner_deg,
                    outer_deg,
                }
            }
            other => other,
        })
        .collect()
}

/// `p` with its mean free path scaled by `s` (more translucent for s > 1): the dipole's own
/// `scale`; exponentials and tables widened by s with their total reflectance kept.
fn scaled(p: &Profile, s: f32) -> Profile {
    match p.clone() {
        Profile::Dipole {
            preset,
            sigma_a,
            sigma_s_prime,
            eta,
            scale,
        } => Profile::Dipole {
            preset,
            sigma_a,
            sigma_s_prime,
            eta,
            scale: Some(scale.unwrap_or(1.0) * s),
        },
        Profile::Exponentials { terms } => Profile::Exponentials {
            terms: terms
                .into_iter()
                .map(|t| ExpTerm {
                    a: t.a.map(|v| v / (s * s)),
                    b: t.b.map(|v| v / s),
                })
                .collect(),
        },
        Profile::Table { radius_mm, values } => Profile::Table {
            radius_mm: radius_mm.iter().map(|r| r * s).collect(),
            values: values.iter().map(|v| v.map(|x| x / (s * s))).collect(),
        },
    }
}

/// Overrides that change the translucency of every translucent object by `s`.
fn translucency(scene: &Scene, s: f32) -> serde_json::Map<String, Value> {
    let mut m = serde_json::Map::new();
    for o in &scene.bundle.manifest().objects {
        let changed = match &o.material {
            Material::Translucent { profile, .. } => Some(Material::Translucent {
                profile: scaled(profile, s),
                specular: None,
            }),
            Material::ThinSheet {
                reflectance,
                transmittance,
                thickness_mm,
                ..
            } => Some(Material::ThinSheet {
                reflectance: scaled(reflectance, s),
                transmittance: scaled(transmittance, s),
                thickness_mm: *thickness_mm,
                specular: None,
            }),
            Material::Heterogeneous {
                materials, pattern, ..
            } => Some(Material::Heterogeneous {
                materials: materials.iter().map(|p| scaled(p, s)).collect(),
                pattern: pattern.clone(),
                specular: None,
            }),
            // Absorption only: σa / f with f in [1, 9), above the walks' floor (σa / 16)
            // however large s grows.
            Material::Simulated { .. } => {
                let medium = translux_engine::simulated::SimMedium::of(&o.material)
                    .expect("a simulated material has a medium");
                let mut m = serde_json::to_value(&o.material).expect("material JSON");
                let f = 1.0 + (s - 1.0).rem_euclid(8.0);
                m["sigma_a"] = json!(medium.sigma_a.map(|v| v / f));
                Some(serde_json::from_value(m).expect("simulated override"))
            }
            _ => None,
        };
        if let Some(c) = changed {
            m.insert(
                o.name.clone(),
                serde_json::to_value(c).expect("material JSON"),
            );
        }
    }
    m
}

fn run(
    scene: &Scene,
    body: &Value,
    tolerance: Option<f32>,
) -> anyhow::Result<relight::RelightOutput> {
    let req = translux_proto::parse_json(&body.to_string()).map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut plan = relight::plan(scene, req).map_err(|e| anyhow::anyhow!("{e:?}"))?;
    if let Some(t) = tolerance {
        plan.tolerance = t;
    }
    relight::run(scene, &plan).map_err(|e| anyhow::anyhow!("{e:?}"))
}

/// Median and max of |a − b| / b over vertex channels with b above 1% of b's peak.
fn rel_err(a: &[Rgb], b: &[Rgb]) -> (f64, f64) {
    let peak = b.iter().flatten().fold(0.0f32, |m, &x| m.max(x));
    let mut e: Vec<f64> = a
        .iter()
        .zip(b)
        .flat_map(|(x, y)| (0..3).map(move |c| (x[c], y[c])))
        .filter(|&(_, y)| y > 0.01 * peak)
        .map(|(x, y)| f64::from((x - y).abs() / y))
        .collect();
    if e.is_empty() {
        return (0.0, 0.0);
    }
    e.sort_by(f64::total_cmp);
    (e[e.len() / 2], e[e.len() - 1])
}

fn measure(spec: &Spec, a: &Args, work: &Path, backend: &Backend) -> anyhow::Result<Row> {
    let loaded = resolve_scene(
        spec.file.clone(),
        &spec.base_dir,
        spec.key.to_owned(),
        format!("table1:{}", spec.key),
    )?;
    let dir = work.join(format!("{}-{}", spec.key, spec.patches));
    let params = a.params(spec.patches)?;
    let inverse = params.inverse;
    eprintln!(
        "== {} at {} patches{}",
        spec.title,
        spec.patches,
        if inverse { ", with T" } else { "" }
    );
    // With --keep, a bundle already kept for this scene and size is relit again (its
    // precompute figures are then its manifest's stage times).
    let reuse = a.keep.is_some() && dir.join(MANIFEST_FILE).is_file();
    let t0 = Instant::now();
    let nnz_f = if reuse {
        eprintln!("   reusing the bundle kept in {}", dir.display());
        None
    } else {
        Some(precompute(&loaded, &dir, &params)?.nnz_f)
    };
    let precompute_s = t0.elapsed().as_secs_f64();
    let scene = Scene::open_with(spec.key, &dir, &backend.resources())?;
    let m = scene.bundle.manifest();
    let precompute_s = if reuse {
        m.stages.iter().map(|s| s.seconds).sum()
    } else {
        precompute_s
    };
    let nnz_f = nnz_f.unwrap_or_else(|| scene.bundle.form_factors().nnz() as u64);
    let stage = |names: &[&str]| -> f64 {
        m.stages
            .iter()
            .filter(|s| names.iter().any(|n| s.stage.contains(n)))
            .map(|s| s.seconds)
            .sum()
    };
    let n = m.patch_count;
    let mut row = Row {
        scene: spec.title.to_owned(),
        patches: n,
        note: spec.note.clone(),
        f_s: stage(&["form factors"]),
        s_s: stage(&["distances", "subsurface", "sheet"]),
        t_s: inverse.then(|| stage(&["inverse"])),
        t_note: if inverse {
            String::new()
        } else {
            format!(
                "T not computed above {} patches: dense LU ~{:.0} min (cubic from the \
                 6,000-patch row) and {:.1} GiB",
                a.t_max,
                40.0 / 60.0 * (n as f64 / 6_024.0).powi(3),
                22.0 * (n as f64).powi(2) / (1u64 << 30) as f64
            )
        },
        precompute_s,
        bundle_mib: scene.bundle.total_bytes() as f64 / (1 << 20) as f64,
        nnz_f,
        nnz_s: scene.bundle.subsurface().nnz() as u64,
        backend: backend.name().to_owned(),
        paper: Some(spec.paper.clone()),
        ..Default::default()
    };
    // S per translucent patch (objects with a subsurface record; thin sheets included).
    {
        let (mut patches, mut entries, mut links) = (0u64, 0u64, 0u64);
        for so in &m.subsurface.objects {
            if let Some(o) = m.objects.iter().find(|o| o.name == so.name) {
                patches += o.patch_count;
                entries += so.entries;
                links += so.links;
            }
        }
        if patches > 0 {
            let s_note = format!(
                "S {}: {:.0} entries per translucent patch ({:.1}% of them links to cluster \
                 nodes), S {:.0} MiB",
                if m.subsurface.links > 0 {
                    "hierarchical"
                } else {
                    "pairwise"
                },
                entries as f64 / patches as f64,
                100.0 * links as f64 / entries.max(1) as f64,
                (m.subsurface.nnz * 16) as f64 / (1u64 << 20) as f64
            );
            let s_note = if m.subsurface.links > 0 {
                format!(
                    "{s_note}, optical distances {} against {} pair by pair",
                    m.subsurface.distance_nnz, m.subsurface.pairwise_distances
                )
            } else {
                s_note
            };
            row.note = if row.note.is_empty() {
                s_note
            } else {
                format!("{}; {s_note}", row.note)
            };
        }
    }
    let lights = m.lights.clone();
    // Exact: a tight iterative solve of the default lights.
    let exact = run(&scene, &json!({"solver": "iterative"}), Some(1e-7))?;
    // Relight with T (light moved each time).
    if scene.bundle.transfer().is_some() {
        row.t_ms = Some(time_ms(a.reps, |r| {
            run(
                &scene,
                &json!({"solver": "inverse", "lights": moved_lights(&lights, r)}),
                None,
            )
            .expect("relight with T");
        }));
        let with_t = run(&scene, &json!({"solver": "inverse"}), None)?;
        let (med, max) = rel_err(&with_t.radiance, &exact.radiance);
        (row.t_err_median, row.t_err_max) = (Some(med), Some(max));
    }
    // Relight with the solver (warm-started from the previous light).
    let mut last = None;
    row.solver_ms = time_ms(a.reps, |r| {
        let o = run(
            &scene,
            &json!({"solver": "iterative", "lights": moved_lights(&lights, r)}),
            None,
        )
        .expect("relight with the solver");
        last = Some(o.stats);
    });
    if let Some(st) = last {
        row.solver_iterations = st.iterations;
        row.solver_name = st.solver.clone();
    }
    // Error of the 0.5% solve, cold (the worst case: no warm start).
    let cold = {
        let fresh = Scene::open_with(spec.key, &dir, &backend.resources())?;
        run(&fresh, &json!({"solver": "iterative"}), None)?
    };
    (row.solver_err_median, row.solver_err_max) = rel_err(&cold.radiance, &exact.radiance);
    // Translucency change: a new scale each time, so S is rebuilt every time. The scales
    // are a slider dragged steadily (0.9, then 1, 1.137, 1.274, …): the untimed warm-up is
    // the drag's second step, as a user's first moves are (a jump to 138× would start from
    // an unrelated answer that the median then carried).
    if !translucency(&scene, 1.0).is_empty() {
        // The first change also reduces S's entries to radial terms (engine::sterms), once
        // per scene: timed on its own, then the later changes.
        let first = Instant::now();
        run(
            &scene,
            &json!({"solver": "iterative", "materials": translucency(&scene, 0.9)}),
            None,
        )
        .expect("translucency change");
        let first_ms = first.elapsed().as_secs_f64() * 1e3;
        // Every timed step's stats (not the warm-up's): the note gives the parts' medians
        // and how many iterations the steps took, not one step's, which varies by tens of
        // milliseconds with its iterations.
        let mut steps = Vec::new();
        row.change_ms = Some(time_ms(a.reps, |r| {
            let step = if r == usize::MAX { 0.0 } else { r as f32 + 1.0 };
            let s = 1.0 + 0.137 * step;
            let o = run(
                &scene,
                &json!({"solver": "iterative", "materials": translucency(&scene, s)}),
                None,
            )
            .expect("translucency change");
            if r != usize::MAX {
                steps.push(o.stats);
            }
        }));
        if !steps.is_empty() {
            let part =
                |f: fn(&RelightStats) -> f64| median(&mut steps.iter().map(f).collect::<Vec<_>>());
            let mut iterations: Vec<u32> = steps.iter().map(|s| s.iterations).collect();
            iterations.sort_unstable();
            row.change_iterations = Some(iterations[iterations.len() / 2]);
            row.change_note = format!(
                "medians of {} steps: S rebuild {:.0} ms + solve {:.0} ms + direct light {:.0} \
                 ms; iterations per step {} (the first change, which reduces S to radial \
                 terms: {first_ms:.0} ms)",
                steps.len(),
                part(|s| s.materials_ms),
                part(|s| s.solve_ms),
                part(|s| s.direct_ms),
                iteration_counts(&iterations),
            );
        }
    }
    if !a.no_mitsuba {
        row.mitsuba = against_mitsuba(&scene, a.quick)?;
    }
    drop(scene);
    if a.keep.is_none() {
        std::fs::remove_dir_all(&dir).ok();
    }
    Ok(row)
}

/// translux after one relight vs Mitsuba after s samples per point, on the scene with its
/// translucent objects opaque at their profile's albedo (this model's S has no Mitsuba
/// counterpart; the opaque scene has the same geometry, F, lights and inter-reflection).
fn against_mitsuba(scene: &Scene, quick: bool) -> anyhow::Result<Option<MitsubaRow>> {
    let m = scene.bundle.manifest();
    let mut over = serde_json::Map::new();
    let mut diffuse = Vec::new();
    for o in &m.objects {
        if !matches!(
            o.material,
            Material::Diffuse { .. } | Material::Emitter { .. }
        ) {
            over.insert(
                o.name.clone(),
                json!({"type": "diffuse", "albedo": o.albedo}),
            );
            diffuse.push((
                o.name.clone(),
                json!({"type": "diffuse", "albedo": o.albedo}),
            ));
        }
    }
    let lights = m.lights.clone();
    let body = json!({"solver": "iterative", "lights": lights, "materials": over});
    let t0 = Instant::now();
    let ours = run(scene, &body, None)?;
    let ours_ms = t0.elapsed().as_secs_f64() * 1e3;
    let (vp, vn) = mitsuba::vertex_queries(&scene.bundle);
    let total_vertices = vp.len();
    let want = if quick { 150 } else { 300 };
    let step = (vp.len() / want).max(1);
    let (vp, vn, mine) = (
        mitsuba::every(&vp, step),
        mitsuba::every(&vn, step),
        mitsuba::every(&ours.radiance, step),
    );
    let objects = mitsuba::objects_with(&scene.bundle, &diffuse);
    let input = |spp: u32, seed: u32| {
        json!({"objects": objects, "lights": lights,
               "queries": {"points": vp, "normals": vn},
               "spp": spp, "max_depth": 64, "rr_depth": 16, "seed": seed})
    };
    let reference_spp = if quick { 4096 } else { 16384 };
    eprintln!(
        "   Mitsuba reference: {} points x {reference_spp} paths",
        vp.len()
    );
    let Some(reference) = mitsuba::run(&input(reference_spp, 1)) else {
        return Ok(None);
    };
    let te = mitsuba::errors(&mine, &reference, 0.05);
    let mut runs = Vec::new();
    for spp in [4u32, 16, 64, 256, 1024] {
        let Some(r) = mitsuba::run(&input(spp, 100 + spp)) else {
            return Ok(None);
        };
        // Mitsuba's estimate at spp against the reference, the same statistic as translux's.
        let e = mitsuba::errors(&r.radiance, &reference, 0.05);
        runs.push((spp, e.median, r.render_seconds));
    }
    // Error ∝ 1/√spp: c from the runs (median of e·√spp), then the spp for translux's error.
    let mut cs: Vec<f64> = runs
        .iter()
        .map(|&(s, e, _)| e * f64::from(s).sqrt())
        .collect();
    cs.sort_by(f64::total_cmp);
    let c = cs[cs.len() / 2];
    let spp_needed = (c / te.median).powi(2);
    let &(big_spp, _, big_s) = runs.last().expect("runs");
    let per_sample = big_s / (f64::from(big_spp) * vp.len() as f64);
    Ok(Some(MitsubaRow {
        points: vp.len(),
        reference_spp,
        reference_noise: te.reference_noise,
        translux_error: te.median,
        translux_ms: ours_ms,
        runs,
        spp_needed,
        seconds_needed: per_sample * spp_needed * total_vertices as f64,
        extrapolated: spp_needed > f64::from(big_spp),
    }))
}

fn fps(ms: f64) -> String {
    format!("{:.1} ({ms:.1} ms)", 1e3 / ms)
}

fn markdown(rows: &[Row], machine: &str, backend: &Backend) -> String {
    let mut s = String::new();
    let opt = |v: Option<f64>, f: &dyn Fn(f64) -> String| v.map_or("—".to_owned(), f);
    s += &format!("## Table 1 on this machine — {machine}\n\n");
    s += &format!("Backend: {}.\n\n", backend.describe());
    s += "| scene | patches | precompute F + S (+ T) | bundle | relight only, T: fps | relight, solver: fps (it.) | translucency change: fps (it.) | error vs exact: T / solver (median, max) | backend |\n";
    s += "|---|---|---|---|---|---|---|---|---|\n";
    for r in rows {
        s += &format!(
            "| {} | {} | {:.1} s + {:.1} s{} | {:.0} MiB | {} | {} ({}) | {} | {} / {:.2}%, {:.1}% | {} |\n",
            r.scene,
            r.patches,
            r.f_s,
            r.s_s,
            r.t_s.map_or(String::new(), |t| format!(" + {t:.1} s")),
            r.bundle_mib,
            opt(r.t_ms, &fps),
            fps(r.solver_ms),
            r.solver_iterations,
            r.change_ms.map_or("—".to_owned(), |ms| format!(
                "{} ({})",
                fps(ms),
                r.change_iterations.unwrap_or(0)
            )),
            match (r.t_err_median, r.t_err_max) {
                (Some(a), Some(b)) => format!("{:.3}%, {:.2}%", 100.0 * a, 100.0 * b),
                _ => "—".to_owned(),
            },
            100.0 * r.solver_err_median,
            100.0 * r.solver_err_max,
            r.backend
        );
    }
    s += "\nThe paper (GTX 590 + quad-core i7, Table 1):\n\n";
    s += "| scene | polygons | precompute | memory | relight only (fps) | relight / translucency change (fps) |\n|---|---|---|---|---|---|\n";
    let mut seen = Vec::new();
    for r in rows {
        if let Some(p) = &r.paper
            && !seen.contains(&r.scene)
        {
            seen.push(r.scene.clone());
            s += &format!(
                "| {} | {} | {} | {} | {} | {} / {} |\n",
                r.scene, p.polys, p.precompute, p.memory, p.t_fps, p.solver_fps, p.change_fps
            );
        }
    }
    s += "\nNotes:\n";
    for r in rows {
        let mut notes = Vec::new();
        if !r.note.is_empty() {
            notes.push(r.note.clone());
        }
        if !r.t_note.is_empty() {
            notes.push(r.t_note.clone());
        }
        if !r.change_note.is_empty() {
            notes.push(format!("translucency change: {}", r.change_note));
        }
        notes.push(format!(
            "nnz(F) {}, nnz(S) {}, solver {}; whole precompute {:.1} s",
            r.nnz_f, r.nnz_s, r.solver_name, r.precompute_s
        ));
        s += &format!(
            "- {} ({} patches): {}.\n",
            r.scene,
            r.patches,
            notes.join("; ")
        );
    }
    let mits: Vec<&Row> = rows.iter().filter(|r| r.mitsuba.is_some()).collect();
    if !mits.is_empty() {
        s += "\n### Against Mitsuba 3's path tracer (llvm_ad_rgb, same threads)\n\n";
        s += "Translucent objects opaque at their profile's albedo (Mitsuba has no counterpart \
              of S), same geometry and lights. translux: one relight (0.5% solver). Mitsuba: \
              median per-vertex error against its own high-sample reference at 4–1024 paths \
              per point, fitted as c/√spp; the time is for every vertex of the mesh.\n\n";
        s += "| scene | points (reference spp, noise) | translux error | translux ms | Mitsuba (spp: error) | Mitsuba spp for the same error | Mitsuba time for it | ratio |\n|---|---|---|---|---|---|---|---|\n";
        for r in mits {
            let m = r.mitsuba.as_ref().expect("filtered");
            let runs: Vec<String> = m
                .runs
                .iter()
                .map(|(s, e, _)| format!("{s}: {:.1}%", 100.0 * e))
                .collect();
            s += &format!(
                "| {} | {} ({}, {:.2}%) | {:.2}% | {:.0} | {} | {:.0}{} | {:.1} s | {:.0}× |\n",
                r.scene,
                m.points,
                m.reference_spp,
                100.0 * m.reference_noise,
                100.0 * m.translux_error,
                m.translux_ms,
                runs.join(", "),
                m.spp_needed,
                if m.extrapolated {
                    " (extrapolated)"
                } else {
                    ""
                },
                m.seconds_needed,
                m.seconds_needed * 1e3 / m.translux_ms
            );
        }
    }
    s
}

fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|c| {
            c.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_owned())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    format!("{} threads, {cpu}", rayon::current_num_threads())
}

fn main() -> anyhow::Result<()> {
    // Logs only when asked for (RUST_LOG, e.g. translux_server=debug for the device
    // rebuild's timings).
    if std::env::var_os("RUST_LOG").is_some() {
        tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
            .with_writer(std::io::stderr)
            .init();
    }
    let a = Args::parse_checked()?;
    let b = Backend::start(a.backend, None).map_err(|e| anyhow::anyhow!("--backend: {e}"))?;
    eprintln!("backend: {}", b.describe());
    // Bundles go beside the build (they are large), in a folder made if missing: with
    // CARGO_TARGET_DIR set elsewhere, the checkout has no target/.
    let scratch = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target");
    std::fs::create_dir_all(&scratch)
        .with_context(|| format!("cannot create {}", scratch.display()))?;
    // The temporary folder (without --keep) lives until the end of main.
    let (work, _temp) = match &a.keep {
        Some(dir) => {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("--keep: cannot create {}", dir.display()))?;
            (dir.clone(), None)
        }
        None => {
            let t = tempfile::Builder::new()
                .prefix("table1-")
                .tempdir_in(&scratch)?;
            (t.path().to_path_buf(), Some(t))
        }
    };
    let gallop = if a.scenes.iter().any(|s| s == "gallop") {
        Some(measure_gallop(&a, &work, &b)?)
    } else {
        None
    };
    let mut rows = Vec::new();
    for spec in specs(&a)? {
        let row = measure(&spec, &a, &work, &b)
            .with_context(|| format!("{} at {} patches", spec.title, spec.patches))?;
        eprintln!("{}", serde_json::to_string(&row)?);
        rows.push(row);
    }
    let machine = machine();
    let date = today();
    let mut md = markdown(&rows, &format!("{date}, {machine}"), &b);
    if let Some(g) = &gallop {
        md += &gallop_markdown(g);
    }
    println!("{md}");
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../bench/results"));
    std::fs::create_dir_all(&out)?;
    let stem = if a.scenes == ["gallop"] {
        if a.quick {
            "table1-gallop-quick"
        } else {
            "table1-gallop"
        }
    } else if a.quick {
        "table1-quick"
    } else if a.full {
        "table1-full"
    } else {
        "table1"
    };
    let md_path = out.join(format!("{stem}-{date}.md"));
    std::fs::write(&md_path, &md)?;
    let mut doc = BTreeMap::new();
    doc.insert("date", json!(date));
    doc.insert("machine", json!(machine));
    doc.insert("rows", serde_json::to_value(&rows)?);
    if let Some(g) = &gallop {
        doc.insert("gallop", serde_json::to_value(g)?);
    }
    std::fs::write(
        out.join(format!("{stem}-{date}.json")),
        serde_json::to_string_pretty(&doc)?,
    )?;
    eprintln!("saved {} and .json", md_path.display());
    Ok(())
}

/// Today's date (UTC) as YYYY-MM-DD, from the system clock (days since 1970 to a civil
/// date; no date crate for one line of a file name).
fn today() -> String {
    let days = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs() / 86_400) as i64;
    // Howard Hinnant's days-from-civil inverse.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!("{y:04}-{m:02}-{d:02}")
}

/// The animated horses (`--scenes gallop`): what a sequence costs per frame.
#[derive(Debug, Serialize)]
struct GallopRow {
    frames: usize,
    /// Distinct frame bundles precomputed (frames that share one are not counted).
    computed: usize,
    patches: u64,
    frame_s_mean: f64,
    frame_s_max: f64,
    /// F and S of one frame (its stages), seconds, mean over frames.
    f_s_mean: f64,
    s_s_mean: f64,
    bundle_mib_per_frame: f64,
    bundles_mib: f64,
    peak_rss_mib: Option<f64>,
    /// Opening every frame (verify, map, BVH), s.
    open_s: f64,
    /// Each frame relit once in order, cold (its first relight): the playback rate.
    playback_fps: f64,
    /// One frame relit with a moved light, warm solver.
    relight_fps: f64,
}

/// Precomputes the gallop sequence (`--quick`: each horse 1,000 triangles and 3,000
/// patches a frame, else 4,000 and 9,000), opens every frame and relights them in order, as
/// the viewer's playback does.
fn measure_gallop(a: &Args, work: &Path, backend: &Backend) -> anyhow::Result<GallopRow> {
    use translux_precompute::sequence::precompute_sequence;
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/scenes/horses-gallop.json");
    let mut src = translux_precompute::scene::read_scene_file(&file)?;
    // Each horse simplified to `tris` triangles (every triangle is at least one patch).
    let (tris, patches) = if a.quick {
        (1_000, 3_000)
    } else {
        (4_000, 9_000)
    };
    for o in &mut src.file.objects {
        if o.simplify_to.is_some() {
            o.simplify_to = Some(tris);
        }
    }
    // No T for a sequence (unless --inverse); S as `translux-precompute` makes it.
    let patches = a.precompute.patches.unwrap_or(patches);
    let params = PrecomputeOptions {
        patches: Some(patches),
        ..a.precompute.clone()
    }
    .params()
    .map_err(anyhow::Error::msg)?;
    let dir = work.join("gallop");
    eprintln!("== animated horses: 48 frames at {patches} patches each");
    let t0 = Instant::now();
    let report = precompute_sequence(&src, &dir, &params, &|f, n| {
        eprintln!(
            "frame {} of {n}: {:?} in {:.2} s",
            f.frame + 1,
            f.outcome,
            f.seconds
        );
    })?;
    let total_s = t0.elapsed().as_secs_f64();
    let (frame_s_mean, frame_s_max) = report.seconds_per_frame().unwrap_or_default();
    let t = Instant::now();
    let manifest: translux_proto::animation::SequenceManifest = serde_json::from_str(
        &std::fs::read_to_string(dir.join(translux_proto::animation::SEQUENCE_FILE))?,
    )?;
    let mut opened: BTreeMap<String, std::sync::Arc<Scene>> = BTreeMap::new();
    let mut frames = Vec::new();
    for f in &manifest.frames {
        let s = match opened.get(f) {
            Some(s) => s.clone(),
            None => {
                let s = std::sync::Arc::new(Scene::open_with(
                    "gallop",
                    &dir.join(f),
                    &backend.resources(),
                )?);
                opened.insert(f.clone(), s.clone());
                s
            }
        };
        frames.push(s);
    }
    let open_s = t.elapsed().as_secs_f64();
    let (mut f_s, mut s_s, mut bytes, mut n) = (0.0, 0.0, 0u64, 0u64);
    for s in opened.values() {
        let m = s.bundle.manifest();
        for st in &m.stages {
            if st.stage.contains("form factors") {
                f_s += st.seconds;
            } else if ["distances", "subsurface"]
                .iter()
                .any(|k| st.stage.contains(k))
            {
                s_s += st.seconds;
            }
        }
        bytes += s.bundle.total_bytes();
        n = n.max(m.patch_count);
    }
    let k = opened.len().max(1) as f64;
    let t = Instant::now();
    for s in &frames {
        run(s, &json!({}), None)?;
    }
    let playback_fps = frames.len() as f64 / t.elapsed().as_secs_f64();
    let s0 = &frames[0];
    let lights = s0.bundle.manifest().lights.clone();
    run(s0, &json!({"lights": lights}), None)?;
    let t = Instant::now();
    for r in 0..a.reps.max(1) {
        let moved = moved_lights(&lights, r);
        run(s0, &json!({"lights": moved}), None)?;
    }
    let relight_fps = a.reps.max(1) as f64 / t.elapsed().as_secs_f64();
    eprintln!("sequence precomputed in {total_s:.1} s");
    Ok(GallopRow {
        frames: report.frames.len(),
        computed: report.computed(),
        patches: n,
        frame_s_mean,
        frame_s_max,
        f_s_mean: f_s / k,
        s_s_mean: s_s / k,
        bundle_mib_per_frame: bytes as f64 / k / (1u64 << 20) as f64,
        bundles_mib: bytes as f64 / (1u64 << 20) as f64,
        peak_rss_mib: translux_precompute::pipeline::peak_rss()
            .map(|b| b as f64 / (1u64 << 20) as f64),
        open_s,
        playback_fps,
        relight_fps,
    })
}

fn gallop_markdown(g: &GallopRow) -> String {
    let mut s = String::from("\n## Animated scene: two horses galloping (`--scenes gallop`)\n\n");
    s += "| frames (precomputed) | patches per frame | precompute per frame: mean, max (F + S) | bundle per frame / all frames | peak memory | open every frame | playback: each frame relit once | relight one frame, light moved |\n";
    s += "|---|---|---|---|---|---|---|---|\n";
    s += &format!(
        "| {} ({}) | {} | {:.2} s, {:.2} s ({:.2} s + {:.2} s) | {:.1} MiB / {:.0} MiB | {} | {:.1} s | {:.1} fps | {:.1} fps |\n",
        g.frames,
        g.computed,
        g.patches,
        g.frame_s_mean,
        g.frame_s_max,
        g.f_s_mean,
        g.s_s_mean,
        g.bundle_mib_per_frame,
        g.bundles_mib,
        g.peak_rss_mib.map_or("—".into(), |m| format!("{m:.0} MiB")),
        g.open_s,
        g.playback_fps,
        g.relight_fps
    );
    s += "\nThe paper (Table 1, horses ~63k polygons, one frame; GTX 590): precompute 9 min + 10 min, 2.4 GB, 43 fps relight with T, 5 fps with the solver.\n";
    s
}
