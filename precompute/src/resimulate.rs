//! Re-simulating simulated objects in an existing bundle: a new scattering medium (σs, g,
//! η, or a σa below the stored walks' floor) that re-weighting the stored walks cannot
//! serve, without the scene's source files.
//!
//! In: a bundle folder and new `"type": "simulated"` materials for some of its simulated
//! objects (by name). Out: the same bundle rewritten in place, atomically
//! ([`crate::bundle::write_bundle_keeping`]): those objects' walks run again on the bundle's
//! own patches with the new medium, their rows of S re-weighted from them, their material
//! and walk report in the manifest replaced; every other array is copied as it is. The
//! transfer matrix T, which depends on S, is dropped (precompute with `--inverse` again to
//! have it). The walks are seeded per patch as in a full precompute, so the result equals a
//! precompute of the scene with the new material.

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use translux_engine::simulated::{SimError, SimMedium};
use translux_engine::smatrix::{self, ObjectMaterial, SParams};
use translux_engine::stop::{Reason, Stop};
use translux_proto::bundle::{Bundle, Manifest, WalksView, arrays};
use translux_proto::scene::Material;

use crate::bundle::{KeptArray, NamedArray, write_bundle_keeping};
use crate::simulate::{SceneWalks, scene_walks};

/// What a re-simulation did.
#[derive(Debug, Clone)]
pub struct ResimulateReport {
    /// Per object walked again: its name, walks, and seconds.
    pub objects: Vec<(String, u64, f64)>,
    /// Records of the bundle's walks after.
    pub records: u64,
    pub bundle_bytes: u64,
    pub patches: u64,
    pub vertices: u64,
    pub nnz_f: u64,
    /// Whether a transfer matrix T was dropped.
    pub dropped_transfer: bool,
    pub seconds: f64,
}

/// `changes` by object index, checked against the bundle's manifest: at least one, each an
/// object precomputed simulated, named once, with a valid simulated material. The errors
/// name the field (`materials.NAME...`). What a server checks before queueing a job.
pub fn check_changes(
    m: &Manifest,
    changes: &[(String, Material)],
) -> Result<Vec<(usize, Material)>, String> {
    if changes.is_empty() {
        return Err("materials: name at least one simulated object to walk again".into());
    }
    let mut overrides: Vec<(usize, Material)> = Vec::new();
    for (name, material) in changes {
        let at = format!("materials.{name}");
        let Some(k) = m.objects.iter().position(|o| &o.name == name) else {
            let names: Vec<&str> = m.objects.iter().map(|o| o.name.as_str()).collect();
            return Err(format!(
                "{at}: the bundle has no object {name:?} (its objects are {})",
                names.join(", ")
            ));
        };
        material.validate(&at).map_err(|e| e.to_string())?;
        let built = &m.objects[k].material;
        if !matches!(built, Material::Simulated { .. }) || SimMedium::of(material).is_none() {
            return Err(format!(
                "{at}: only a simulated object walks again, with a simulated material that \
                 names its medium ({name:?} was precomputed as {}; this material is {})",
                built.kind(),
                material.kind()
            ));
        }
        if overrides.iter().any(|(i, _)| *i == k) {
            return Err(format!("{at}: named twice"));
        }
        overrides.push((k, material.clone()));
    }
    Ok(overrides)
}

/// The error of a re-simulation stopped by its [`Stop`]'s flag.
pub const CANCELLED: &str = "cancelled";

/// The error of a re-simulation stopped at its time `limit` after `seconds`, with `done`
/// of `total` patches walked.
fn over_limit(limit: Duration, seconds: f64, done: u64, total: u64) -> String {
    let all = if done == 0 {
        // Each patch takes longer than `seconds` on one of the threads.
        let threads = rayon::current_num_threads().max(1) as f64;
        format!(
            "more than {:.0} s (not one patch finished)",
            seconds * total as f64 / threads
        )
    } else {
        format!("about {:.0} s", seconds * total as f64 / done as f64)
    };
    format!(
        "walks: stopped at this job's limit of {:.1} s of walks, with {done} of \
         {total} patches walked; all of them would take {all}. Ask fewer walks \
         (max_walks, noise), a medium with fewer scattering events (lower sigma_s, higher \
         sigma_a), or use a token with a higher limit",
        limit.as_secs_f64()
    )
}

