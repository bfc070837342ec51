//! Matrices on the device, split into row blocks that each fit one storage binding.
//!
//! ```text
//!  CSR (F: f32 values, S: RGB values)        dense T ([row][col][RGB], f16 or f32)
//!  block 0: rows [0, r1)   row_ptr (u32, relative), col, val      rows [0, r1)
//!  block 1: rows [r1, r2)  ...                                    rows [r1, r2) ...
//! ```
//!
//! A CSR block ends before its `col` or `val` array would pass the tile size; a dense block
//! holds as many whole rows as fit (an even number of elements before it, so an f16's
//! position in its u32 is the parity of its index). Every block is dispatched on its own
//! and writes its own rows of the output, so no block needs another's data.

use translux_proto::csr::CsrView;
use wgpu::util::DeviceExt;

use super::cpu_twin::{DENSE_ROWS, DenseData, dense_vector_lanes};
use super::{GpuContext, GpuError, grid};
use translux_engine::radiosity::Rgb;

/// Keep in sync with `Params` in `csr_spmv_rgb.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct CsrParams {
    row0: u32,
    rows: u32,
    groups_x: u32,
    _pad: u32,
    /// RGB entries between a batch's vectors in x (A's columns) and y (A's rows).
    x_stride: u32,
    y_stride: u32,
    _pad1: u32,
    _pad2: u32,
}

/// Keep in sync with `Params` in `dense_matmul_rgb.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct DenseParams {
    row0: u32,
    rows: u32,
    n_cols: u32,
    k: u32,
    v0: u32,
    groups_x: u32,
    _pad0: u32,
    _pad1: u32,
}

/// Rows per workgroup of `csr_spmv_rgb.wgsl` (`ROWS_PER_WG`).
const SPMV_ROWS_PER_WG: u32 = 8;

/// A storage buffer holding `bytes` (padded to at least 16 bytes: bindings cannot be empty).
pub(crate) fn storage_init(ctx: &GpuContext, label: &str, bytes: &[u8]) -> wgpu::Buffer {
    let usage =
        wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC;
    if bytes.len() >= 16 && bytes.len().is_multiple_of(4) {
        ctx.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytes,
                usage,
            })
    } else {
        let mut padded = bytes.to_vec();
        padded.resize(bytes.len().max(16).next_multiple_of(4), 0);
        ctx.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: &padded,
                usage,
            })
    }
}

/// A zeroed storage buffer of `bytes` bytes (at least 16).
pub(crate) fn storage_zeroed(ctx: &GpuContext, label: &str, bytes: u64) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(16).next_multiple_of(4),
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_DST
            | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    })
}

/// A uniform buffer holding `value`.
pub(crate) fn uniform<T: bytemuck::Pod>(ctx: &GpuContext, label: &str, value: &T) -> wgpu::Buffer {
    ctx.device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytemuck::bytes_of(value),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        })
}

/// A buffer the CPU can map to read `bytes` copied into it.
pub(crate) fn staging(ctx: &GpuContext, label: &str, bytes: u64) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(16).next_multiple_of(4),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// Size of a buffer as allocated (what [`storage_init`] and friends round to).
pub(crate) fn alloc_size(bytes: u64) -> u64 {
    bytes.max(16).next_multiple_of(4)
}

#[derive(Debug)]
struct CsrBlock {
    params: wgpu::Buffer,
    row_ptr: wgpu::Buffer,
    col: wgpu::Buffer,
    val: wgpu::Buffer,
    groups: (u32, u32),
    /// The entries it holds: `values.0..values.1` of the whole matrix's.
    values: (u64, u64),
}

/// A CSR matrix on the device (F with f32 values, or S with RGB values), in row blocks.
#[derive(Debug)]
pub struct GpuCsr {
    n_rows: usize,
    n_cols: usize,
    nnz: usize,
    rgb: bool,
    blocks: Vec<CsrBlock>,
    bytes: u64,
}

