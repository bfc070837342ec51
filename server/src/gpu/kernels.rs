//! The compute pipelines, compiled once per device: one WGSL file per kernel, each with an
//! explicit bind-group layout so that every variant of a kernel (override constants) accepts
//! the same bind groups.

use std::collections::HashMap;
use std::sync::Mutex;

/// WGSL sources, one file per kernel.
pub const CSR_SPMV_RGB: &str = include_str!("kernels/csr_spmv_rgb.wgsl");
pub const DENSE_MATMUL_RGB: &str = include_str!("kernels/dense_matmul_rgb.wgsl");
pub const JACOBI_UPDATE: &str = include_str!("kernels/jacobi_update.wgsl");
pub const REDUCE_SUM: &str = include_str!("kernels/reduce_sum.wgsl");
pub const MR_STEP: &str = include_str!("kernels/mr_step.wgsl");
pub const MR_ALPHA: &str = include_str!("kernels/mr_alpha.wgsl");
/// The BVH traversal `shadow_rays` and `direct_light` share, put in front of each source.
pub const BVH_TRAVERSE: &str = include_str!("kernels/bvh_traverse.wgsl");
pub const SHADOW_RAYS: &str = include_str!("kernels/shadow_rays.wgsl");
pub const DIRECT_LIGHT: &str = include_str!("kernels/direct_light.wgsl");
pub const VERTEX_COLOURS: &str = include_str!("kernels/vertex_colours.wgsl");
pub const ENV_IRRADIANCE: &str = include_str!("kernels/env_irradiance.wgsl");
pub const S_TERMS: &str = include_str!("kernels/s_terms.wgsl");

/// Relights one batched device solve carries (`KV` of the batch's `csr_spmv_rgb`; at most
/// its `KMAX`).
pub const BATCH: u32 = 8;

/// A binding's kind, in binding order after the uniform at binding 0.
#[derive(Debug, Clone, Copy)]
enum Slot {
    Read,
    ReadWrite,
}

/// One kernel: its module, its bind-group layout and pipeline layout.
#[derive(Debug)]
pub struct Kernel {
    pub(crate) layout: wgpu::BindGroupLayout,
    pipeline_layout: wgpu::PipelineLayout,
    module: wgpu::ShaderModule,
    name: &'static str,
}

impl Kernel {
    fn new(device: &wgpu::Device, name: &'static str, src: &str, slots: &[Slot]) -> Kernel {
        let mut entries = vec![wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        }];
        for (k, s) in slots.iter().enumerate() {
            entries.push(wgpu::BindGroupLayoutEntry {
                binding: k as u32 + 1,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage {
                        read_only: matches!(s, Slot::Read),
                    },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            });
        }
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some(name),
            entries: &entries,
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(name),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(name),
            source: wgpu::ShaderSource::Wgsl(src.into()),
        });
        Kernel {
            layout,
            pipeline_layout,
            module,
            name,
        }
    }

    /// A pipeline of this kernel with the given override constants.
    fn pipeline(&self, device: &wgpu::Device, constants: &[(&str, f64)]) -> wgpu::ComputePipeline {
        device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(self.name),
            layout: Some(&self.pipeline_layout),
            module: &self.module,
            entry_point: Some("main"),
            compilation_options: wgpu::PipelineCompilationOptions {
                constants,
                // Every kernel writes its workgroup memory before reading it.
                zero_initialize_workgroup_memory: false,
            },
            cache: None,
        })
    }

    /// A bind group: `uniform` at binding 0, then `buffers` in order.
    pub(crate) fn bind(
        &self,
        device: &wgpu::Device,
        uniform: &wgpu::Buffer,
        buffers: &[&wgpu::Buffer],
    ) -> wgpu::BindGroup {
        let mut entries = vec![wgpu::BindGroupEntry {
            binding: 0,
            resource: uniform.as_entire_binding(),
        }];
        for (k, b) in buffers.iter().enumerate() {
            entries.push(wgpu::BindGroupEntry {
                binding: k as u32 + 1,
                resource: b.as_entire_binding(),
            });
        }
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(self.name),
            layout: &self.layout,
            entries: &entries,
        })
    }
}

/// Every kernel and the pipelines built from it.
#[derive(Debug)]
pub struct Kernels {
    pub(crate) spmv: Kernel,
    pub(crate) dense: Kernel,
    pub(crate) jacobi: Kernel,
    pub(crate) reduce: Kernel,
    pub(crate) mr: Kernel,
    pub(crate) alpha: Kernel,
    pub(crate) shadow: Kernel,
    pub(crate) direct: Kernel,
    pub(crate) colours: Kernel,
    pub(crate) env: Kernel,
    pub(crate) s_terms: Kernel,
    pub(crate) spmv_scalar: wgpu::ComputePipeline,
    pub(crate) spmv_rgb: wgpu::ComputePipeline,
    /// The same for [`BATCH`] vectors at once.
    pub(crate) spmv_scalar_batch: wgpu::ComputePipeline,
    pub(crate) spmv_rgb_batch: wgpu::ComputePipeline,
    pub(crate) jacobi_update: wgpu::ComputePipeline,
    pub(crate) reduce_sum: wgpu::ComputePipeline,
    /// `mr_step` by its `STAGE`: the residual, the dots, the update.
    pub(crate) mr_residual: wgpu::ComputePipeline,
    pub(crate) mr_dots: wgpu::ComputePipeline,
    pub(crate) mr_update: wgpu::ComputePipeline,
    pub(crate) mr_alpha: wgpu::ComputePipeline,
    pub(crate) shadow_rays: wgpu::ComputePipeline,
    pub(crate) direct_light: wgpu::ComputePipeline,
    pub(crate) vertex_colours: wgpu::ComputePipeline,
    pub(crate) env_irradiance: wgpu::ComputePipeline,
    /// `s_terms` by its `STAGE`: the rows' values, the column sums, the node sums, the
    /// scaling by the energy bound's factors, the node rows pushed to the patches.
    pub(crate) s_write: wgpu::ComputePipeline,
    pub(crate) s_column_sums: wgpu::ComputePipeline,
    pub(crate) s_node_sums: wgpu::ComputePipeline,
    pub(crate) s_scale: wgpu::ComputePipeline,
    pub(crate) s_push: wgpu::ComputePipeline,
    /// `dense_matmul_rgb` by (f16 storage, vector lanes), built on first use.
    dense_variants: Mutex<HashMap<(bool, u32), wgpu::ComputePipeline>>,
}

