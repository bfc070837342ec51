//! Mitsuba 3 as an independent reference (`tests/validation/mitsuba_reference.py`, which
//! shares no code with translux): scene conversion from a bundle, the call, and the error
//! statistics the validation tests and the benchmark report.
//!
//! Mitsuba must be installed (`pip install mitsuba`, Debian's `libllvm19`; `.ci/run` does
//! both). Without it [`run`] panics and says what to install, unless
//! `TRANSLUX_SKIP_MITSUBA=1` (CI never sets it).
//!
//! The validation tests take Mitsuba's answers through [`stored`]: an answer rendered once
//! is kept in the repository (`tests/validation/references/`, tens of KiB each), named by a
//! digest of its whole input, the reference script and the pinned Mitsuba version, so CI
//! compares against the same Mitsuba render without spending its minutes on it again. Any
//! change to what Mitsuba would be asked names a new file, and the test renders it.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::{Value, json};
use translux_engine::radiosity::Rgb;
use translux_proto::bundle::Bundle;
use translux_proto::scene::Material;

fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("validation/mitsuba_reference.py")
}

/// Mitsuba's answer for a set of query points.
#[derive(Debug)]
pub struct Reference {
    pub radiance: Vec<Rgb>,
    pub std_error: Vec<Rgb>,
    /// Build and render time (JIT included), s.
    pub seconds: f64,
    /// Rendering alone, s.
    pub render_seconds: f64,
    /// Queries whose ray did not hit a front face at the point (left out).
    pub suspect: Vec<usize>,
}

/// Runs the reference script on `input`; `None` only when Mitsuba is missing and
/// `TRANSLUX_SKIP_MITSUBA=1`.
pub fn run(input: &Value) -> Option<Reference> {
    render(input).map(|bytes| parse(&bytes))
}

/// Mitsuba's answer for `input` from the reference store ([`STORE`]) when it holds one,
/// else rendered ([`run`]) and added to the store (with a line on stderr asking for the new
/// file to be committed). `TRANSLUX_MITSUBA_RENDER=1` renders every input again and
/// replaces what the store holds.
///
/// A stored answer is named by the SHA-256 of everything that decides it: the input as
/// sent (geometry, materials, lights, query points, samples, seed), the reference script's
/// bytes and the Mitsuba version `scripts/test` pins. A changed mesh, probe, light, sample
/// count, script or Mitsuba version names another file, so a stale answer is never read:
/// the test renders anew.
pub fn stored(input: &Value) -> Option<Reference> {
    let path = store_path(input);
    let fresh = std::env::var("TRANSLUX_MITSUBA_RENDER").as_deref() == Ok("1");
    if !fresh && let Ok(bytes) = std::fs::read(&path) {
        return Some(parse(&bytes));
    }
    let bytes = render(input)?;
    let reference = parse(&bytes);
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(&path, &bytes).unwrap();
    eprintln!(
        "Mitsuba rendered in {:.1} s; stored as {} (commit it: CI reads it instead of rendering)",
        reference.seconds,
        path.display()
    );
    Some(reference)
}

/// Where Mitsuba's answers are stored, in the repository: `tests/validation/references/`.
pub const STORE: &str = "validation/references";

/// The store's file for `input` (see [`stored`]).
fn store_path(input: &Value) -> PathBuf {
    use sha2::{Digest, Sha256};
    let mut h = Sha256::new();
    h.update(std::fs::read(script()).unwrap());
    h.update(pinned_mitsuba().as_bytes());
    h.update(serde_json::to_vec(input).unwrap());
    let hex: String = h.finalize()[..16]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join(STORE)
        .join(format!("{hex}.json"))
}

/// The `mitsuba==…` requirement `scripts/test` installs.
fn pinned_mitsuba() -> String {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/test");
    let text = std::fs::read_to_string(&script).unwrap();
    let at = text
        .find("'mitsuba==")
        .unwrap_or_else(|| panic!("{} pins no Mitsuba version", script.display()));
    text[at + 1..].split('\'').next().unwrap().to_owned()
}