/// A matrix product bound to its input and output buffers: the bind groups and workgroup
/// counts of every block, made once and replayed by every request.
#[derive(Debug)]
pub(crate) struct BoundOp {
    /// Kernels in order, each with its dispatches (a product may take several: the pull of
    /// a hierarchical F, then C).
    steps: Vec<Step>,
}

/// One kernel's dispatches within a [`BoundOp`].
type Step = (wgpu::ComputePipeline, Vec<(wgpu::BindGroup, (u32, u32))>);

impl BoundOp {
    pub(crate) fn new(
        pipeline: wgpu::ComputePipeline,
        groups: Vec<(wgpu::BindGroup, (u32, u32))>,
    ) -> Self {
        Self {
            steps: vec![(pipeline, groups)],
        }
    }

    /// This op, then `next` (its dispatches see what this one wrote: WebGPU orders the
    /// dispatches of a pass).
    pub(crate) fn then(mut self, next: BoundOp) -> Self {
        self.steps.extend(next.steps);
        self
    }

    /// Records the op's dispatches into `pass`.
    pub(crate) fn encode(&self, pass: &mut wgpu::ComputePass<'_>) {
        for (pipeline, groups) in &self.steps {
            pass.set_pipeline(pipeline);
            for (bg, (x, y)) in groups {
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(*x, *y, 1);
            }
        }
    }

    /// The workgroup grid of each dispatch, in the order [`Self::encode`] records them.
    pub(crate) fn grids(&self) -> Vec<(u32, u32)> {
        self.steps
            .iter()
            .flat_map(|(_, groups)| groups.iter().map(|(_, g)| *g))
            .collect()
    }

    /// Records the op's dispatches into `pass` as indirect dispatches whose grids are the
    /// (x, y, 1) triples of `args` from triple `first` on (as [`Self::grids`] lays them out);
    /// answers the triple after the last. A triple zeroed on the device dispatches nothing.
    pub(crate) fn encode_indirect(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        args: &wgpu::Buffer,
        first: u32,
    ) -> u32 {
        let mut slot = first;
        for (pipeline, groups) in &self.steps {
            pass.set_pipeline(pipeline);
            for (bg, _) in groups {
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups_indirect(args, 12 * slot as u64);
                slot += 1;
            }
        }
        slot
    }
}

/// Row blocks of a CSR matrix: (first row, end row) pairs whose entries fit `tile` bytes
/// per array.
fn csr_blocks(
    row_ptr: &[u64],
    entry_bytes: u64,
    tile: u64,
    what: &str,
) -> Result<Vec<(usize, usize)>, GpuError> {
    let n = row_ptr.len() - 1;
    let max_entries = tile / entry_bytes;
    let max_rows = (tile / 4).saturating_sub(1) as usize;
    let mut blocks = Vec::new();
    let mut start = 0usize;
    while start < n {
        let mut end = start;
        while end < n && row_ptr[end + 1] - row_ptr[start] <= max_entries && end - start < max_rows
        {
            end += 1;
        }
        if end == start {
            return Err(GpuError::MatrixTooLarge {
                what: format!("{what} row {start}"),
                requested: (row_ptr[start + 1] - row_ptr[start]) * entry_bytes,
                max_binding: tile,
            });
        }
        blocks.push((start, end));
        start = end;
    }
    Ok(blocks)
}

impl GpuCsr {
    /// Uploads F (f32 values).
    pub fn upload_f32(
        ctx: &GpuContext,
        what: &str,
        m: &CsrView<'_, f32>,
    ) -> Result<GpuCsr, GpuError> {
        Self::upload(
            ctx,
            what,
            m.n_rows(),
            m.n_cols(),
            m.row_ptr(),
            m.col(),
            bytemuck::cast_slice(m.val()),
            false,
        )
    }

