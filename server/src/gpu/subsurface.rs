//! S rebuilt on the device for a translucency change.
//!
//! In: a bundle (patch corners, the stored optical distances and their kinds) and the
//! scene's materials with a request's overrides applied. Out: S on the device as a
//! [`GpuCsr`] ready for the solve, and its values read back once for the CPU's products
//! (S E for the right-hand side and the `subsurface_only` / heuristic components).
//!
//! Two stages, the same split as the CPU's [`translux_engine::smatrix`]:
//!
//! 1. [`STemplate`] (CPU, once per scene and per object radii): which entries S has —
//!    the self term and every stored pair within the radius of each translucent object or
//!    thin sheet, the diagonal of opaque patches — laid out in receiver rows (the SpMV's
//!    CSR), with the column order of the CPU's assembly (`perm`), and per entry its
//!    quadrature plan ([`Quadrature`]: far, polar or point samples), which depends on
//!    geometry alone. It is kept with headroom (1.5× the radius asked for, up to what the
//!    bundle stores), so a translucency slider moving back and forth reuses it; entries
//!    beyond a profile's current truncation radius come out as explicit zeros.
//! 2. Per override set, two kernels: `s_entries` evaluates every entry's plan against the
//!    objects' tabulated profiles (uploaded: 2 × 4097 RGB rows a profile), and
//!    `s_column_bound` enforces Σ_j A_j S_ji ≤ A_i per column as the CPU does. Nothing
//!    geometric is recomputed, nothing is uploaded but the tables.
//!
//! A hierarchical S (links from receivers to whole nodes of the cluster tree,
//! `translux_precompute::slinks`) is rebuilt the same way: its links are entries of the
//! node columns N + k, evaluated as far pairs with the node's area (S_{j,N+k} = A_k R(r);
//! a link read at two distances, `--s-link-near`, carries its spread σ in an aux row and
//! reads A_k (R(r − σ) + R(r + σ)) / 2), and more kernels hold every column to the
//! energy bound with them, as the CPU's `subsurface::add_links` does: `s_node_energy` sums
//! what each node re-emits (e_k = Σ_j A_j S_{j,N+k} / A_k); `s_link_bound`'s first pass adds
//! to each patch column the e_k of the linked nodes that hold the patch and takes the
//! factor a pairwise S would scale the column by (1 / total past 1); `s_link_scale` scales
//! each node's links (and e_k) by its patches' area-weighted mean factor; the last pass
//! scales each column's direct entries by its factor, or further where the links left more.
//!
//! Heterogeneous objects (eq. 9 over per-medium lengths) are rebuilt on the CPU: [`Plan`]
//! says so, and the relight reports where S was built (`stats.materials_on`).

use rayon::prelude::*;
use translux_engine::radiosity::Rgb;
use translux_engine::sheet::{self, KIND_OPPOSITE};
use translux_engine::smatrix::{self, PatchGeometry, SError, SParams};
use translux_engine::subsurface::{self, ObjectPatches, Quadrature, SubsurfaceParams, Tabulated};
use translux_proto::bundle::Bundle;
use translux_proto::csr::Csr;
use translux_proto::scene::Material;

use super::matrix::{alloc_size, staging, storage_init, storage_zeroed, uniform};
use super::{GpuContext, GpuCsr, GpuError, grid};

/// What one S dispatch gives back: the value buffer, its values and column reports as
/// read back, and the bytes it reserved.
type Dispatched = (wgpu::Buffer, Vec<Rgb>, Vec<ColumnReport>, u64);

/// Entry modes (the low two bits of an entry's meta word; `s_entries.wgsl`).
pub const MODE_DIAG: u32 = 0;
pub const MODE_FAR: u32 = 1;
pub const MODE_POLAR: u32 = 2;
pub const MODE_POINTS: u32 = 3;
/// Meta bit 3: a far entry read at two distances r ∓ σ (a link of `--s-link-near`), σ in
/// its aux row's x.
pub const TWO_POINT: u32 = 1 << 3;
/// Meta bits 4–31: the entry's first aux row (2²⁸ rows, 4 GiB of them, at most).
pub const AUX_SHIFT: u32 = 4;

/// The most sample points per patch the kernel holds (`MAX_SAMPLES`): m ≤ 8.
pub const MAX_SAMPLES: u32 = 64;

/// Threads per workgroup of both kernels.
const WG: u32 = 256;

/// What an object contributes to S (the kernels' class codes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Class {
    /// Nothing (an emitter).
    Emitter = 0,
    /// ρ on the diagonal.
    Diffuse = 1,
    /// A homogeneous translucent object: its profile over its stored pairs.
    Translucent = 2,
    /// A thin sheet: reflectance within a side, transmittance across.
    Sheet = 3,
}

/// One object as the kernels read it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObjectParams {
    pub class: Class,
    /// Table of the profile (a sheet's reflectance).
    pub slot_r: u32,
    /// Table of a sheet's transmittance (= `slot_r` otherwise).
    pub slot_t: u32,
    /// ρ of a diffuse object.
    pub albedo: Rgb,
}

