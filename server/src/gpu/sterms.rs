//! A translucency change written on the device: one object's rows of S summed from its
//! radial terms (`s_terms.wgsl`) into S's values where the solve reads them.
//!
//! In: the object's flat terms ([`FlatTerms`], uploaded once), and per change the tables of
//! its new profiles ([`FlatTable`]) and the energy bound's rule (from the column and node
//! sums to the factors, [`translux_engine::sterms::ObjectTerms::factors_from_sums`]). Out:
//! the object's values of a device S ([`GpuCsr`]), as the engine's
//! `ObjectTerms::write` makes them on the CPU (its twin), to f32 rounding.
//!
//! A change is two submissions: the values and the sums, whose (n + nodes) × 16 bytes are
//! read back for the bound (taken on the host, by the engine's own rule); then the factors
//! up, the scaling, the node rows pushed down to the patches where S has them, and the
//! copies into S.
//!
//! [`MaterialsOnDevice`] is what the backend keeps per scene: S of the last material
//! overrides as a system beside the scene's F, and the objects a slider's change rewrites.

use std::borrow::Cow;

use translux_engine::backend::SceneRef;
use translux_engine::radiosity::Rgb;
use translux_engine::smatrix::{self, OverrideMaterials, PatchGeometry, SParams};
use translux_engine::sterms::{ColumnFactors, FlatTable, FlatTerms, STerms, ValueRun};
use translux_engine::transport::push_node_rows;
use translux_proto::csr::ValidCsr;
use translux_proto::scene::Material;

use super::matrix::{alloc_size, staging, storage_init, storage_zeroed, uniform};
use super::{GpuContext, GpuCsr, GpuError, GpuSystem, grid};

/// `s_terms.wgsl`'s `Table`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct TableParams {
    base: u32,
    w_base: u32,
    end: f32,
    r_max: f32,
    scale: f32,
    cells_f: f32,
    _pad: [u32; 2],
}

/// `s_terms.wgsl`'s `Params`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    rows: u32,
    n: u32,
    nodes: u32,
    grid_x: u32,
    column_ptr: u32,
    node_ptr: u32,
    column_items: u32,
    node_items: u32,
    push_ptr: u32,
    push_items: u32,
    pushed: u32,
    _pad: u32,
    same: TableParams,
    other: TableParams,
}

/// Threads per workgroup of `s_terms.wgsl`.
const WG: u32 = 64;

/// One object's terms on the device, with the buffers its changes write.
#[derive(Debug)]
pub struct GpuObjectTerms {
    params: wgpu::Buffer,
    base: Params,
    rows: wgpu::Buffer,
    entries: wgpu::Buffer,
    terms: wgpu::Buffer,
    links: wgpu::Buffer,
    gather: wgpu::Buffer,
    sums: wgpu::Buffer,
    values: wgpu::Buffer,
    /// The values of S with node rows pushed to the patches (a stand-in of 16 bytes
    /// without node rows).
    pushed: wgpu::Buffer,
    sums_read: wgpu::Buffer,
    groups: (u32, u32),
    runs: Vec<ValueRun>,
    n: usize,
    nodes: usize,
    bytes: u64,
}

/// What one change did on the device.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ChangeCounts {
    pub submissions: u32,
    pub bytes_up: u64,
    pub bytes_down: u64,
}