    /// Uploads S (RGB values).
    pub fn upload_rgb(
        ctx: &GpuContext,
        what: &str,
        m: &CsrView<'_, Rgb>,
    ) -> Result<GpuCsr, GpuError> {
        Self::upload(
            ctx,
            what,
            m.n_rows(),
            m.n_cols(),
            m.row_ptr(),
            m.col(),
            bytemuck::cast_slice(m.val()),
            true,
        )
    }

    /// Uploads from raw arrays (`val`: one f32 per entry, or three when `rgb`). The arrays
    /// must form a valid CSR matrix (a [`CsrView`] guarantees it).
    #[expect(
        clippy::too_many_arguments,
        reason = "a CSR matrix as its raw arrays, from the two public constructors"
    )]
    fn upload(
        ctx: &GpuContext,
        what: &str,
        n_rows: usize,
        n_cols: usize,
        row_ptr: &[u64],
        col: &[u32],
        val: &[f32],
        rgb: bool,
    ) -> Result<GpuCsr, GpuError> {
        let comps = if rgb { 3 } else { 1 };
        let tile = ctx.tile_bytes();
        let ranges = csr_blocks(row_ptr, 4 * comps as u64, tile, what)?;
        // Bytes of every buffer, reserved before anything is allocated.
        let mut bytes = 0u64;
        for &(a, b) in &ranges {
            let nnz = row_ptr[b] - row_ptr[a];
            bytes += alloc_size(4 * (b - a + 1) as u64)
                + alloc_size(4 * nnz)
                + alloc_size(4 * comps as u64 * nnz)
                + 16;
        }
        ctx.reserve(what, bytes)?;
        let made = ctx.scoped(|| {
            let mut blocks = Vec::with_capacity(ranges.len());
            for &(a, b) in &ranges {
                let (e0, e1) = (row_ptr[a] as usize, row_ptr[b] as usize);
                let rel: Vec<u32> = row_ptr[a..=b]
                    .iter()
                    .map(|&p| (p - row_ptr[a]) as u32)
                    .collect();
                let rows = (b - a) as u32;
                let groups = grid(rows.div_ceil(SPMV_ROWS_PER_WG));
                let params = CsrParams {
                    row0: a as u32,
                    rows,
                    groups_x: groups.0,
                    _pad: 0,
                    x_stride: n_cols as u32,
                    y_stride: n_rows as u32,
                    _pad1: 0,
                    _pad2: 0,
                };
                blocks.push(CsrBlock {
                    params: uniform(ctx, what, &params),
                    row_ptr: storage_init(ctx, what, bytemuck::cast_slice(&rel)),
                    col: storage_init(ctx, what, bytemuck::cast_slice(&col[e0..e1])),
                    val: storage_init(
                        ctx,
                        what,
                        bytemuck::cast_slice(&val[e0 * comps..e1 * comps]),
                    ),
                    groups,
                    values: (row_ptr[a], row_ptr[b]),
                });
            }
            Ok(blocks)
        });
        match made {
            Ok(blocks) => Ok(GpuCsr {
                n_rows,
                n_cols,
                nnz: col.len(),
                rgb,
                blocks,
                bytes,
            }),
            Err(e) => {
                ctx.release(bytes);
                Err(e)
            }
        }
    }

    pub fn n_rows(&self) -> usize {
        self.n_rows
    }
    pub fn n_cols(&self) -> usize {
        self.n_cols
    }
    pub fn nnz(&self) -> usize {
        self.nnz
    }
    /// Row blocks the matrix was split into.
    pub fn blocks(&self) -> usize {
        self.blocks.len()
    }
    /// GPU bytes held.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
    /// Bytes one product reads from the matrix (its row pointers, columns and values).
    pub fn stream_bytes(&self) -> u64 {
        let comps = if self.rgb { 3 } else { 1 };
        (self.n_rows as u64 + self.blocks.len() as u64) * 4 + self.nnz as u64 * 4 * (1 + comps)
    }

    /// y = A x bound to the buffers `x` (n_cols × 3 f32) and `y` (n_rows × 3 f32).
    pub(crate) fn bind(&self, ctx: &GpuContext, x: &wgpu::Buffer, y: &wgpu::Buffer) -> BoundOp {
        self.bind_lanes(ctx, x, y, false)
    }

    /// y = A x for every vector of a batch ([`super::kernels::BATCH`] vectors one after
    /// another in `x` and `y`), or for one (`batch` false), reading A once.
    pub(crate) fn bind_lanes(
        &self,
        ctx: &GpuContext,
        x: &wgpu::Buffer,
        y: &wgpu::Buffer,
        batch: bool,
    ) -> BoundOp {
        let k = &ctx.kernels;
        let pipeline = match (self.rgb, batch) {
            (true, false) => k.spmv_rgb.clone(),
            (false, false) => k.spmv_scalar.clone(),
            (true, true) => k.spmv_rgb_batch.clone(),
            (false, true) => k.spmv_scalar_batch.clone(),
        };
        let groups = self
            .blocks
            .iter()
            .map(|b| {
                let bg = k
                    .spmv
                    .bind(&ctx.device, &b.params, &[&b.row_ptr, &b.col, &b.val, x, y]);
                (bg, b.groups)
            })
            .collect();
        BoundOp::new(pipeline, groups)
    }

    /// y = A x, uploading x and reading y back (tests and one-off products; the solve keeps
    /// its vectors on the device).
    pub fn multiply(&self, ctx: &GpuContext, x: &[Rgb]) -> Result<Vec<Rgb>, GpuError> {
        if x.len() != self.n_cols {
            return Err(GpuError::Invalid(format!(
                "x has {} entries; the matrix has {} columns",
                x.len(),
                self.n_cols
            )));
        }
        ctx.scoped(|| {
            let xb = storage_init(ctx, "x", bytemuck::cast_slice(x));
            let yb = storage_zeroed(ctx, "y", 12 * self.n_rows as u64);
            let op = self.bind(ctx, &xb, &yb);
            let st = staging(ctx, "y-read", 12 * self.n_rows as u64);
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                op.encode(&mut pass);
            }
            enc.copy_buffer_to_buffer(&yb, 0, &st, 0, alloc_size(12 * self.n_rows as u64));
            ctx.queue.submit([enc.finish()]);
            let bytes = ctx.read_back(&st, alloc_size(12 * self.n_rows as u64))?;
            Ok(
                bytemuck::pod_collect_to_vec::<u8, f32>(&bytes[..12 * self.n_rows])
                    .chunks_exact(3)
                    .map(|c| [c[0], c[1], c[2]])
                    .collect(),
            )
        })
    }
}