/// S's materials as the device rebuild takes them: per object its class, tables and the
/// radius its entries must reach.
#[derive(Debug, Clone)]
pub struct SMaterials {
    pub objects: Vec<ObjectParams>,
    pub tables: Vec<Tabulated>,
    /// Per object: the largest radius its tables reach (0 without tables).
    pub reach: Vec<f32>,
}

/// Where S is to be rebuilt.
#[derive(Debug)]
pub enum Plan {
    Device(SMaterials),
    /// On the CPU, and why.
    Cpu(String),
}

impl SMaterials {
    /// The materials' classes and tables, the tables cut as the CPU's assembly cuts them
    /// (truncation radius, capped by the stored distances `stored`).
    pub fn plan(
        bundle: &Bundle,
        materials: &[Material],
        stored: &[f32],
        params: &SParams,
    ) -> Result<Plan, SError> {
        let m = bundle.manifest();
        if m.subsurface.links > 0 && bundle.tree().is_none() {
            return Ok(Plan::Cpu(
                "a hierarchical S without its cluster tree is rebuilt on the CPU".into(),
            ));
        }
        if params.quadrature.samples.pow(2) > MAX_SAMPLES {
            return Ok(Plan::Cpu(format!(
                "{} sample points per patch; the device kernel holds at most {MAX_SAMPLES}",
                params.quadrature.samples.pow(2)
            )));
        }
        let mut out = SMaterials {
            objects: Vec::with_capacity(materials.len()),
            tables: Vec::new(),
            reach: Vec::with_capacity(materials.len()),
        };
        for (k, (o, mat)) in m.objects.iter().zip(materials).enumerate() {
            let reach = stored.get(k).copied().unwrap_or(0.0);
            let slot = out.tables.len() as u32;
            let (class, albedo, radius, slots) = match mat {
                Material::Emitter { .. } => (Class::Emitter, [0.0; 3], 0.0, (0, 0)),
                Material::Diffuse { albedo, .. } => (Class::Diffuse, *albedo, 0.0, (0, 0)),
                Material::Translucent { profile, .. } => {
                    let (tab, _) =
                        smatrix::translucent_table(&o.name, profile, reach, m.unit_mm, params)?;
                    let r = tab.r_max();
                    out.tables.push(tab);
                    (Class::Translucent, [0.0; 3], r, (slot, slot))
                }
                Material::ThinSheet {
                    reflectance,
                    transmittance,
                    ..
                } => {
                    let (tr, tt, _) = sheet::tables(
                        &o.name,
                        (reflectance, transmittance),
                        reach,
                        m.unit_mm,
                        params,
                    )?;
                    let r = tr.r_max().max(tt.r_max());
                    out.tables.push(tr);
                    out.tables.push(tt);
                    (Class::Sheet, [0.0; 3], r, (slot, slot + 1))
                }
                Material::Heterogeneous { .. } => {
                    return Ok(Plan::Cpu(format!(
                        "'{}' is heterogeneous (eq. 9 is rebuilt on the CPU)",
                        o.name
                    )));
                }
                Material::Simulated { .. } => {
                    return Ok(Plan::Cpu(format!(
                        "'{}' is simulated (its walks are re-weighted on the CPU)",
                        o.name
                    )));
                }
            };
            out.objects.push(ObjectParams {
                class,
                slot_r: slots.0,
                slot_t: slots.1,
                albedo,
            });
            out.reach.push(radius);
        }
        Ok(Plan::Device(out))
    }
}

/// The structure of S for per-object classes and radii, and every entry's quadrature
/// plan: built once on the CPU ([`STemplate::build`]), then reused by every override set
/// it [covers](STemplate::covers).
#[derive(Debug, Clone)]
pub struct STemplate {
    pub n: usize,
    /// Nodes of the cluster tree a hierarchical S links to (0 without links): S has
    /// `n + nodes` columns, node k's being column n + k.
    pub nodes: usize,
    pub classes: Vec<Class>,
    /// Per object: entries kept for pairs closer than this (translucent objects, sheets).
    pub radius: Vec<f32>,
    /// Receiver rows j (the SpMV's CSR); `col` holds the source i.
    pub row_ptr: Vec<u64>,
    pub col: Vec<u32>,
    /// Per entry (row order): (i, j, r as bits, mode | opposite << 2 | two << 3 | aux << 4),
    /// `two` ([`TWO_POINT`]) set on a link read at two distances.
    pub entries: Vec<[u32; 4]>,
    /// Polar plans: 4 rows (corner 0 and the factor, corner 1, corner 2, the plane's
    /// normal); point plans: 1 row (the excess path); links read at two distances: 1 row
    /// (their spread σ).
    pub aux: Vec<[f32; 4]>,
    /// Columns (sources i, then nodes N + k): `perm[col_ptr[i]..col_ptr[i + 1]]` are the
    /// positions of column i's entries in row order, in the CPU assembly's order (self term
    /// first).
    pub col_ptr: Vec<u32>,
    pub perm: Vec<u32>,
    /// Per patch 4 rows: (corner 0, area), (corner 1, size), (corner 2, linked), (normal,
    /// object index as a float), `linked` 1 when the patch's object has links; then per node
    /// 4 rows: (0, area), (0, 0), (0, 0), (0, object index), so that a link (source N + k)
    /// reads its node's area and object where a pair reads its source patch's.
    pub patches: Vec<[f32; 4]>,
    /// Per patch, the linked nodes that hold it (what `s_link_bound` adds to its column):
    /// words `far[i]..far[i + 1]` of this same array, nodes ascending; then, from word
    /// `far[n]`, per node the patches it holds (what `s_link_scale` averages over): words
    /// `far[far[n] + k]..far[far[n] + k + 1]`, empty for a node without links. Empty
    /// without links.
    pub far: Vec<u32>,
    /// The order `s_entries` evaluates the entries in: polar plans, then point plans, then
    /// far pairs and links, then diagonals, so the threads of a warp share a plan's cost
    /// (a polar plan takes m² × K ray steps, a far pair one lookup).
    pub order: Vec<u32>,
}