impl GpuObjectTerms {
    /// Uploads `flat` (`what` names it in errors and the memory budget).
    pub fn upload(ctx: &GpuContext, what: &str, flat: &FlatTerms) -> Result<Self, GpuError> {
        let (gather, at) = gather_of(flat);
        let arrays = [
            records(&flat.rows),
            records(&flat.entries),
            records(&flat.terms),
            records(&flat.links),
            records(&gather),
        ];
        let sums_len = 16 * (flat.n + flat.nodes) as u64;
        let bytes = arrays
            .iter()
            .map(|a| alloc_size(a.len() as u64))
            .sum::<u64>()
            + 2 * alloc_size(sums_len)
            + alloc_size(12 * flat.values as u64)
            + alloc_size(12 * flat.pushed as u64);
        let max_binding = ctx.adapter().max_binding_bytes;
        if let Some(a) = arrays.iter().find(|a| a.len() as u64 > max_binding) {
            return Err(GpuError::MatrixTooLarge {
                what: format!("{what}'s radial terms"),
                requested: a.len() as u64,
                max_binding,
            });
        }
        ctx.reserve(what, bytes)?;
        let (n, nodes) = (flat.n as u32, flat.nodes as u32);
        let pushed = flat.pushed as u32;
        let threads = (flat.rows.len() as u32).max(n).max(nodes).max(pushed);
        let groups = grid(threads.div_ceil(WG));
        let base = Params {
            rows: flat.rows.len() as u32,
            n,
            nodes,
            grid_x: groups.0,
            column_ptr: at[0],
            node_ptr: at[1],
            column_items: at[2],
            node_items: at[3],
            push_ptr: at[4],
            push_items: at[5],
            pushed,
            ..Default::default()
        };
        let [rows, entries, terms, links, gather] = arrays;
        let made = ctx.scoped(|| {
            Ok(GpuObjectTerms {
                params: uniform(ctx, what, &base),
                base,
                rows: storage_init(ctx, what, &rows),
                entries: storage_init(ctx, what, &entries),
                terms: storage_init(ctx, what, &terms),
                links: storage_init(ctx, what, &links),
                gather: storage_init(ctx, what, &gather),
                sums: storage_zeroed(ctx, what, sums_len),
                values: storage_zeroed(ctx, what, 12 * flat.values as u64),
                pushed: storage_zeroed(ctx, what, 12 * flat.pushed as u64),
                sums_read: staging(ctx, what, sums_len),
                groups,
                runs: flat.runs.clone(),
                n: flat.n,
                nodes: flat.nodes,
                bytes,
            })
        });
        if made.is_err() {
            ctx.release(bytes);
        }
        made
    }

    /// Bytes held on the device.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Writes the object's values of `s` under the tables `same` and `other` (a sheet's
    /// transmittance; none for a translucent object, which reads `same` alone): the values and sums, then
    /// `bound` from the columns' and nodes' sums to the factors, then the scaling and the
    /// copies into `s`. Counts what crossed the bus.
    pub fn write(
        &self,
        ctx: &GpuContext,
        s: &GpuCsr,
        (same, other): (&FlatTable, Option<&FlatTable>),
        bound: impl FnOnce(&[Rgb], &[Rgb]) -> ColumnFactors,
    ) -> Result<ChangeCounts, GpuError> {
        let mut counts = ChangeCounts::default();
        ctx.scoped(|| {
            let (tables, params) = self.tables(same, other);
            let tables = storage_init(ctx, "S tables", bytemuck::cast_slice(&tables));
            ctx.queue
                .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
            counts.bytes_up += tables.size() + std::mem::size_of::<Params>() as u64;
            let bind = self.bind(ctx, &tables);
            let k = &ctx.kernels;
            let sums_len = 16 * (self.n + self.nodes) as u64;
            // The values, then the sums the bound reads, read back.
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_bind_group(0, &bind, &[]);
                for p in [&k.s_write, &k.s_column_sums, &k.s_node_sums] {
                    pass.set_pipeline(p);
                    pass.dispatch_workgroups(self.groups.0, self.groups.1, 1);
                }
            }
            enc.copy_buffer_to_buffer(&self.sums, 0, &self.sums_read, 0, alloc_size(sums_len));
            ctx.queue.submit([enc.finish()]);
            let sums: Vec<[f32; 4]> = ctx.read_back_as(&self.sums_read, alloc_size(sums_len))?;
            counts.bytes_down += alloc_size(sums_len);
            let rgb = |v: &[f32; 4]| [v[0], v[1], v[2]];
            let column: Vec<Rgb> = sums[..self.n].iter().map(rgb).collect();
            let node: Vec<Rgb> = sums[self.n..self.n + self.nodes].iter().map(rgb).collect();
            // The factors over the sums, the values scaled by them and copied into S.
            let f = bound(&column, &node);
            let factors: Vec<[f32; 4]> = f
                .patches
                .iter()
                .chain(&f.nodes)
                .map(|c| [c[0], c[1], c[2], 0.0])
                .collect();
            if factors.len() != self.n + self.nodes {
                return Err(GpuError::Invalid(format!(
                    "{} factors for {} columns and {} nodes",
                    factors.len(),
                    self.n,
                    self.nodes
                )));
            }
            ctx.queue
                .write_buffer(&self.sums, 0, bytemuck::cast_slice(&factors));
            counts.bytes_up += sums_len;
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_bind_group(0, &bind, &[]);
                pass.set_pipeline(&k.s_scale);
                pass.dispatch_workgroups(self.groups.0, self.groups.1, 1);
                if self.base.pushed > 0 {
                    pass.set_pipeline(&k.s_push);
                    pass.dispatch_workgroups(self.groups.0, self.groups.1, 1);
                }
            }
            let from = if self.base.pushed > 0 {
                &self.pushed
            } else {
                &self.values
            };
            s.copy_values_in(&mut enc, from, &self.runs);
            ctx.queue.submit([enc.finish()]);
            counts.submissions = 2;
            Ok(())
        })?;
        Ok(counts)
    }

    /// The tables' cells one after the other (`other`'s only for a sheet: without it the
    /// other side reads `same`), and the parameters that find them.
    fn tables(&self, same: &FlatTable, other: Option<&FlatTable>) -> (Vec<[f32; 4]>, Params) {
        let cells_of = |t: &FlatTable| 2 * t.cells.len();
        let mut cells = Vec::with_capacity(cells_of(same) + other.map_or(0, cells_of));
        let mut header = |t: &FlatTable| {
            let base = cells.len() as u32;
            cells.extend(t.cells.iter().flatten().copied());
            TableParams {
                base,
                w_base: t.w_base,
                end: t.end,
                r_max: t.r_max,
                scale: t.scale,
                cells_f: t.cells_f,
                _pad: [0; 2],
            }
        };
        let same = header(same);
        let other = other.map_or(same, header);
        let params = Params {
            same,
            other,
            ..self.base
        };
        (cells, params)
    }

    fn bind(&self, ctx: &GpuContext, tables: &wgpu::Buffer) -> wgpu::BindGroup {
        ctx.kernels.s_terms.bind(
            &ctx.device,
            &self.params,
            &[
                tables,
                &self.rows,
                &self.entries,
                &self.terms,
                &self.links,
                &self.gather,
                &self.sums,
                &self.values,
                &self.pushed,
            ],
        )
    }

    /// Gives its memory back to the budget.
    pub fn release(self, ctx: &GpuContext) {
        ctx.release(self.bytes);
    }
}

