//! The random walks of simulated objects (`"type": "simulated"`), stage 1 of their S.
//!
//! In: the scene's objects with their source triangles and patch ranges, the patches, the
//! scene unit. Out: the walks of every simulated object as one scene-wide record array
//! ([`SceneWalks`], global rows and columns, what the bundle stores as `sim_*`) and a report
//! per object. The walking itself is `translux_engine::simulated`; this module refuses the
//! meshes walks cannot run in (open, or closed but wound inward) before any walk starts.

use std::collections::HashMap;

use glam::Vec3;
use translux_engine::simulated::{self, SimError, SimMedium, SimPatches};
use translux_engine::smatrix::{ObjectMaterial, PatchGeometry};
use translux_engine::stop::Stop;
use translux_proto::bundle::SimulationInfo;
use translux_proto::scene::Material;

/// All simulated objects' walks, global indices (rows over every patch of the scene).
#[derive(Debug, Clone, Default)]
pub struct SceneWalks {
    pub row_ptr: Vec<u64>,
    pub col: Vec<u32>,
    pub bin: Vec<u32>,
    pub weight: Vec<[f32; 3]>,
    /// The same records for collimated entry along the normal (`sim_weight_normal`).
    pub weight_normal: Vec<[f32; 3]>,
    /// Their lamp-only parts: G_u, G_v and U (`sim_weight_lamp`).
    pub weight_lamp: Vec<[u32; 3]>,
    /// Per simulated object: its name and what the walks did.
    pub reports: Vec<(String, SimulationInfo, f64)>,
}

impl SceneWalks {
    /// Whether any object was simulated.
    pub fn is_empty(&self) -> bool {
        self.reports.is_empty()
    }
}

/// Why a mesh cannot hold walks: open edges, or faces wound inward. `None`: closed and
/// outward. Vertices closer than 1e-6 of the mesh's size are one vertex.
pub fn closed_mesh_problem(tris: &[[Vec3; 3]]) -> Option<String> {
    if tris.is_empty() {
        return Some("it has no triangles".into());
    }
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for t in tris {
        for v in t {
            lo = lo.min(*v);
            hi = hi.max(*v);
        }
    }
    let q = ((hi - lo).max_element() * 1e-6).max(f32::MIN_POSITIVE);
    let key = |v: Vec3| {
        let k = ((v - lo) / q).round();
        (k.x as i64, k.y as i64, k.z as i64)
    };
    // Directed edge counts: a closed, consistently wound mesh uses each edge once in each
    // direction.
    type Vertex = (i64, i64, i64);
    let mut edges: HashMap<(Vertex, Vertex), i32> = HashMap::new();
    for t in tris {
        for k in 0..3 {
            let (a, b) = (key(t[k]), key(t[(k + 1) % 3]));
            if a == b {
                continue;
            }
            *edges.entry((a, b)).or_insert(0) += 1;
        }
    }
    let open = edges
        .iter()
        .filter(|(e, c)| edges.get(&(e.1, e.0)).copied().unwrap_or(0) != **c)
        .count();
    if open > 0 {
        return Some(format!(
            "its mesh is not closed ({open} edges have no matching face on the other side): \
             walks would leave through the holes. Close the mesh (a scanned bunny is open at \
             the bottom) or use `translucent` with a dipole"
        ));
    }
    let volume: f64 = tris
        .iter()
        .map(|t| {
            let (a, b, c) = (t[0].as_dvec3(), t[1].as_dvec3(), t[2].as_dvec3());
            a.dot(b.cross(c)) / 6.0
        })
        .sum();
    if volume <= 0.0 {
        return Some(
            "its closed mesh is wound inward (negative volume): walks start inside the \
             object, behind each face; set \"orientation\": \"outward\""
                .into(),
        );
    }
    None
}

/// The first simulated object of `objects` (name, material, source triangles) that walks
/// cannot run in, as a message; checked before any other stage runs.
pub fn check_meshes<'a>(
    objects: impl IntoIterator<Item = (&'a str, &'a Material, &'a [[Vec3; 3]])>,
) -> Result<(), String> {
    for (name, material, tris) in objects {
        if matches!(material, Material::Simulated { .. })
            && let Some(why) = closed_mesh_problem(tris)
        {
            return Err(format!("object '{name}' is simulated, but {why}"));
        }
    }
    Ok(())
}

/// Runs the walks of every simulated object; their meshes must have passed
/// [`check_meshes`]. `progress` gets the number of patches walked so far.
pub fn scene_walks(
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    unit_mm: f64,
    (progress, stop): (&(dyn Fn(u64) + Sync), &Stop),
) -> Result<SceneWalks, SimError> {
    let n = g.corners.len();
    let mut rows: Vec<u64> = vec![0; n + 1];
    let mut per_object = Vec::new();
    let mut done = 0u64;
    for o in objects {
        let Some(medium) = SimMedium::of(o.material) else {
            continue;
        };
        let r = o.patches.clone();
        let p = SimPatches {
            corners: &g.corners[r.clone()],
            normal: &g.normal[r.clone()],
            area: &g.area[r.clone()],
        };
        let base = done;
        let w = simulated::simulate(
            o.name,
            p,
            &medium,
            unit_mm,
            r.start as u64,
            (&|d| progress(base + d), stop),
        )?;
        done += r.len() as u64;
        for (j, pair) in w.row_ptr.windows(2).enumerate() {
            rows[r.start + j + 1] = pair[1] - pair[0];
        }
        per_object.push((o.name.to_string(), r, w));
    }
    let mut out = SceneWalks::default();
    if per_object.is_empty() {
        return Ok(out);
    }
    for j in 0..n {
        rows[j + 1] += rows[j];
    }
    out.row_ptr = rows;
    // Objects are in patch order, so their records concatenate in row order.
    for (name, r, w) in per_object {
        out.col.extend(w.col.iter().map(|&i| i + r.start as u32));
        out.bin.extend_from_slice(&w.bin);
        out.weight.extend_from_slice(&w.weight);
        out.weight_normal.extend_from_slice(&w.weight_normal);
        out.weight_lamp.extend_from_slice(&w.weight_lamp);
        out.reports.push((name, w.report, w.seconds));
    }
    Ok(out)
}