/// One entry of a column while the template is built: (j, r, mode | opposite << 2 | two << 3,
/// aux rows).
type ColumnEntry = (u32, f32, u32, Vec<[f32; 4]>);

impl STemplate {
    /// Headroom on the radius a template is built for, so that nearby translucencies reuse it.
    pub const HEADROOM: f32 = 1.5;

    /// Whether this template serves `m`: the same classes, and every translucent object's
    /// radius within the template's.
    pub fn covers(&self, m: &SMaterials) -> bool {
        self.classes.len() == m.objects.len()
            && self
                .classes
                .iter()
                .zip(&m.objects)
                .all(|(c, o)| *c == o.class)
            && self
                .radius
                .iter()
                .zip(&m.reach)
                .all(|(have, want)| want <= have)
    }

    /// The template for `m`'s classes, with radii `HEADROOM` × `m`'s (at most what the
    /// bundle stores, `stored`).
    pub fn build(
        bundle: &Bundle,
        g: &PatchGeometry,
        m: &SMaterials,
        stored: &[f32],
        params: &SubsurfaceParams,
    ) -> STemplate {
        let man = bundle.manifest();
        let n = g.corners.len();
        // Links are read only with the tree they refer to (`bundle_geometry` gives it for a
        // hierarchical S).
        let tree = g.nodes.as_ref().filter(|_| man.subsurface.links > 0);
        let nodes = tree.map_or(0, |t| t.range.len());
        let classes: Vec<Class> = m.objects.iter().map(|o| o.class).collect();
        let radius: Vec<f32> = m
            .reach
            .iter()
            .enumerate()
            .map(|(k, r)| {
                (r * Self::HEADROOM)
                    .min(stored.get(k).copied().unwrap_or(0.0))
                    .max(*r)
            })
            .collect();
        let mut object_of = vec![0u32; n];
        let mut columns: Vec<Vec<ColumnEntry>> = vec![Vec::new(); n + nodes];
        let distances = bundle.distances();
        let kinds = bundle.distance_kinds();
        // Per stored distance the spread of a link read at two distances (empty without
        // `--s-link-near`; 0 on direct pairs).
        let spreads = bundle.distance_spreads();
        for (k, o) in man.objects.iter().enumerate() {
            let range = o.first_patch as usize..(o.first_patch + o.patch_count) as usize;
            object_of[range.clone()].fill(k as u32);
            let base = range.start;
            let p = ObjectPatches {
                corners: &g.corners[range.clone()],
                centroid: &g.centroid[range.clone()],
                normal: &g.normal[range.clone()],
                area: &g.area[range.clone()],
                size: &g.size[range.clone()],
            };
            let eps = subsurface::coplanar_eps(&p);
            let class = classes[k];
            let cut = radius[k];
            columns[range.clone()]
                .par_iter_mut()
                .enumerate()
                .for_each(|(li, col)| {
                    let i = base + li;
                    match class {
                        Class::Emitter => {}
                        Class::Diffuse => col.push((i as u32, 0.0, MODE_DIAG, Vec::new())),
                        Class::Translucent | Class::Sheet => {
                            let (mode, aux) = encode(&Quadrature::self_term(&p, li));
                            col.push((i as u32, 0.0, mode, aux));
                            let first = distances.row_ptr()[i] as usize;
                            let (cols, ds) = distances.row(i);
                            for (e, (&j, &r)) in cols.iter().zip(ds).enumerate() {
                                let j = j as usize;
                                if j < range.start || j >= range.end || r >= cut {
                                    continue;
                                }
                                let lj = j - base;
                                let (plan, opposite) = if class == Class::Sheet {
                                    let kd = kinds.get(first + e).copied().unwrap_or(0);
                                    (
                                        sheet::pair_plan(&p, (li, lj), r, params),
                                        kd == KIND_OPPOSITE,
                                    )
                                } else {
                                    (Quadrature::pair(&p, li, lj, r, params, eps), false)
                                };
                                let (mode, aux) = encode(&plan);
                                col.push((j as u32, r, mode | (opposite as u32) << 2, aux));
                            }
                        }
                    }
                });
        }
        // Links: receiver j's stored entries in node columns, within its object's radius
        // (a node's links in receiver order, as the CPU sums them).
        let mut linked = vec![false; man.objects.len()];
        if nodes > 0 {
            for (k, o) in man.objects.iter().enumerate() {
                if !matches!(classes[k], Class::Translucent | Class::Sheet) {
                    continue;
                }
                let range = o.first_patch as usize..(o.first_patch + o.patch_count) as usize;
                for j in range {
                    let first = distances.row_ptr()[j] as usize;
                    let (cols, ds) = distances.row(j);
                    for (e, (&c, &r)) in cols.iter().zip(ds).enumerate() {
                        let c = c as usize;
                        if c < n || c >= n + nodes || r >= radius[k] {
                            continue;
                        }
                        let opposite = classes[k] == Class::Sheet
                            && kinds.get(first + e).copied().unwrap_or(0) == KIND_OPPOSITE;
                        let mode = MODE_FAR | (opposite as u32) << 2;
                        // A link with a spread is read at r ∓ σ, as `smatrix::node_links`
                        // reads it; σ travels in an aux row.
                        let entry = match spreads.get(first + e).copied().unwrap_or(0.0) {
                            s if s > 0.0 => {
                                (j as u32, r, mode | TWO_POINT, vec![[s, 0.0, 0.0, 0.0]])
                            }
                            _ => (j as u32, r, mode, Vec::new()),
                        };
                        columns[c].push(entry);
                        linked[k] = true;
                    }
                }
            }
        }
        // Rows: entries of row j sorted by source (nodes after patches), as the CPU's
        // transpose and its links leave them.
        let mut row_ptr = vec![0u64; n + 1];
        for col in &columns {
            for e in col {
                row_ptr[e.0 as usize + 1] += 1;
            }
        }
        for j in 0..n {
            row_ptr[j + 1] += row_ptr[j];
        }
        let nnz = row_ptr[n] as usize;
        let mut next: Vec<u64> = row_ptr[..n].to_vec();
        let mut col = vec![0u32; nnz];
        let mut entries = vec![[0u32; 4]; nnz];
        let mut aux = Vec::new();
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut perm = Vec::with_capacity(nnz);
        col_ptr.push(0u32);
        for (i, column) in columns.into_iter().enumerate() {
            for (j, r, mode, a) in column {
                let pos = next[j as usize] as usize;
                next[j as usize] += 1;
                let meta = mode | ((aux.len() as u32) << AUX_SHIFT);
                aux.extend(a);
                col[pos] = i as u32;
                entries[pos] = [i as u32, j, r.to_bits(), meta];
                perm.push(pos as u32);
            }
            col_ptr.push(perm.len() as u32);
        }
        let mut patches = Vec::with_capacity(4 * (n + nodes));
        for (i, &obj) in object_of.iter().enumerate() {
            let c = g.corners[i];
            let flag = if linked[obj as usize] { 1.0 } else { 0.0 };
            patches.push([c[0].x, c[0].y, c[0].z, g.area[i]]);
            patches.push([c[1].x, c[1].y, c[1].z, g.size[i]]);
            patches.push([c[2].x, c[2].y, c[2].z, flag]);
            // The object's index as a float: exact below 2²⁴ objects.
            patches.push([g.normal[i].x, g.normal[i].y, g.normal[i].z, obj as f32]);
        }
        // Nodes: the tree splits objects apart at its top, so a linked node's patches are
        // one object's (its first patch's).
        let mut far_lists: Vec<Vec<u32>> = vec![Vec::new(); if nodes > 0 { n } else { 0 }];
        let mut member_lists: Vec<&[u32]> = vec![&[]; nodes];
        if let Some(t) = tree {
            for k in 0..nodes {
                let members = t.members(k);
                let obj = members.first().map_or(0, |&p| object_of[p as usize]);
                patches.push([0.0, 0.0, 0.0, t.area[k]]);
                patches.push([0.0; 4]);
                patches.push([0.0; 4]);
                patches.push([0.0, 0.0, 0.0, obj as f32]);
                if col_ptr[n + k + 1] > col_ptr[n + k] {
                    for &p in members {
                        far_lists[p as usize].push(k as u32);
                    }
                    member_lists[k] = members;
                }
            }
        }
        let mut far = Vec::new();
        if nodes > 0 {
            let mut at = n as u32 + 1;
            far.push(at);
            for l in &far_lists {
                at += l.len() as u32;
                far.push(at);
            }
            far.extend(far_lists.into_iter().flatten());
            // far[n] is where the patches' lists end: the nodes' offsets start there.
            let mut at = far.len() as u32 + nodes as u32 + 1;
            far.push(at);
            for l in &member_lists {
                at += l.len() as u32;
                far.push(at);
            }
            far.extend(member_lists.into_iter().flatten());
        }
        let mut order: Vec<u32> = (0..nnz as u32).collect();
        let rank = |meta: u32| match meta & 3 {
            MODE_POLAR => 0u8,
            MODE_POINTS => 1,
            MODE_FAR => 2,
            _ => 3,
        };
        order.sort_by_key(|&e| rank(entries[e as usize][3]));
        STemplate {
            n,
            nodes,
            far,
            order,
            classes,
            radius,
            row_ptr,
            col,
            entries,
            aux,
            col_ptr,
            perm,
            patches,
        }
    }