impl GpuCsr {
    /// Records copies of runs of RGB values from `src` into the matrix's values: each run's
    /// `len` values from `src`'s value `local` on land at the matrix's value `s_value` on,
    /// split over the blocks that hold them. Values are three f32 each.
    pub(crate) fn copy_values_in(
        &self,
        enc: &mut wgpu::CommandEncoder,
        src: &wgpu::Buffer,
        runs: &[translux_engine::sterms::ValueRun],
    ) {
        let comps = if self.rgb { 12 } else { 4 };
        for r in runs {
            let (a, b) = (r.s_value, r.s_value + r.len as u64);
            for blk in &self.blocks {
                let (lo, hi) = (a.max(blk.values.0), b.min(blk.values.1));
                if lo >= hi {
                    continue;
                }
                enc.copy_buffer_to_buffer(
                    src,
                    (r.local as u64 + (lo - a)) * comps,
                    &blk.val,
                    (lo - blk.values.0) * comps,
                    (hi - lo) * comps,
                );
            }
        }
    }

    /// Every value, read back (three f32 each for RGB): what tests compare.
    pub fn read_values(&self, ctx: &GpuContext) -> Result<Vec<f32>, GpuError> {
        let comps = if self.rgb { 3 } else { 1 };
        let bytes = 4 * comps * self.nnz as u64;
        ctx.scoped(|| {
            let st = staging(ctx, "values-read", bytes);
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            for blk in &self.blocks {
                let len = 4 * comps * (blk.values.1 - blk.values.0);
                if len > 0 {
                    enc.copy_buffer_to_buffer(&blk.val, 0, &st, 4 * comps * blk.values.0, len);
                }
            }
            ctx.queue.submit([enc.finish()]);
            let out: Vec<f32> = ctx.read_back_as(&st, alloc_size(bytes))?;
            Ok(out[..(comps * self.nnz as u64) as usize].to_vec())
        })
    }
}