/// The reference script on `input`: its answer (OUT.json's bytes); `None` only when
/// Mitsuba is missing and `TRANSLUX_SKIP_MITSUBA=1`.
fn render(input: &Value) -> Option<Vec<u8>> {
    let dir = tempfile::tempdir().unwrap();
    let (inp, out) = (dir.path().join("in.json"), dir.path().join("out.json"));
    std::fs::write(&inp, serde_json::to_vec(input).unwrap()).unwrap();
    let python = std::env::var("TRANSLUX_PYTHON").unwrap_or_else(|_| "python3".to_owned());
    let run = Command::new(&python)
        .arg(script())
        .arg(&inp)
        .arg(&out)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {python}: {e} (set TRANSLUX_PYTHON)"));
    let stderr = String::from_utf8_lossy(&run.stderr);
    if run.status.code() == Some(3) {
        if std::env::var("TRANSLUX_SKIP_MITSUBA").as_deref() == Ok("1") {
            eprintln!("Mitsuba validation skipped (TRANSLUX_SKIP_MITSUBA=1): {stderr}");
            return None;
        }
        panic!(
            "Mitsuba 3 is not available: {stderr}\ninstall it with `pip install mitsuba` and \
             `apt-get install libllvm19` (bash .ci/run does), or set TRANSLUX_SKIP_MITSUBA=1"
        );
    }
    assert!(
        run.status.success(),
        "mitsuba_reference.py failed: {stderr}"
    );
    Some(std::fs::read(&out).unwrap())
}

/// The reference script's answer (its OUT.json).
fn parse(bytes: &[u8]) -> Reference {
    let v: Value = serde_json::from_slice(bytes).unwrap();
    let rgb = |key: &str| -> Vec<Rgb> {
        v[key]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| {
                let c = c.as_array().unwrap();
                [0, 1, 2].map(|k| c[k].as_f64().unwrap() as f32)
            })
            .collect()
    };
    let radiance = rgb("radiance");
    // Points where the query ray does not meet a front face at the point: floor under a
    // box standing on it (the box's bottom coincides with the floor). Left out of the
    // comparison, and counted.
    let suspect: Vec<usize> = v["suspect_queries"]
        .as_array()
        .map(|a| a.iter().map(|k| k.as_u64().unwrap() as usize).collect())
        .unwrap_or_default();
    assert!(
        suspect.len() * 20 < radiance.len(),
        "{} of {} query rays missed their surface",
        suspect.len(),
        radiance.len()
    );
    Reference {
        radiance,
        std_error: rgb("std_error"),
        seconds: v["seconds"].as_f64().unwrap(),
        render_seconds: v["render_seconds"].as_f64().unwrap_or(f64::NAN),
        suspect,
    }
}

/// The bundle's geometry as Mitsuba objects: each object's patches as its triangles (in
/// metres), with its material.
pub fn objects(b: &Bundle) -> Vec<Value> {
    objects_with(b, &[])
}

/// [`objects`] with the objects named in `overrides` given that Mitsuba material instead
/// (the reference script's JSON: diffuse, emitter or volume). translucent objects have no
/// Mitsuba counterpart in this model and must be overridden: the benchmark makes them opaque
/// at their profile's albedo, the volumetric test a medium of the same coefficients.
pub fn objects_with(b: &Bundle, overrides: &[(String, Value)]) -> Vec<Value> {
    let m = b.manifest();
    // Positions and lights go to Mitsuba as they are: keep validation scenes in metres.
    assert_eq!(m.unit_mm, 1000.0, "validation scenes are in metres");
    let corners = b.patch_corners();
    m.objects
        .iter()
        .map(|o| {
            let first = o.first_patch as usize;
            let tris = &corners[first..first + o.patch_count as usize];
            let positions: Vec<[f32; 3]> = tris
                .iter()
                .flat_map(|t| t.iter().copied())
                .collect();
            let indices: Vec<[usize; 3]> =
                (0..tris.len()).map(|k| [3 * k, 3 * k + 1, 3 * k + 2]).collect();
            let over = overrides.iter().find(|(n, _)| *n == o.name).map(|(_, m)| m.clone());
            let material = match (&o.material, over) {
                (_, Some(m)) => m,
                (Material::Diffuse { albedo, .. }, None) => {
                    json!({"type": "diffuse", "albedo": albedo})
                }
                (Material::Emitter { radiance }, None) => {
                    json!({"type": "emitter", "radiance": radiance})
                }
                (other, None) => panic!("{}: no Mitsuba counterpart for {other:?}", o.name),
            };
            json!({"name": o.name, "positions": positions, "indices": indices, "material": material})
        })
        .collect()
}