    pub fn nnz(&self) -> usize {
        self.entries.len()
    }

    /// Entry `e`'s plan, decoded from the template (the CPU twin evaluates it with the
    /// precompute's own [`Quadrature::eval`]); `None` for a diagonal ρ entry.
    pub fn plan(&self, e: usize) -> Option<Quadrature> {
        let [i, j, _, meta] = self.entries[e];
        let a = (meta >> AUX_SHIFT) as usize;
        let corners = |p: u32| -> [glam::Vec3; 3] {
            std::array::from_fn(|k| glam::Vec3::from_slice(&self.patches[4 * p as usize + k][..3]))
        };
        match meta & 3 {
            MODE_FAR => Some(Quadrature::Far {
                area_i: self.patches[4 * i as usize][3],
            }),
            MODE_POLAR => Some(Quadrature::Polar {
                tri: std::array::from_fn(|k| glam::Vec3::from_slice(&self.aux[a + k][..3])),
                normal: glam::Vec3::from_slice(&self.aux[a + 3][..3]),
                factor: self.aux[a][3],
            }),
            MODE_POINTS => Some(Quadrature::Points {
                tri_j: corners(j),
                excess: self.aux[a][0],
                area_i: self.patches[4 * i as usize][3],
            }),
            _ => None,
        }
    }