/// `items` as bytes, or one zeroed record where there are none (a binding holds at least
/// one of its array's elements: an object without links still binds `links`).
fn records<T: bytemuck::Pod>(items: &[T]) -> Cow<'_, [u8]> {
    if items.is_empty() {
        Cow::Owned(vec![0u8; std::mem::size_of::<T>()])
    } else {
        Cow::Borrowed(bytemuck::cast_slice(items))
    }
}

/// The column and node pointers, the column and node items, then the pushed values'
/// pointers and items, one after another as `s_terms.wgsl`'s `gather` reads them; and where
/// each of the six starts.
fn gather_of(flat: &FlatTerms) -> (Vec<u32>, [u32; 6]) {
    let parts: [&[u32]; 6] = [
        &flat.column_ptr,
        &flat.node_ptr,
        flat.column_items.as_flattened(),
        flat.node_items.as_flattened(),
        &flat.push_ptr,
        &flat.push_items,
    ];
    let mut g = Vec::with_capacity(parts.iter().map(|p| p.len()).sum());
    let mut at = [0u32; 6];
    for (a, p) in at.iter_mut().zip(parts) {
        *a = g.len() as u32;
        g.extend_from_slice(p);
    }
    (g, at)
}

/// S of a set of material overrides on the device ([`crate::backend`]'s solves with
/// overridden materials): a system over the scene's F with K = that S, the radial terms of
/// the objects a change rewrites there, and the overrides its values hold. A change that
/// only moves those objects' profiles (a translucency slider) is written in place
/// ([`MaterialsOnDevice::write`]); anything else is uploaded afresh from the CPU's S.
#[derive(Debug)]
pub struct MaterialsOnDevice {
    /// The CPU's S layout it was uploaded from ([`OverrideMaterials::layout`]).
    pub layout: u64,
    pub system: GpuSystem,
    /// The objects whose rows a change writes here, by object index.
    objects: Vec<(usize, GpuObjectTerms)>,
    /// The overrides S's values are for.
    written: Vec<(usize, Material)>,
    geometry: PatchGeometry,
}

/// Why S could not be written in place: it is uploaded afresh instead.
#[derive(Debug)]
pub enum Rewrite {
    /// Something other than the profiles of objects held here changed.
    Upload,
    Failed(GpuError),
}