/// Query points for the viewer mesh's vertices: each vertex moved 1% of the way toward the
/// centroid of a triangle that uses it (so a vertex on a room's edge is measured on its own
/// wall), with the vertex normal.
pub fn vertex_queries(b: &Bundle) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    let to_m = (b.manifest().unit_mm / 1000.0) as f32;
    let pos = b.vertex_positions();
    let mut toward = vec![None; pos.len()];
    for t in b.triangle_vertices() {
        let c = [0, 1, 2].map(|k| t.iter().map(|&v| pos[v as usize][k]).sum::<f32>() / 3.0);
        for &v in t {
            toward[v as usize].get_or_insert(c);
        }
    }
    let points = pos
        .iter()
        .zip(&toward)
        .map(|(p, c)| {
            let c = c.expect("every vertex belongs to a triangle");
            [0, 1, 2].map(|k| (p[k] + 0.01 * (c[k] - p[k])) * to_m)
        })
        .collect();
    (points, b.vertex_normals().to_vec())
}

/// Errors of `got` against `want` per vertex: |Σ_c got − Σ_c want| / Σ_c want (the error
/// of the vertex's total radiance) over vertices whose reference is above `floor` × the
/// mean (shadowed corners of no radiance say nothing about relative error).
#[derive(Debug, Clone)]
pub struct Errors {
    pub median: f64,
    pub p90: f64,
    /// Σ got / Σ want over all vertices: a systematic gain or loss of energy.
    pub total_ratio: f64,
    /// Median of the reference's own relative standard error.
    pub reference_noise: f64,
    pub counted: usize,
}

pub fn errors(got: &[Rgb], reference: &Reference, floor: f64) -> Errors {
    let sum = |c: &Rgb| c.iter().map(|&x| f64::from(x)).sum::<f64>();
    let want: Vec<f64> = reference.radiance.iter().map(sum).collect();
    let have: Vec<f64> = got.iter().map(sum).collect();
    let mean = want.iter().sum::<f64>() / want.len() as f64;
    let mut rel = Vec::new();
    let mut noise = Vec::new();
    for (k, (&h, &w)) in have.iter().zip(&want).enumerate() {
        if w > floor * mean && !reference.suspect.contains(&k) {
            rel.push((h - w).abs() / w);
            let se = reference.std_error[k]
                .iter()
                .map(|&s| f64::from(s).powi(2))
                .sum::<f64>()
                .sqrt();
            noise.push(se / w);
        }
    }
    let pct = |v: &mut Vec<f64>, q: f64| {
        v.sort_by(f64::total_cmp);
        v[((v.len() - 1) as f64 * q).round() as usize]
    };
    Errors {
        median: pct(&mut rel, 0.5),
        p90: pct(&mut rel, 0.9),
        total_ratio: have.iter().sum::<f64>() / want.iter().sum::<f64>(),
        reference_noise: pct(&mut noise, 0.5),
        counted: rel.len(),
    }
}

/// Every `step`-th element of `v`.
pub fn every<T: Clone>(v: &[T], step: usize) -> Vec<T> {
    v.iter().step_by(step).cloned().collect()
}

/// The answers for queries `lo..hi` of a reference that covered several sets.
pub fn slice(r: &Reference, lo: usize, hi: usize) -> Reference {
    Reference {
        radiance: r.radiance[lo..hi].to_vec(),
        std_error: r.std_error[lo..hi].to_vec(),
        seconds: r.seconds,
        render_seconds: r.render_seconds,
        suspect: r
            .suspect
            .iter()
            .filter(|&&k| (lo..hi).contains(&k))
            .map(|k| k - lo)
            .collect(),
    }
}