    /// The spread σ of entry `e` when it is a link read at two distances, r ∓ σ.
    pub fn spread(&self, e: usize) -> Option<f32> {
        let meta = self.entries[e][3];
        (meta & 3 == MODE_FAR && meta & TWO_POINT != 0)
            .then(|| self.aux[(meta >> AUX_SHIFT) as usize][0])
    }

    /// The object patch `i` belongs to.
    pub fn object(&self, i: usize) -> usize {
        self.patches[4 * i + 3][3] as usize
    }

    /// Bytes the template holds on the device.
    fn device_bytes(&self) -> u64 {
        let nnz = self.nnz() as u64;
        alloc_size(16 * nnz)
            + alloc_size(16 * self.aux.len() as u64)
            + alloc_size(4 * self.col_ptr.len() as u64)
            + alloc_size(4 * nnz)
            + alloc_size(16 * self.patches.len() as u64)
            + alloc_size(4 * (self.n as u64 + 1))
            + alloc_size(4 * nnz)
            + alloc_size(4 * self.far.len().max(1) as u64)
            + alloc_size(12 * self.nodes.max(1) as u64)
            + alloc_size(12 * self.n.max(1) as u64)
            + alloc_size(4 * nnz)
            + 16
    }

    /// Columns of S: the patches, then the nodes a hierarchical S links to.
    pub fn n_cols(&self) -> usize {
        self.n + self.nodes
    }

    /// Whether any column reaches nodes (the link kernels run).
    pub fn has_links(&self) -> bool {
        self.nodes > 0 && self.col_ptr[self.n_cols()] > self.col_ptr[self.n]
    }
}

/// A plan as the template stores it: (mode, aux rows).
fn encode(q: &Quadrature) -> (u32, Vec<[f32; 4]>) {
    match *q {
        Quadrature::Far { .. } => (MODE_FAR, Vec::new()),
        Quadrature::Polar {
            tri,
            normal,
            factor,
        } => (
            MODE_POLAR,
            vec![
                [tri[0].x, tri[0].y, tri[0].z, factor],
                [tri[1].x, tri[1].y, tri[1].z, 0.0],
                [tri[2].x, tri[2].y, tri[2].z, 0.0],
                [normal.x, normal.y, normal.z, 0.0],
            ],
        ),
        Quadrature::Points { excess, .. } => (MODE_POINTS, vec![[excess, 0.0, 0.0, 0.0]]),
    }
}

/// The tables as `s_entries.wgsl` reads them: per slot 2 (N + 1) rows, (R, r_k), (W, 0).
pub fn table_rows(tables: &[Tabulated]) -> Result<(Vec<[f32; 4]>, u32), GpuError> {
    let n = tables.first().map_or(8, |t| t.grid().0.len() - 1);
    let mut rows = Vec::with_capacity(tables.len() * 2 * (n + 1));
    for t in tables {
        let (radii, r, w) = t.grid();
        if radii.len() != n + 1 {
            return Err(GpuError::Invalid(
                "profile tables of different sizes in one rebuild".into(),
            ));
        }
        for k in 0..=n {
            rows.push([r[k][0], r[k][1], r[k][2], radii[k]]);
            rows.push([w[k][0], w[k][1], w[k][2], 0.0]);
        }
    }
    Ok((rows, n as u32))
}