impl MaterialsOnDevice {
    /// `s` (S for `m`, made on the CPU) as K beside `base`'s F, and the radial terms of
    /// every overridden translucent object and thin sheet whose rows `s` lays out as its
    /// terms do (the others are uploaded afresh when they change).
    pub fn upload(
        ctx: &GpuContext,
        (scene, terms): (SceneRef<'_>, &STerms),
        base: &GpuSystem,
        m: &OverrideMaterials,
        s: &ValidCsr<Rgb>,
    ) -> Result<Self, GpuError> {
        // S's node rows pushed down to the patches (the device multiplies patch rows alone).
        let pushed = match scene.bundle.tree().filter(|_| s.view().n_rows() > base.n()) {
            Some(tree) => Some(
                push_node_rows(s.view(), tree)
                    .and_then(ValidCsr::new)
                    .map_err(|e| GpuError::Invalid(format!("{}: S's node rows: {e}", scene.id)))?,
            ),
            None => None,
        };
        let device_s = pushed.as_ref().unwrap_or(s);
        let system = base.with_s(
            ctx,
            &format!("{} S of its materials", scene.id),
            &device_s.view(),
        )?;
        let geometry = smatrix::bundle_geometry(scene.bundle);
        let mut objects = Vec::new();
        for (k, material) in &m.overrides {
            let sheet = match material {
                Material::Translucent { .. } => false,
                Material::ThinSheet { .. } => true,
                _ => continue,
            };
            let (Some(t), Some((area, at))) = (
                terms.get(*k, sheet),
                smatrix::object_placement(scene.bundle, &geometry, *k),
            ) else {
                continue;
            };
            let Ok(mut flat) = t.flatten(area, at, s.view().row_ptr()) else {
                continue;
            };
            if let Some(p) = &pushed
                && t.push_into(&mut flat, at, &p.view()).is_err()
            {
                continue;
            }
            let what = format!("{} object {k}", scene.id);
            match GpuObjectTerms::upload(ctx, &what, &flat) {
                Ok(o) => objects.push((*k, o)),
                Err(e) => {
                    for (_, o) in objects {
                        o.release(ctx);
                    }
                    system.release(ctx);
                    return Err(e);
                }
            }
        }
        Ok(MaterialsOnDevice {
            layout: m.layout,
            system,
            objects,
            written: m.overrides.clone(),
            geometry,
        })
    }

    /// Bytes held on the device (its K and vectors, and the objects' terms).
    pub fn bytes(&self) -> u64 {
        self.system.own_bytes() + self.objects.iter().map(|(_, o)| o.bytes()).sum::<u64>()
    }

    /// Writes the rows of the objects whose profiles differ between the overrides held and
    /// `overrides` (of this layout) from their radial terms, as the CPU's
    /// `smatrix::rewrite_with_terms` would; what crossed the bus. [`Rewrite::Upload`] when
    /// anything else differs.
    pub fn write(
        &mut self,
        ctx: &GpuContext,
        (scene, terms): (SceneRef<'_>, &STerms),
        overrides: &[(usize, Material)],
    ) -> Result<ChangeCounts, Rewrite> {
        let changed =
            smatrix::changed_profiles(&self.written, overrides, terms).ok_or(Rewrite::Upload)?;
        let params = SParams::default();
        let mut counts = ChangeCounts::default();
        for k in changed {
            let sheet = matches!(
                overrides.iter().find(|(o, _)| *o == k),
                Some((_, Material::ThinSheet { .. }))
            );
            let (Some(t), Some((_, dev))) = (
                terms.get(k, sheet),
                self.objects.iter().find(|(o, _)| *o == k),
            ) else {
                return Err(Rewrite::Upload);
            };
            let (area, at) = smatrix::object_placement(scene.bundle, &self.geometry, k)
                .ok_or(Rewrite::Upload)?;
            let (same, other) = smatrix::object_flat_tables(scene.bundle, overrides, k, &params)
                .map_err(|_| Rewrite::Upload)?;
            let c = dev
                .write(
                    ctx,
                    self.system.k(),
                    (&same, other.as_ref()),
                    |column, node| t.factors_from_sums(area, at, column, node),
                )
                .map_err(Rewrite::Failed)?;
            counts.submissions += c.submissions;
            counts.bytes_up += c.bytes_up;
            counts.bytes_down += c.bytes_down;
        }
        self.written = overrides.to_vec();
        Ok(counts)
    }

    /// Gives its memory back to the budget.
    pub fn release(self, ctx: &GpuContext) {
        for (_, o) in self.objects {
            o.release(ctx);
        }
        self.system.release(ctx);
    }
}
