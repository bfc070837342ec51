//! A translucency change's rows of S written on the device (`s_terms.wgsl`) from the radial
//! terms, against the CPU's rewrite of the same rows (`smatrix::rewrite_with_terms`, which
//! `ObjectTerms::write` does), value for value, on lavapipe.

use std::cell::RefCell;

use translux_engine::smatrix::{self, SParams};
use translux_engine::sterms::{OPPOSITE, Scratch};
use translux_engine::transport::push_node_rows;
use translux_proto::bundle::Bundle;
use translux_proto::csr::ValidCsr;
use translux_proto::scene::{Material, Profile};
use translux_server::gpu::sterms::GpuObjectTerms;
use translux_server::gpu::{GpuContext, GpuCsr};

fn marble(scale: f32) -> Material {
    Material::Translucent {
        profile: Profile::Dipole {
            preset: Some("marble".into()),
            sigma_a: None,
            sigma_s_prime: None,
            eta: None,
            scale: Some(scale),
        },
        specular: None,
    }
}

/// R(r) = a e^(−b r) whose whole integral is `energy` per channel (a profile brighter than
/// any physical one drives every column past the energy bound).
fn exponential(energy: [f32; 3], b: f32) -> Material {
    use translux_proto::scene::ExpTerm;
    let a = energy.map(|e| e * b * b / (2.0 * std::f32::consts::PI));
    Material::Translucent {
        profile: Profile::Exponentials {
            terms: vec![ExpTerm { a, b: [b; 3] }],
        },
        specular: None,
    }
}

/// S rewritten for the block at several translucencies — marble less and more translucent
/// than it was built with, and profiles bright enough in some channels that the energy
/// bound scales columns and the links' nodes —
/// on the device from S as it was, equals the CPU's rewrite entry for entry (within f32
/// rounding: the device adds the bound's sums in another order), every other object's
/// values untouched; with S in one block and split over many (a 4 KiB binding); and with
/// S's node rows pushed down to the patches, as the GPU backend holds it.
#[test]
fn a_translucency_change_writes_s_on_the_device_as_the_cpu_does() {
    let tmp = tempfile::tempdir().unwrap();
    let b = crate::gpu::hierarchical_cornell(&tmp.path().join("cornell"), 1500);
    let k = b
        .manifest()
        .objects
        .iter()
        .position(|o| o.name == "tall_block")
        .unwrap();
    let materials = vec![
        marble(8.0),
        marble(2.0),
        marble(0.5),
        marble(20.0),
        exponential([3.0, 1.0, 0.5], 0.05),
        exponential([2.0, 0.5, 1.5], 0.01),
    ];
    let Some(seen) = device_against_cpu(&b, k, materials) else {
        return;
    };
    assert!(
        seen.links && seen.node_rows,
        "the block links to nodes: {seen:?}"
    );
    assert!(
        seen.scaled_columns > 0,
        "no column was scaled: the bound went untested"
    );
    assert!(
        seen.scaled_nodes > 0,
        "no node was scaled: the links' bound went untested"
    );
}

/// A thin sheet's change (a petal of `builtin:flower`, its reflectance and transmittance
/// scaled and widened) written on the device equals the CPU's rewrite: entries on the
/// petal's other side read the transmittance's table.
#[test]
fn a_thin_sheets_change_writes_s_on_the_device_as_the_cpu_does() {
    use translux_precompute::pipeline::{PrecomputeParams, precompute};
    use translux_proto::scene::ExpTerm;
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("flower");
    let scene = translux_precompute::scene::load_scene("builtin:flower").unwrap();
    let params = PrecomputeParams {
        patches: Some(1200),
        environment: translux_engine::envvis::EnvVisParams {
            bins: None,
            ..Default::default()
        },
        ..Default::default()
    };
    precompute(&scene, &dir, &params).unwrap();
    let b = translux_proto::bundle::Bundle::open(&dir).unwrap();
    let k = (0..b.manifest().objects.len())
        .find(|&k| matches!(b.manifest().objects[k].material, Material::ThinSheet { .. }))
        .unwrap();
    let sheet = |r: f32, t: f32, wide: f32| {
        let p = |energy: [f32; 3], b: f32| Profile::Exponentials {
            terms: vec![ExpTerm {
                a: energy.map(|e| e * b * b / (2.0 * std::f32::consts::PI)),
                b: [b; 3],
            }],
        };
        Material::ThinSheet {
            reflectance: p([0.45 * r, 0.2 * r, 0.3 * r], 1.0 / wide),
            transmittance: p([0.35 * t, 0.12 * t, 0.22 * t], 0.7 / wide),
            thickness_mm: 1.0,
            specular: None,
        }
    };
    let materials = vec![
        sheet(1.0, 1.0, 1.0),
        sheet(0.5, 2.0, 2.0),
        sheet(2.0, 0.2, 0.5),
    ];
    let Some(seen) = device_against_cpu(&b, k, materials) else {
        return;
    };
    assert!(
        seen.opposite,
        "the petal has entries on its other side: {seen:?}"
    );
}

/// What [`device_against_cpu`] found the object to hold and the bound to do.
#[derive(Debug, Default)]
struct Seen {
    links: bool,
    node_rows: bool,
    opposite: bool,
    scaled_columns: usize,
    scaled_nodes: usize,
}