/// The objects as both kernels read them: (class, slot_r, slot_t, 0), (albedo bits, 0).
pub fn object_rows(objects: &[ObjectParams]) -> Vec<[u32; 4]> {
    objects
        .iter()
        .flat_map(|o| {
            [
                [o.class as u32, o.slot_r, o.slot_t, 0],
                [
                    o.albedo[0].to_bits(),
                    o.albedo[1].to_bits(),
                    o.albedo[2].to_bits(),
                    0,
                ],
            ]
        })
        .collect()
}

/// (cos θ_k, sin θ_k) of the polar integration's K directions, as
/// [`subsurface::polar_integral`] computes them.
pub fn directions(k: u32) -> Vec<[f32; 2]> {
    (0..k)
        .map(|dir| {
            let th = (dir as f32 + 0.5) * std::f32::consts::TAU / k as f32;
            [th.cos(), th.sin()]
        })
        .collect()
}

/// Keep in sync with `Params` in `s_entries.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct EntryParams {
    count: u32,
    groups_x: u32,
    m: u32,
    directions: u32,
    table_n: u32,
    _pad: [u32; 3],
}

/// Keep in sync with `Params` in `s_column_bound.wgsl`, `s_node_energy.wgsl` and
/// `s_link_bound.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ColumnParams {
    /// Patches.
    n: u32,
    groups_x: u32,
    /// Nodes (the link kernels).
    nodes: u32,
    _pad: u32,
}

/// Per object, how its columns stood against energy conservation: the largest
/// Σ_j A_j S_ji / A_i before scaling, and how many columns were scaled down.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ColumnReport {
    pub max_column: f32,
    pub scaled_columns: u32,
}

/// A template on the device.
#[derive(Debug)]
pub struct GpuSTemplate {
    pub template: STemplate,
    entries: wgpu::Buffer,
    aux: wgpu::Buffer,
    col_ptr: wgpu::Buffer,
    perm: wgpu::Buffer,
    patches: wgpu::Buffer,
    row_ptr: wgpu::Buffer,
    col: wgpu::Buffer,
    far: wgpu::Buffer,
    order: wgpu::Buffer,
    /// e_k per node, written by `s_node_energy` (12 bytes a node).
    node_energy: wgpu::Buffer,
    /// Each column's factor f between `s_link_bound`'s two passes (12 bytes a patch).
    factor: wgpu::Buffer,
    /// The read-back buffer of the last rebuild and its size, kept for the next one (a
    /// slider's rebuilds all read the same number of values back).
    read: std::sync::Mutex<Option<(wgpu::Buffer, u64)>>,
    bytes: u64,
}

/// What one device rebuild produced.
#[derive(Debug)]
pub struct DeviceS {
    /// S on the device, bound by the solve.
    pub s: GpuCsr,
    /// The same values on the CPU (explicit zeros kept: the template's structure).
    pub csr: Csr<Rgb>,
    pub reports: Vec<ColumnReport>,
}

impl DeviceS {
    /// Returns the values' bytes to the budget when S is dropped unused.
    pub fn release(self, ctx: &GpuContext) {
        ctx.release(self.s.bytes());
    }
}

impl GpuSTemplate {
    /// Uploads `t`; refuses one whose entries do not fit one storage binding (the kernels
    /// see the whole matrix at once) or the budget, or whose aux rows are more than an
    /// entry's meta word can index (2²⁸).
    pub fn upload(ctx: &GpuContext, what: &str, t: STemplate) -> Result<GpuSTemplate, GpuError> {
        if t.aux.len() as u64 > u64::from(u32::MAX >> AUX_SHIFT) {
            return Err(GpuError::Invalid(format!(
                "{what}: {} aux rows, more than an entry can index ({})",
                t.aux.len(),
                u32::MAX >> AUX_SHIFT
            )));
        }
        let largest = (16 * t.nnz() as u64)
            .max(16 * t.aux.len() as u64)
            .max(16 * t.patches.len() as u64)
            .max(4 * t.far.len() as u64);
        if largest > ctx.tile_bytes() {
            return Err(GpuError::MatrixTooLarge {
                what: format!("{what}: S's {} entries", t.nnz()),
                requested: largest,
                max_binding: ctx.tile_bytes(),
            });
        }
        let bytes = t.device_bytes();
        ctx.reserve(what, bytes)?;
        let rel: Vec<u32> = t.row_ptr.iter().map(|&p| p as u32).collect();
        // Without links the link kernels never run; their buffers hold one word.
        let far: &[u32] = if t.far.is_empty() { &[0] } else { &t.far };
        let made = ctx.scoped(|| {
            Ok((
                (
                    storage_init(ctx, what, bytemuck::cast_slice(&t.entries)),
                    storage_init(ctx, what, bytemuck::cast_slice(&t.aux)),
                    storage_init(ctx, what, bytemuck::cast_slice(&t.col_ptr)),
                    storage_init(ctx, what, bytemuck::cast_slice(&t.perm)),
                    storage_init(ctx, what, bytemuck::cast_slice(&t.patches)),
                ),
                (
                    storage_init(ctx, what, bytemuck::cast_slice(&rel)),
                    storage_init(ctx, what, bytemuck::cast_slice(&t.col)),
                    storage_init(ctx, what, bytemuck::cast_slice(far)),
                    storage_zeroed(ctx, what, 12 * t.nodes.max(1) as u64),
                    storage_init(ctx, what, bytemuck::cast_slice(&t.order)),
                    storage_zeroed(ctx, what, 12 * t.n.max(1) as u64),
                ),
            ))
        });
        match made {
            Ok((
                (entries, aux, col_ptr, perm, patches),
                (row_ptr, col, far, node_energy, order, factor),
            )) => Ok(GpuSTemplate {
                template: t,
                entries,
                aux,
                col_ptr,
                perm,
                patches,
                row_ptr,
                col,
                far,
                order,
                node_energy,
                factor,
                read: std::sync::Mutex::new(None),
                bytes,
            }),
            Err(e) => {
                ctx.release(bytes);
                Err(e)
            }
        }
    }