/// The most vectors one pass of `dense_matmul_rgb` serves.
pub const MAX_BATCH: usize = 64;

#[derive(Debug)]
struct DenseBlock {
    params: wgpu::Buffer,
    rows: u32,
    row0: u32,
    groups: (u32, u32),
    bind: wgpu::BindGroup,
}

/// A dense RGB matrix T on the device (f16 or f32 storage), in row blocks, with its own
/// input and output buffers for batches of up to [`MAX_BATCH`] vectors.
#[derive(Debug)]
pub struct GpuDense {
    n_rows: usize,
    n_cols: usize,
    f16: bool,
    blocks: Vec<DenseBlock>,
    x: wgpu::Buffer,
    y: wgpu::Buffer,
    y_read: wgpu::Buffer,
    bytes: u64,
    /// Bytes of T itself (what one pass reads).
    matrix_bytes: u64,
    /// One batch at a time: the batch buffers and block parameters are shared.
    busy: std::sync::Mutex<()>,
    /// Per row and channel factor applied to every product (on the CPU after the read-back:
    /// n·k·3 multiplications against the n²·3 of the product).
    row_scale: Option<Vec<Rgb>>,
}

impl GpuDense {
    /// Uploads T (`n_rows` × `n_cols` RGB entries, [`DenseData`] layout). `row_scale`
    /// (`[n_rows]` RGB) multiplies row j's channel c of every product: the bundle stores its
    /// transfer matrix scaled per row and channel so that f16 keeps its precision.
    pub fn upload(
        ctx: &GpuContext,
        what: &str,
        n_rows: usize,
        n_cols: usize,
        t: DenseData<'_>,
        row_scale: Option<&[Rgb]>,
    ) -> Result<GpuDense, GpuError> {
        if row_scale.is_some_and(|s| s.len() != n_rows) {
            return Err(GpuError::Invalid(format!(
                "{what}: the row scale has {} entries for {n_rows} rows",
                row_scale.map_or(0, |s| s.len())
            )));
        }
        if t.len() != n_rows * n_cols * 3 {
            return Err(GpuError::Invalid(format!(
                "{what}: {} elements for a {n_rows}×{n_cols} RGB matrix (expected {})",
                t.len(),
                n_rows * n_cols * 3
            )));
        }
        let eb = t.elem_bytes() as u64;
        let row_bytes = n_cols as u64 * 3 * eb;
        // Whole rows per block, an even count so that every block starts on an even element.
        let tile = ctx.tile_bytes().saturating_sub(8);
        let mut rows_per = (tile / row_bytes.max(1)) as usize;
        rows_per -= rows_per % 2;
        if rows_per == 0 {
            return Err(GpuError::MatrixTooLarge {
                what: what.into(),
                requested: 2 * row_bytes,
                max_binding: ctx.tile_bytes(),
            });
        }
        // The element index inside a block must fit u32.
        rows_per = rows_per.min((u32::MAX as usize / 2) / (3 * n_cols.max(1)));
        rows_per -= rows_per % 2;
        let ranges: Vec<(usize, usize)> = (0..n_rows)
            .step_by(rows_per.max(2))
            .map(|a| (a, (a + rows_per).min(n_rows)))
            .collect();
        let vec_bytes = |n: usize| alloc_size(12 * (n * MAX_BATCH) as u64);
        let matrix_bytes = n_rows as u64 * row_bytes;
        let mut bytes = vec_bytes(n_cols) + 2 * vec_bytes(n_rows);
        for &(a, b) in &ranges {
            bytes += alloc_size((b - a) as u64 * row_bytes + 8) + 32;
        }
        ctx.reserve(what, bytes)?;
        let made = ctx.scoped(|| {
            let x = storage_zeroed(ctx, "T-x", vec_bytes(n_cols));
            let y = storage_zeroed(ctx, "T-y", vec_bytes(n_rows));
            let y_read = staging(ctx, "T-y-read", vec_bytes(n_rows));
            let mut blocks = Vec::new();
            for &(a, b) in &ranges {
                let (e0, e1) = (a * n_cols * 3, b * n_cols * 3);
                let words: Vec<u32> = match t {
                    DenseData::F16(h) => h[e0..e1]
                        .chunks(2)
                        .map(|p| p[0] as u32 | ((p.get(1).copied().unwrap_or(0) as u32) << 16))
                        .chain(std::iter::once(0))
                        .collect(),
                    DenseData::F32(f) => f[e0..e1]
                        .iter()
                        .map(|v| v.to_bits())
                        .chain(std::iter::once(0))
                        .collect(),
                };
                let buf = storage_init(ctx, what, bytemuck::cast_slice(&words));
                let rows = (b - a) as u32;
                let groups = grid(rows.div_ceil(DENSE_ROWS as u32));
                let params = uniform(
                    ctx,
                    what,
                    &DenseParams {
                        row0: a as u32,
                        rows,
                        n_cols: n_cols as u32,
                        k: 1,
                        v0: 0,
                        groups_x: groups.0,
                        _pad0: 0,
                        _pad1: 0,
                    },
                );
                let bind = ctx
                    .kernels
                    .dense
                    .bind(&ctx.device, &params, &[&buf, &x, &y]);
                blocks.push(DenseBlock {
                    params,
                    rows,
                    row0: a as u32,
                    groups,
                    bind,
                });
            }
            Ok((blocks, x, y, y_read))
        });
        match made {
            Ok((blocks, x, y, y_read)) => Ok(GpuDense {
                n_rows,
                n_cols,
                f16: matches!(t, DenseData::F16(_)),
                blocks,
                x,
                y,
                y_read,
                bytes,
                matrix_bytes,
                busy: std::sync::Mutex::new(()),
                row_scale: row_scale.map(<[Rgb]>::to_vec),
            }),
            Err(e) => {
                ctx.release(bytes);
                Err(e)
            }
        }
    }