/// Walks the simulated objects named in `changes` again with their new materials and
/// rewrites the bundle in `dir` (see the module docs). `progress(done, total)` counts
/// patches walked. Errors name the object and the problem; on any error the bundle is left
/// as it was.
///
/// `stop` ends the walks within milliseconds (the error is [`CANCELLED`]), and so does
/// `limit`, the most time they may take (the error says how long all of them would take,
/// estimated from the patches walked).
pub fn resimulate(
    dir: &Path,
    changes: &[(String, Material)],
    progress: &(dyn Fn(u64, u64) + Sync),
    (stop, limit): (&Stop, Option<Duration>),
) -> Result<ResimulateReport, String> {
    let start = Instant::now();
    let stop = match limit {
        Some(limit) => stop.clone().until(start + limit),
        None => stop.clone(),
    };
    let bundle = Bundle::open(dir).map_err(|e| e.to_string())?;
    let m = bundle.manifest();
    let overrides = check_changes(m, changes)?;
    let old = bundle
        .walks()
        .ok_or_else(|| "the bundle holds no walks (precompute it again)".to_string())?;
    let (Some(old_normal), Some(old_lamp)) = (old.normal, old.lamp) else {
        return Err(format!(
            "the bundle is format version {} (its walks have no collimated or lamp \
             weights): precompute the scene again",
            m.version
        ));
    };

    // The bundle's own patches, exactly as the precompute walked them.
    let mut g = smatrix::bundle_geometry(&bundle);
    g.normal = bundle
        .patch_normals()
        .iter()
        .map(|&n| glam::Vec3::from(n))
        .collect();
    g.area = bundle.patch_areas().to_vec();
    let objects: Vec<ObjectMaterial<'_>> = overrides
        .iter()
        .map(|(k, mat)| {
            let o = &m.objects[*k];
            ObjectMaterial {
                name: &o.name,
                material: mat,
                patches: o.first_patch as usize..(o.first_patch + o.patch_count) as usize,
            }
        })
        .collect();
    let total: u64 = objects.iter().map(|o| o.patches.len() as u64).sum();
    let done = AtomicU64::new(0);
    let fresh: SceneWalks = scene_walks(
        &g,
        &objects,
        m.unit_mm,
        (
            &|d| {
                done.fetch_max(d, Ordering::Relaxed);
                progress(d, total)
            },
            &stop,
        ),
    )
    .map_err(|e| match (&e, stop.reason()) {
        (SimError::Stopped { .. }, Some(Reason::Time)) => over_limit(
            limit.unwrap_or_default(),
            start.elapsed().as_secs_f64(),
            done.load(Ordering::Relaxed),
            total,
        ),
        (SimError::Stopped { .. }, _) => CANCELLED.to_string(),
        _ => e.to_string(),
    })?;

    // The scene's records: walked-again rows from `fresh`, every other row as stored.
    let n = g.corners.len();
    let renewed = |j: usize| objects.iter().any(|o| o.patches.contains(&j));
    let mut walks = SceneWalks::default();
    walks.row_ptr.push(0);
    for j in 0..n {
        let (col, bin, weight, normal, lamp) = if renewed(j) {
            let r = fresh.row_ptr[j] as usize..fresh.row_ptr[j + 1] as usize;
            (
                &fresh.col[r.clone()],
                &fresh.bin[r.clone()],
                &fresh.weight[r.clone()],
                &fresh.weight_normal[r.clone()],
                &fresh.weight_lamp[r],
            )
        } else {
            let r = old.row_ptr[j] as usize..old.row_ptr[j + 1] as usize;
            (
                &old.col[r.clone()],
                &old.bin[r.clone()],
                &old.weight[r.clone()],
                &old_normal[r.clone()],
                &old_lamp[r],
            )
        };
        walks.col.extend_from_slice(col);
        walks.bin.extend_from_slice(bin);
        walks.weight.extend_from_slice(weight);
        walks.weight_normal.extend_from_slice(normal);
        walks.weight_lamp.extend_from_slice(lamp);
        walks.row_ptr.push(walks.col.len() as u64);
    }
    let view = WalksView::new_checked(
        n,
        &walks.row_ptr,
        &walks.col,
        &walks.bin,
        &walks.weight,
        Some(&walks.weight_normal),
    )?
    .with_lamp(&walks.weight_lamp)?;
    let (s, reports) = smatrix::rebuild_with_walks(&bundle, &overrides, &SParams::default(), &view)
        .map_err(|e| e.to_string())?;

    // The manifest: new materials, walk reports and counts; no T.
    let mut manifest = m.clone();
    for (k, mat) in &overrides {
        manifest.objects[*k].material = mat.clone();
    }
    for (name, info, seconds) in &fresh.reports {
        if let Some(o) = manifest
            .subsurface
            .objects
            .iter_mut()
            .find(|o| &o.name == name)
        {
            o.simulation = Some(info.clone());
            o.seconds = *seconds;
            if let Some(r) = reports.iter().find(|r| &r.name == name) {
                o.max_column_energy = r.max_column_energy;
                o.entries = r.entries;
            }
        }
    }
    manifest.subsurface.nnz = s.col.len() as u64;
    manifest.subsurface.walks = walks.col.len() as u64;
    let dropped_transfer = manifest.transfer.take().is_some();

    let records = walks.col.len() as u64;
    let np = n as u64;
    let new_arrays = vec![
        NamedArray::u64(arrays::S_ROW_PTR, vec![np + 1], s.row_ptr),
        NamedArray::u32(arrays::S_COL, vec![s.col.len() as u64], s.col),
        NamedArray::f32(arrays::S_VAL, vec![s.val.len() as u64, 3], s.val.concat()),
        NamedArray::u64(arrays::SIM_ROW_PTR, vec![np + 1], walks.row_ptr),
        NamedArray::u32(arrays::SIM_COL, vec![records], walks.col),
        NamedArray::u32(arrays::SIM_BIN, vec![records], walks.bin),
        NamedArray::f32(
            arrays::SIM_WEIGHT,
            vec![records, 3],
            walks.weight.iter().flatten().copied().collect(),
        ),
        NamedArray::f32(
            arrays::SIM_WEIGHT_NORMAL,
            vec![records, 3],
            walks.weight_normal.iter().flatten().copied().collect(),
        ),
        NamedArray::u32(
            arrays::SIM_WEIGHT_LAMP,
            vec![records, 3],
            walks.weight_lamp.iter().flatten().copied().collect(),
        ),
    ];
    let mut kept = Vec::new();
    for (name, entry) in &m.arrays {
        let replaced = new_arrays.iter().any(|a| a.name == name.as_str());
        let dropped = [arrays::TRANSFER, arrays::TRANSFER_SCALE].contains(&name.as_str());
        if replaced || dropped {
            continue;
        }
        kept.push(KeptArray {
            name: name.clone(),
            entry: entry.clone(),
            from: dir.join(&entry.file),
        });
    }
    let (patches, vertices, nnz_f) = (m.patch_count, m.vertex_count, m.form_factors.nnz);
    drop(bundle);
    let written =
        write_bundle_keeping(dir, manifest, new_arrays, &kept).map_err(|e| e.to_string())?;
    Ok(ResimulateReport {
        objects: fresh
            .reports
            .iter()
            .map(|(name, info, seconds)| (name.clone(), info.walks, *seconds))
            .collect(),
        records,
        bundle_bytes: written.bytes,
        patches,
        vertices,
        nnz_f,
        dropped_transfer,
        seconds: start.elapsed().as_secs_f64(),
    })
}