    /// GPU bytes held by the template (the values of each rebuild are the [`GpuCsr`]'s).
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Returns the template's bytes to the budget (its buffers go with it).
    pub fn release(self, ctx: &GpuContext) {
        ctx.release(self.bytes);
    }

    /// S for `m` (which the template must cover): `s_entries`, then `s_column_bound`, then
    /// one read-back of the values and the per-object reports.
    pub fn assemble(
        &self,
        ctx: &GpuContext,
        what: &str,
        m: &SMaterials,
        params: &SubsurfaceParams,
    ) -> Result<DeviceS, GpuError> {
        let (val, values, reports, val_bytes) = self.dispatch(ctx, what, m, params, None, true)?;
        let t = &self.template;
        let s = GpuCsr::from_device(
            ctx,
            what,
            (t.n, t.n_cols(), t.nnz()),
            (self.row_ptr.clone(), self.col.clone(), val),
            val_bytes,
        );
        Ok(DeviceS {
            s,
            csr: Csr {
                n_rows: t.n,
                n_cols: t.n_cols(),
                row_ptr: t.row_ptr.clone(),
                col: t.col.clone(),
                val: values,
            },
            reports,
        })
    }

    /// `s_entries` alone: the values before the column bound (tests hold it to its twin).
    pub fn entries_once(
        &self,
        ctx: &GpuContext,
        m: &SMaterials,
        params: &SubsurfaceParams,
    ) -> Result<Vec<Rgb>, GpuError> {
        let (val, values, _, bytes) = self.dispatch(ctx, "s_entries", m, params, None, false)?;
        drop(val);
        ctx.release(bytes);
        Ok(values)
    }

    /// `s_column_bound` alone on the values `val` (row order): the bounded values and the
    /// per-object reports.
    pub fn column_bound_once(
        &self,
        ctx: &GpuContext,
        m: &SMaterials,
        val: &[Rgb],
    ) -> Result<(Vec<Rgb>, Vec<ColumnReport>), GpuError> {
        let params = SubsurfaceParams::default();
        let (buf, values, reports, bytes) =
            self.dispatch(ctx, "s_column_bound", m, &params, Some(val), true)?;
        drop(buf);
        ctx.release(bytes);
        Ok((values, reports))
    }