    pub fn n_rows(&self) -> usize {
        self.n_rows
    }
    pub fn n_cols(&self) -> usize {
        self.n_cols
    }
    pub fn blocks(&self) -> usize {
        self.blocks.len()
    }
    /// GPU bytes held (T and the batch buffers).
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
    /// Bytes of T: what one pass reads.
    pub fn matrix_bytes(&self) -> u64 {
        self.matrix_bytes
    }

    /// Y = T X with X and Y interleaved as `[row][k][RGB]` (`x`: n_cols·k·3 values, `y`:
    /// n_rows·k·3): the kernel's own layout and the relight's. Any k: one pass over T per
    /// 64 vectors.
    pub fn multiply_interleaved(
        &self,
        ctx: &GpuContext,
        x: &[f32],
        k: usize,
        y: &mut [f32],
    ) -> Result<(), GpuError> {
        if x.len() != self.n_cols * k * 3 || y.len() != self.n_rows * k * 3 {
            return Err(GpuError::Invalid(format!(
                "X has {} and Y {} values; T is {}×{} and k = {k}",
                x.len(),
                y.len(),
                self.n_rows,
                self.n_cols
            )));
        }
        for v0 in (0..k).step_by(MAX_BATCH) {
            let kc = (k - v0).min(MAX_BATCH);
            let xs: Vec<Vec<Rgb>> = (v0..v0 + kc)
                .map(|v| {
                    (0..self.n_cols)
                        .map(|i| {
                            let o = (i * k + v) * 3;
                            [x[o], x[o + 1], x[o + 2]]
                        })
                        .collect()
                })
                .collect();
            let refs: Vec<&[Rgb]> = xs.iter().map(|v| v.as_slice()).collect();
            let ys = self.multiply(ctx, &refs)?;
            for (dv, yv) in ys.iter().enumerate() {
                for (j, e) in yv.iter().enumerate() {
                    let o = (j * k + v0 + dv) * 3;
                    y[o..o + 3].copy_from_slice(e);
                }
            }
        }
        Ok(())
    }