impl Kernels {
    pub fn new(device: &wgpu::Device) -> Kernels {
        use Slot::{Read, ReadWrite};
        let spmv = Kernel::new(
            device,
            "csr_spmv_rgb",
            CSR_SPMV_RGB,
            &[Read, Read, Read, Read, ReadWrite],
        );
        let dense = Kernel::new(
            device,
            "dense_matmul_rgb",
            DENSE_MATMUL_RGB,
            &[Read, Read, ReadWrite],
        );
        let jacobi = Kernel::new(
            device,
            "jacobi_update",
            JACOBI_UPDATE,
            &[Read, Read, ReadWrite, ReadWrite],
        );
        let reduce = Kernel::new(
            device,
            "reduce_sum",
            REDUCE_SUM,
            &[Read, ReadWrite, ReadWrite, ReadWrite],
        );
        let mr = Kernel::new(
            device,
            "mr_step",
            MR_STEP,
            &[Read, Read, Read, ReadWrite, ReadWrite, ReadWrite],
        );
        let alpha = Kernel::new(device, "mr_alpha", MR_ALPHA, &[Read, ReadWrite]);
        let colours = Kernel::new(
            device,
            "vertex_colours",
            VERTEX_COLOURS,
            &[Read, Read, Read, Read, Read, Read, Read, Read, ReadWrite],
        );
        let env = Kernel::new(
            device,
            "env_irradiance",
            ENV_IRRADIANCE,
            &[Read, Read, ReadWrite, ReadWrite],
        );
        // Bindings 1 and 2 (nodes, triangles) are the traversal's, declared in BVH_TRAVERSE.
        let shadow = Kernel::new(
            device,
            "shadow_rays",
            &format!("{BVH_TRAVERSE}\n{SHADOW_RAYS}"),
            &[Read, Read, Read, ReadWrite],
        );
        let direct = Kernel::new(
            device,
            "direct_light",
            &format!("{BVH_TRAVERSE}\n{DIRECT_LIGHT}"),
            &[Read, Read, Read, Read, Read, ReadWrite],
        );
        let s_terms = Kernel::new(
            device,
            "s_terms",
            S_TERMS,
            &[
                Read, Read, Read, Read, Read, Read, ReadWrite, ReadWrite, ReadWrite,
            ],
        );
        let stage = |k: f64| s_terms.pipeline(device, &[("STAGE", k)]);
        Kernels {
            s_write: stage(0.0),
            s_column_sums: stage(1.0),
            s_node_sums: stage(2.0),
            s_scale: stage(3.0),
            s_push: stage(4.0),
            spmv_scalar: spmv.pipeline(device, &[("VAL_RGB", 0.0)]),
            spmv_rgb: spmv.pipeline(device, &[("VAL_RGB", 1.0)]),
            spmv_scalar_batch: spmv.pipeline(device, &[("VAL_RGB", 0.0), ("KV", BATCH as f64)]),
            spmv_rgb_batch: spmv.pipeline(device, &[("VAL_RGB", 1.0), ("KV", BATCH as f64)]),
            jacobi_update: jacobi.pipeline(device, &[]),
            reduce_sum: reduce.pipeline(device, &[]),
            mr_residual: mr.pipeline(device, &[("STAGE", 0.0)]),
            mr_dots: mr.pipeline(device, &[("STAGE", 1.0)]),
            mr_update: mr.pipeline(device, &[("STAGE", 2.0)]),
            mr_alpha: alpha.pipeline(device, &[]),
            shadow_rays: shadow.pipeline(device, &[]),
            direct_light: direct.pipeline(device, &[]),
            vertex_colours: colours.pipeline(device, &[]),
            env_irradiance: env.pipeline(device, &[]),
            spmv,
            dense,
            jacobi,
            reduce,
            mr,
            alpha,
            shadow,
            direct,
            colours,
            env,
            s_terms,
            dense_variants: Mutex::new(HashMap::new()),
        }
    }

    /// The `dense_matmul_rgb` pipeline for f16 (or f32) storage and `kv` vector lanes.
    pub(crate) fn dense_pipeline(
        &self,
        device: &wgpu::Device,
        f16: bool,
        kv: u32,
    ) -> wgpu::ComputePipeline {
        let mut cache = self
            .dense_variants
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        cache
            .entry((f16, kv))
            .or_insert_with(|| {
                self.dense.pipeline(
                    device,
                    &[("F16", if f16 { 1.0 } else { 0.0 }), ("KV", kv as f64)],
                )
            })
            .clone()
    }
}