    /// Runs `s_entries` (or starts from `input`) and, when `bound`, `s_column_bound`; reads
    /// the values and reports back. Returns the value buffer and its reserved bytes.
    fn dispatch(
        &self,
        ctx: &GpuContext,
        what: &str,
        m: &SMaterials,
        params: &SubsurfaceParams,
        input: Option<&[Rgb]>,
        bound: bool,
    ) -> Result<Dispatched, GpuError> {
        if !self.template.covers(m) {
            return Err(GpuError::Invalid(format!(
                "{what}: the S template does not cover these materials"
            )));
        }
        let t = &self.template;
        let nnz = t.nnz();
        if input.is_some_and(|v| v.len() != nnz) {
            return Err(GpuError::Invalid(format!(
                "{what}: {} values for {nnz} entries",
                input.map_or(0, |v| v.len())
            )));
        }
        let val_bytes = alloc_size(12 * nnz as u64);
        let (rows, table_n) = table_rows(&m.tables)?;
        let objects = object_rows(&m.objects);
        let report_bytes = alloc_size(8 * m.objects.len() as u64);
        ctx.reserve(what, val_bytes)?;
        let made = ctx.scoped(|| {
            let k = &ctx.kernels;
            let val = match input {
                Some(v) => storage_init(ctx, what, bytemuck::cast_slice(v)),
                None => storage_zeroed(ctx, what, 12 * nnz as u64),
            };
            let tables = storage_init(ctx, what, bytemuck::cast_slice(&rows));
            let objs = storage_init(ctx, what, bytemuck::cast_slice(&objects));
            let dirs = storage_init(
                ctx,
                what,
                bytemuck::cast_slice(&directions(params.directions.max(1))),
            );
            let report = storage_zeroed(ctx, what, report_bytes);
            let eg = grid((nnz as u32).div_ceil(WG));
            let ep = uniform(
                ctx,
                what,
                &EntryParams {
                    count: nnz as u32,
                    groups_x: eg.0,
                    m: params.samples.max(1),
                    directions: params.directions.max(1),
                    table_n,
                    _pad: [0; 3],
                },
            );
            // One thread a column: patches (`s_column_bound`, `s_link_bound`) or nodes
            // (`s_node_energy`).
            let columns = |count: usize| {
                let g = grid((count.max(1) as u32).div_ceil(WG));
                let params = ColumnParams {
                    n: t.n as u32,
                    groups_x: g.0,
                    nodes: t.nodes as u32,
                    _pad: 0,
                };
                (g, uniform(ctx, what, &params))
            };
            let (cg, cp) = columns(t.n);
            let (ng, np) = columns(t.nodes);
            let kept = self
                .read
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .take()
                .filter(|(_, size)| *size == val_bytes);
            let val_read = match kept {
                Some((b, _)) => b,
                None => staging(ctx, "S read", val_bytes),
            };
            let report_read = staging(ctx, "S report read", report_bytes);
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            if input.is_none() {
                let bg = k.s_entries.bind(
                    &ctx.device,
                    &ep,
                    &[
                        &self.entries,
                        &self.patches,
                        &self.aux,
                        &tables,
                        &objs,
                        &dirs,
                        &val,
                        &self.order,
                    ],
                );
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&k.s_entries_pipeline);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(eg.0, eg.1, 1);
            }
            if bound {
                let bg = k.s_column_bound.bind(
                    &ctx.device,
                    &cp,
                    &[
                        &self.col_ptr,
                        &self.perm,
                        &self.entries,
                        &self.patches,
                        &objs,
                        &val,
                        &report,
                    ],
                );
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&k.s_column_bound_pipeline);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(cg.0, cg.1, 1);
            }
            if bound && t.has_links() {
                // What each node re-emits through its links, then each patch column with
                // the nodes that hold it (after the direct bound, as the CPU's add_links).
                let bg = k.s_node_energy.bind(
                    &ctx.device,
                    &np,
                    &[
                        &self.col_ptr,
                        &self.perm,
                        &self.entries,
                        &self.patches,
                        &val,
                        &self.node_energy,
                    ],
                );
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&k.s_node_energy_pipeline);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(ng.0, ng.1, 1);
                drop(pass);
                // Each column's factor, each node's links by its patches' mean factor,
                // then the direct entries (the CPU's add_links, step for step).
                let bound = k.s_link_bound.bind(
                    &ctx.device,
                    &cp,
                    &[
                        &self.col_ptr,
                        &self.perm,
                        &self.entries,
                        &self.patches,
                        &val,
                        &report,
                        &self.node_energy,
                        &self.far,
                        &self.factor,
                    ],
                );
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&k.s_link_factor_pipeline);
                pass.set_bind_group(0, &bound, &[]);
                pass.dispatch_workgroups(cg.0, cg.1, 1);
                drop(pass);
                let bg = k.s_link_scale.bind(
                    &ctx.device,
                    &np,
                    &[
                        &self.col_ptr,
                        &self.perm,
                        &self.patches,
                        &val,
                        &self.node_energy,
                        &self.far,
                        &self.factor,
                    ],
                );
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&k.s_link_scale_pipeline);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(ng.0, ng.1, 1);
                drop(pass);
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&k.s_link_bound_pipeline);
                pass.set_bind_group(0, &bound, &[]);
                pass.dispatch_workgroups(cg.0, cg.1, 1);
            }
            // The kernels, waited for on their own (so the log can tell them from the
            // read-back), then the copies.
            let t0 = std::time::Instant::now();
            ctx.queue.submit([enc.finish()]);
            ctx.device
                .poll(wgpu::PollType::wait_indefinitely())
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            let kernels_ms = t0.elapsed().as_secs_f64() * 1e3;
            let t0 = std::time::Instant::now();
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            enc.copy_buffer_to_buffer(&val, 0, &val_read, 0, val_bytes);
            enc.copy_buffer_to_buffer(&report, 0, &report_read, 0, report_bytes);
            ctx.queue.submit([enc.finish()]);
            // The values as RGB triplets, one copy out of the mapped range.
            let values: Vec<Rgb> = ctx.read_back_as(&val_read, val_bytes)?;
            *self.read.lock().unwrap_or_else(|p| p.into_inner()) = Some((val_read, val_bytes));
            let report: Vec<u32> = ctx.read_back_as(&report_read, report_bytes)?;
            tracing::debug!(
                entries = nnz,
                kernels_ms,
                read_back_ms = t0.elapsed().as_secs_f64() * 1e3,
                "S on the device"
            );
            Ok((val, values, report))
        });
        let (val, values, report) = match made {
            Ok(v) => v,
            Err(e) => {
                ctx.release(val_bytes);
                return Err(e);
            }
        };
        let mut values = values;
        values.truncate(nnz);
        let reports = report[..2 * m.objects.len()]
            .chunks_exact(2)
            .map(|w| ColumnReport {
                max_column: f32::from_bits(w[0]),
                scaled_columns: w[1],
            })
            .collect();
        Ok((val, values, reports, val_bytes))
    }
}