    /// Y = T X for `xs.len()` ≤ 64 vectors in one pass over T (`xs[v]` has n_cols entries;
    /// the answer `[v]` has n_rows).
    pub fn multiply(&self, ctx: &GpuContext, xs: &[&[Rgb]]) -> Result<Vec<Vec<Rgb>>, GpuError> {
        let k = xs.len();
        if k == 0 {
            return Ok(Vec::new());
        }
        if k > MAX_BATCH {
            return Err(GpuError::Invalid(format!(
                "{k} vectors in one batch; one pass over T serves at most {MAX_BATCH}"
            )));
        }
        if let Some(v) = xs.iter().position(|x| x.len() != self.n_cols) {
            return Err(GpuError::Invalid(format!(
                "vector {v} has {} entries; T has {} columns",
                xs[v].len(),
                self.n_cols
            )));
        }
        // X as [col][vector][RGB].
        let mut x = vec![0.0f32; self.n_cols * k * 3];
        for (v, xv) in xs.iter().enumerate() {
            for (i, e) in xv.iter().enumerate() {
                x[(i * k + v) * 3..(i * k + v) * 3 + 3].copy_from_slice(e);
            }
        }
        let kv = dense_vector_lanes(k) as u32;
        let _busy = self.busy.lock().unwrap_or_else(|p| p.into_inner());
        ctx.scoped(|| {
            ctx.queue.write_buffer(&self.x, 0, bytemuck::cast_slice(&x));
            for b in &self.blocks {
                let p = DenseParams {
                    row0: b.row0,
                    rows: b.rows,
                    n_cols: self.n_cols as u32,
                    k: k as u32,
                    v0: 0,
                    groups_x: b.groups.0,
                    _pad0: 0,
                    _pad1: 0,
                };
                ctx.queue.write_buffer(&b.params, 0, bytemuck::bytes_of(&p));
            }
            let pipeline = ctx.kernels.dense_pipeline(&ctx.device, self.f16, kv);
            let op = BoundOp::new(
                pipeline,
                self.blocks
                    .iter()
                    .map(|b| (b.bind.clone(), b.groups))
                    .collect(),
            );
            let out_bytes = 12 * (self.n_rows * k) as u64;
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                op.encode(&mut pass);
            }
            enc.copy_buffer_to_buffer(&self.y, 0, &self.y_read, 0, out_bytes);
            ctx.queue.submit([enc.finish()]);
            let bytes = ctx.read_back(&self.y_read, out_bytes)?;
            let y: Vec<f32> = bytemuck::pod_collect_to_vec(&bytes);
            Ok((0..k)
                .map(|v| {
                    (0..self.n_rows)
                        .map(|j| {
                            let o = (j * k + v) * 3;
                            let s = self.row_scale.as_ref().map_or([1.0; 3], |s| s[j]);
                            [y[o] * s[0], y[o + 1] * s[1], y[o + 2] * s[2]]
                        })
                        .collect()
                })
                .collect())
        })
    }
}