/// Object `k` of `b` overridden with each of `materials` in turn (S built for the first),
/// written on the device from S as it was built, against the CPU's rewrite, value for
/// value; with S in one block and split over many (a 4 KiB binding), and with S's node rows
/// pushed down to the patches where it has them (as the GPU backend holds it). `None`
/// without a GPU adapter.
fn device_against_cpu(b: &Bundle, k: usize, materials: Vec<Material>) -> Option<Seen> {
    let contexts: Vec<&GpuContext> = [crate::support::gpu(), tiny()]
        .into_iter()
        .flatten()
        .collect();
    if contexts.is_empty() {
        return None;
    }
    let params = SParams::default();
    let terms = smatrix::terms_of_bundle(b, &params.quadrature);
    let sheet = matches!(materials[0], Material::ThinSheet { .. });
    let t = terms.get(k, sheet).expect("the object has radial terms");
    let g = smatrix::bundle_geometry(b);
    let (area, at) = smatrix::object_placement(b, &g, k).unwrap();
    let (start, _) =
        smatrix::rebuild_with_terms(b, &[(k, materials[0].clone())], &params, &terms).unwrap();
    let start = ValidCsr::new(start).unwrap();
    let flat = t.flatten(area, at, start.view().row_ptr()).unwrap();
    let mut seen = Seen {
        links: !flat.links.is_empty(),
        node_rows: flat.rows.iter().any(|r| r.local == u32::MAX),
        opposite: flat.entries.iter().any(|e| e.terms & OPPOSITE != 0),
        ..Default::default()
    };
    // The same S with its node rows pushed down to the patches, as the GPU backend holds it.
    let push = |s: &ValidCsr<[f32; 3]>| match b.tree().filter(|_| seen.node_rows) {
        Some(tree) => ValidCsr::new(push_node_rows(s.view(), tree).unwrap()).unwrap(),
        None => s.clone(),
    };
    let start_pushed = push(&start);
    let mut flat_pushed = flat.clone();
    t.push_into(&mut flat_pushed, at, &start_pushed.view())
        .unwrap();
    assert_eq!(flat_pushed.pushed > 0, seen.node_rows);
    let flat_values =
        |m: &ValidCsr<[f32; 3]>| -> Vec<f32> { m.view().val().iter().flatten().copied().collect() };
    for ctx in contexts {
        let s = GpuCsr::upload_rgb(ctx, "S", &start.view()).unwrap();
        let dev = GpuObjectTerms::upload(ctx, "object", &flat).unwrap();
        let sp = GpuCsr::upload_rgb(ctx, "pushed S", &start_pushed.view()).unwrap();
        let dev_pushed = GpuObjectTerms::upload(ctx, "object pushed", &flat_pushed).unwrap();
        for (x, m) in materials.iter().enumerate() {
            let over = [(k, m.clone())];
            let mut scratch = Scratch::default();
            let (want, _) = smatrix::rewrite_with_terms(
                b,
                start.clone(),
                &mut None,
                &over,
                &[k],
                &params,
                &terms,
                &mut scratch,
            )
            .unwrap();
            let (same, other) = smatrix::object_flat_tables(b, &over, k, &params).unwrap();
            let tables = (&same, other.as_ref());
            let found = RefCell::new((0, 0));
            let counts = dev
                .write(ctx, &s, tables, |column, node| {
                    let f = t.factors_from_sums(area, at, column, node);
                    let below = |v: &[[f32; 3]]| v.iter().filter(|x| **x != [1.0; 3]).count();
                    *found.borrow_mut() = (below(&f.patches), below(&f.nodes));
                    f
                })
                .unwrap();
            let (c, n) = found.into_inner();
            seen.scaled_columns += c;
            seen.scaled_nodes += n;
            assert_eq!(counts.submissions, 2);
            let got = s.read_values(ctx).unwrap();
            compare(&format!("material {x}"), &got, &flat_values(&want));
            let bound = |column: &[[f32; 3]], node: &[[f32; 3]]| {
                t.factors_from_sums(area, at, column, node)
            };
            dev_pushed.write(ctx, &sp, tables, bound).unwrap();
            let got = sp.read_values(ctx).unwrap();
            compare(
                &format!("material {x}, pushed"),
                &got,
                &flat_values(&push(&want)),
            );
        }
        dev.release(ctx);
        dev_pushed.release(ctx);
    }
    Some(seen)
}

/// A context whose matrix buffers hold at most 4 KiB (S split into many blocks).
fn tiny() -> Option<&'static GpuContext> {
    static CTX: std::sync::OnceLock<Option<GpuContext>> = std::sync::OnceLock::new();
    CTX.get_or_init(|| crate::support::gpu_context(Some(4096)))
        .as_ref()
}

/// Every value within 2e-5 of the CPU's, relative to itself or to a millionth of the
/// largest value (values near 0).
fn compare(what: &str, got: &[f32], want: &[f32]) {
    assert_eq!(got.len(), want.len(), "{what}: values");
    let top = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let mut worst = (0.0f32, 0usize);
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        let rel = (g - w).abs() / w.abs().max(1e-6 * top);
        if rel > worst.0 {
            worst = (rel, i);
        }
    }
    assert!(
        worst.0 <= 2e-5,
        "{what}: relative error {:.3e} at value {} (got {}, want {})",
        worst.0,
        worst.1,
        got[worst.1],
        want[worst.1]
    );
}
