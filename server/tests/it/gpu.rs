//! The wgpu backend against its references: every kernel against its CPU twin (and the
//! sparse products against the precompute's own CPU product) on random, non-zero inputs,
//! matrices forced into many row blocks by a tiny binding cap, and whole solves against the
//! CPU solver on a precomputed Cornell box with a translucent block.
//!
//! These tests need a GPU adapter; without a GPU, Mesa's lavapipe (`apt-get install
//! mesa-vulkan-drivers libvulkan1`, `.ci/run` does it) is one. With no adapter they fail,
//! saying so, unless `TRANSLUX_SKIP_GPU_TESTS=1`.

use std::sync::OnceLock;

use translux_engine::radiosity::{Method, Rgb, SolveParams, SparseScatter, solve, spmv_rgb};
use translux_proto::csr::CsrView;
use translux_server::gpu::cpu_twin::{self, DenseData};
use translux_server::gpu::system::{
    jacobi_update_once, mr_alpha_once, mr_step_once, reduce_sum_once,
};
use translux_server::gpu::{GpuContext, GpuCsr, GpuDense, GpuOptions, GpuSystem};

/// The shared context (adapter limits), or `None` when skipping is allowed and no adapter
/// exists.
fn ctx() -> Option<&'static GpuContext> {
    crate::support::gpu()
}

/// A context whose matrix buffers hold at most 4 KiB: everything is split into blocks.
fn tiny_ctx() -> Option<&'static GpuContext> {
    static CTX: OnceLock<Option<GpuContext>> = OnceLock::new();
    CTX.get_or_init(|| crate::support::gpu_context(Some(4096)))
        .as_ref()
}

/// A seeded xorshift generator: reproducible random inputs without a crate.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    /// Uniform in [lo, hi).
    fn f(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * ((self.next() >> 40) as f32 / (1u64 << 24) as f32)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
    fn rgb(&mut self) -> Rgb {
        [self.f(0.1, 1.0), self.f(0.1, 1.0), self.f(0.1, 1.0)]
    }
}

/// A random CSR pattern: row lengths from 0 to `max_len` (some past 32 lanes), sorted
/// distinct columns.
fn pattern(rng: &mut Rng, rows: usize, cols: usize, max_len: usize) -> (Vec<u64>, Vec<u32>) {
    let mut row_ptr = vec![0u64];
    let mut col = Vec::new();
    for r in 0..rows {
        let len = if r % 17 == 5 {
            0
        } else {
            rng.below(max_len + 1)
        };
        let mut c: Vec<u32> = (0..len).map(|_| rng.below(cols) as u32).collect();
        c.sort_unstable();
        c.dedup();
        col.extend(c);
        row_ptr.push(col.len() as u64);
    }
    (row_ptr, col)
}

/// |a − b| ≤ tol · max(|b|, floor) componentwise, with the worst index in the message.
fn assert_close(what: &str, got: &[Rgb], want: &[Rgb], tol: f32) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    let scale = want
        .iter()
        .flat_map(|v| v.iter())
        .fold(0.0f32, |m, v| m.max(v.abs()));
    let floor = 1e-6 * scale.max(1e-30);
    let mut worst = (0.0f32, 0usize);
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        for c in 0..3 {
            let rel = (g[c] - w[c]).abs() / w[c].abs().max(floor);
            if rel > worst.0 {
                worst = (rel, i);
            }
        }
    }
    assert!(
        worst.0 <= tol,
        "{what}: relative error {:.3e} at {} (got {:?}, want {:?})",
        worst.0,
        worst.1,
        got[worst.1],
        want[worst.1]
    );
}

fn spmv_case(ctx: &GpuContext, rows: usize, max_len: usize, seed: u64) -> (usize, usize) {
    let mut rng = Rng(seed);
    let cols = rows + 7;
    let (row_ptr, col) = pattern(&mut rng, rows, cols, max_len);
    let x: Vec<Rgb> = (0..cols).map(|_| rng.rgb()).collect();
    // F: scalar values.
    let fv: Vec<f32> = col.iter().map(|_| rng.f(0.01, 1.0)).collect();
    let f = CsrView::new_checked(rows, cols, &row_ptr, &col, &fv).unwrap();
    let gf = GpuCsr::upload_f32(ctx, "F", &f).unwrap();
    let got = gf.multiply(ctx, &x).unwrap();
    let mut twin = vec![[0.0; 3]; rows];
    cpu_twin::csr_spmv_rgb(&row_ptr, &col, &fv, &x, &mut twin);
    assert_close("csr_spmv_rgb (f32 values) vs twin", &got, &twin, 1e-4);
    // The precompute's own product (an independent CPU reference, other summation order).
    // It is square-only in spirit but takes any CSR view.
    let mut cpu = vec![[0.0; 3]; rows];
    spmv_rgb(&f, &x, &mut cpu);
    assert_close(
        "csr_spmv_rgb (f32 values) vs radiosity::spmv_rgb",
        &got,
        &cpu,
        1e-4,
    );
    // S: RGB values.
    let sv: Vec<Rgb> = col.iter().map(|_| rng.rgb()).collect();
    let s = CsrView::new_checked(rows, cols, &row_ptr, &col, &sv).unwrap();
    let gs = GpuCsr::upload_rgb(ctx, "S", &s).unwrap();
    let got = gs.multiply(ctx, &x).unwrap();
    let mut twin = vec![[0.0; 3]; rows];
    cpu_twin::csr_spmv_rgb(&row_ptr, &col, &sv, &x, &mut twin);
    assert_close("csr_spmv_rgb (RGB values) vs twin", &got, &twin, 1e-4);
    (gf.blocks(), gs.blocks())
}

#[test]
fn csr_spmv_rgb_matches_its_twin() {
    let Some(ctx) = ctx() else { return };
    for (rows, max_len, seed) in [(1, 40, 1), (257, 3, 2), (1000, 300, 3), (3001, 70, 4)] {
        let (bf, bs) = spmv_case(ctx, rows, max_len, seed);
        assert_eq!(
            (bf, bs),
            (1, 1),
            "the adapter's binding holds these matrices whole"
        );
    }
}

#[test]
fn csr_spmv_rgb_matches_its_twin_when_tiled() {
    let Some(ctx) = tiny_ctx() else { return };
    let (bf, bs) = spmv_case(ctx, 2000, 120, 11);
    // 4 KiB tiles: F's ~120k column indices need dozens of blocks, S's more.
    assert!(bf > 20 && bs > bf, "blocks: F {bf}, S {bs}");
}

fn dense_case(ctx: &GpuContext, rows: usize, cols: usize, k: usize, f16: bool, seed: u64) -> usize {
    let mut rng = Rng(seed);
    let vals: Vec<f32> = (0..rows * cols * 3).map(|_| rng.f(0.0, 1.0)).collect();
    let halves: Vec<u16> = vals
        .iter()
        .map(|&v| half::f16::from_f32(v).to_bits())
        .collect();
    let t = if f16 {
        DenseData::F16(&halves)
    } else {
        DenseData::F32(&vals)
    };
    let g = GpuDense::upload(ctx, "T", rows, cols, t, None).unwrap();
    let xs: Vec<Vec<Rgb>> = (0..k)
        .map(|_| (0..cols).map(|_| rng.rgb()).collect())
        .collect();
    let refs: Vec<&[Rgb]> = xs.iter().map(|v| v.as_slice()).collect();
    let got = g.multiply(ctx, &refs).unwrap();
    // The twin takes X as [col][vector].
    let mut x = vec![[0.0f32; 3]; cols * k];
    for (v, xv) in xs.iter().enumerate() {
        for (i, e) in xv.iter().enumerate() {
            x[i * k + v] = *e;
        }
    }
    let mut y = vec![[0.0f32; 3]; rows * k];
    cpu_twin::dense_matmul_rgb(t, rows, cols, &x, k, &mut y);
    for v in 0..k {
        let want: Vec<Rgb> = (0..rows).map(|j| y[j * k + v]).collect();
        assert_close(
            &format!("dense_matmul_rgb {rows}×{cols} f16={f16} k={k} vector {v}"),
            &got[v],
            &want,
            1e-4,
        );
    }
    g.blocks()
}

#[test]
fn dense_matmul_rgb_matches_its_twin() {
    let Some(ctx) = ctx() else { return };
    // Odd column counts put triples across u32 boundaries; k crosses the lane widths.
    for (rows, cols, k, f16, seed) in [
        (5, 3, 1, true, 1),
        (129, 127, 1, true, 2),
        (130, 301, 3, true, 3),
        (64, 255, 8, false, 4),
        (37, 513, 64, true, 5),
        (200, 200, 17, false, 6),
    ] {
        assert_eq!(dense_case(ctx, rows, cols, k, f16, seed), 1);
    }
}

#[test]
fn dense_matmul_rgb_matches_its_twin_when_tiled() {
    let Some(ctx) = tiny_ctx() else { return };
    // 4 KiB tiles: 111 f16 RGB columns are 666 bytes a row, so 6 rows a block.
    let blocks = dense_case(ctx, 101, 111, 5, true, 7);
    assert!(blocks >= 17, "blocks: {blocks}");
    let blocks = dense_case(ctx, 60, 50, 64, false, 8);
    assert!(blocks >= 10, "blocks: {blocks}");
}

#[test]
fn jacobi_update_and_reduce_sum_match_their_twins() {
    let Some(ctx) = ctx() else { return };
    let mut rng = Rng(21);
    for n in [1usize, 255, 256, 1000, 70_001] {
        let b: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
        let sfx: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
        let x: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
        let (gx, gp) = jacobi_update_once(ctx, &b, &sfx, &x).unwrap();
        let mut tx = x.clone();
        let tp = cpu_twin::jacobi_update(&b, &sfx, &mut tx);
        assert_close(&format!("jacobi_update x, n = {n}"), &gx, &tx, 1e-6);
        let gp3: Vec<Rgb> = gp.iter().map(|&v| [v; 3]).collect();
        let tp3: Vec<Rgb> = tp.iter().map(|&v| [v; 3]).collect();
        assert_close(
            &format!("jacobi_update partials, n = {n}"),
            &gp3,
            &tp3,
            1e-4,
        );
        // reduce_sum on those partials, three times, never stopping: three equal slots.
        let st = reduce_sum_once(ctx, &[gp.clone(), gp.clone(), gp.clone()], 1, 0.0, 0).unwrap();
        let want = cpu_twin::reduce_sum(&gp);
        assert_eq!(st.counter, [3, 0], "n = {n}");
        for (k, v) in st.history.iter().enumerate() {
            assert!(
                (v - want).abs() <= 1e-4 * want.abs(),
                "reduce_sum slot {k}, n = {n}: {v} vs twin {want}"
            );
        }
    }
}

#[test]
fn mr_step_and_mr_alpha_match_their_twins() {
    use cpu_twin::MrStage;
    let Some(ctx) = ctx() else { return };
    let mut rng = Rng(23);
    for n in [1usize, 255, 256, 1000, 70_001] {
        let b: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
        let kr: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
        let x: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
        let r: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
        let alpha = [rng.f(0.1, 1.9), rng.f(0.1, 1.9), rng.f(0.1, 1.9), 0.0];
        for stage in [MrStage::Residual, MrStage::Dots, MrStage::Update] {
            let what = format!("mr_step {stage:?}, n = {n}");
            let run = mr_step_once(ctx, stage, &b, &kr, alpha, &x, &r).unwrap();
            let (gx, gr, gp) = (run.x, run.r, run.partial);
            let (mut tx, mut tr) = (x.clone(), r.clone());
            let tp = cpu_twin::mr_step(stage, &b, &kr, alpha, &mut tx, &mut tr);
            assert_close(&format!("{what}: x"), &gx, &tx, 1e-6);
            assert_close(&format!("{what}: r"), &gr, &tr, 1e-5);
            assert_eq!(gp.len(), tp.len(), "{what}: partials");
            let three = |v: &[f32]| -> Vec<Rgb> { v.iter().map(|&v| [v; 3]).collect() };
            assert_close(&format!("{what}: partials"), &three(&gp), &three(&tp), 1e-4);
            if stage == MrStage::Dots {
                // α from the device's own partials, as one system and as a batch of three
                // (the same partials three times: the same α three times).
                let ga = mr_alpha_once(ctx, &gp, 1).unwrap();
                let ta = cpu_twin::mr_alpha(&gp, 1);
                let gp3 = [gp.clone(), gp.clone(), gp.clone()].concat();
                let ga3 = mr_alpha_once(ctx, &gp3, 3).unwrap();
                assert_eq!(ga3.len(), 12, "{what}");
                for (k, (g, t)) in ga.iter().chain(&ga3).zip(ta.iter().cycle()).enumerate() {
                    assert!(
                        (g - t).abs() <= 1e-5 * t.abs().max(1.0),
                        "mr_alpha entry {k}, n = {n}: {g} vs twin {t}"
                    );
                }
            }
        }
    }
    // α itself: channel 0 minimises |r + α v| inside the clamp, channel 1 is clamped to
    // MAX_STEP, channel 2 has v = 0 (a dark channel): the plain step, α = 1.
    let (rv, vv) = ([-0.6f32, -5.0, 0.0], [1.0f32, 1.0, 0.0]);
    let partial: Vec<f32> = rv.iter().chain(&vv).copied().collect();
    let want = [0.6f32, 1.9, 1.0, 0.0];
    assert_eq!(cpu_twin::mr_alpha(&partial, 1), want);
    let got = mr_alpha_once(ctx, &partial, 1).unwrap();
    for (g, w) in got.iter().zip(want) {
        assert!((g - w).abs() <= 1e-6, "mr_alpha {got:?} vs {want:?}");
    }
    // The shader's clamp is the CPU solver's.
    let max = translux_engine::solver::MAX_STEP as f32;
    assert!(
        translux_server::gpu::kernels::MR_ALPHA.contains(&format!("MAX_STEP: f32 = {max};")),
        "mr_alpha.wgsl's MAX_STEP is {max}"
    );
}

#[test]
fn reduce_sum_stops_the_solve_where_its_twin_does() {
    let Some(ctx) = ctx() else { return };
    let mut rng = Rng(5);
    // ‖b‖² then residuals falling by 10 per slot: a tolerance of 0.02 (0.0004 squared) is
    // met at slot 4 (1e-4 of ‖b‖²), after which nothing is appended and the grids are zero.
    // In a batch of three the third system falls by 10 only every other slot: the batch
    // stops when it too has met the tolerance, at slot 8.
    let base: Vec<f32> = (0..700).map(|_| rng.f(0.5, 1.5)).collect();
    let fall = |k: i32| -> Vec<f32> { base.iter().map(|v| v * 10f32.powi(-k)).collect() };
    let single: Vec<Vec<f32>> = (0..10).map(fall).collect();
    let batch: Vec<Vec<f32>> = (0..10)
        .map(|k| [fall(k), fall(k), fall(k / 2)].concat())
        .collect();
    for (partials, kv, tol, stop) in [
        (&single, 1usize, 0.02f32, Some(4u32)),
        (&single, 1, 1e-6, None),
        (&batch, 3, 0.02, Some(8)),
    ] {
        let got = reduce_sum_once(ctx, partials, kv as u32, tol * tol, 5).unwrap();
        let mut twin = cpu_twin::ReduceState {
            history: vec![0.0; partials.len() * kv],
            counter: [0, 0],
            args: vec![1; 15],
        };
        for p in partials {
            cpu_twin::reduce_stop(p, kv, tol * tol, &mut twin);
        }
        let what = format!("kv {kv}, tolerance {tol}");
        assert_eq!(got.counter, twin.counter, "{what}");
        assert_eq!(got.args, twin.args, "{what}");
        assert_eq!(
            stop,
            (got.counter[1] != 0).then_some(got.counter[1]),
            "{what}"
        );
        for (k, (g, t)) in got.history.iter().zip(&twin.history).enumerate() {
            assert!(
                (g - t).abs() <= 1e-4 * t.abs(),
                "{what}, entry {k}: {g} vs twin {t}"
            );
        }
    }
}

/// A random transport system with a known contraction: F rows sum to ≤ 0.9, S columns
/// (Σ_j S_ji) to ≤ 0.9 per channel.
struct System {
    n: usize,
    f_ptr: Vec<u64>,
    f_col: Vec<u32>,
    f_val: Vec<f32>,
    s_ptr: Vec<u64>,
    s_col: Vec<u32>,
    s_val: Vec<Rgb>,
}

fn random_system(n: usize, seed: u64) -> System {
    let mut rng = Rng(seed);
    let (f_ptr, f_col) = pattern(&mut rng, n, n, 60);
    let mut f_val: Vec<f32> = f_col.iter().map(|_| rng.f(0.1, 1.0)).collect();
    for r in 0..n {
        let (a, b) = (f_ptr[r] as usize, f_ptr[r + 1] as usize);
        let sum: f32 = f_val[a..b].iter().sum();
        let target = rng.f(0.3, 0.9);
        for v in &mut f_val[a..b] {
            *v *= target / sum.max(1e-9);
        }
    }
    // S: a diagonal plus a few neighbours, then columns scaled to ≤ 0.9.
    let mut s_ptr = vec![0u64];
    let mut s_col = Vec::new();
    let mut s_val = Vec::new();
    for j in 0..n {
        let mut c: Vec<u32> = vec![j as u32];
        for _ in 0..rng.below(6) {
            c.push(rng.below(n) as u32);
        }
        c.sort_unstable();
        c.dedup();
        for &i in &c {
            s_col.push(i);
            s_val.push(rng.rgb());
        }
        s_ptr.push(s_col.len() as u64);
    }
    let mut colsum = vec![[0.0f32; 3]; n];
    for (k, &i) in s_col.iter().enumerate() {
        for c in 0..3 {
            colsum[i as usize][c] += s_val[k][c];
        }
    }
    for (k, &i) in s_col.iter().enumerate() {
        for c in 0..3 {
            s_val[k][c] *= 0.9 / colsum[i as usize][c].max(0.9);
        }
    }
    System {
        n,
        f_ptr,
        f_col,
        f_val,
        s_ptr,
        s_col,
        s_val,
    }
}

fn solve_both(ctx: &GpuContext, sys: &System, seed: u64) -> (usize, usize) {
    let mut rng = Rng(seed);
    let n = sys.n;
    let f = CsrView::new_checked(n, n, &sys.f_ptr, &sys.f_col, &sys.f_val).unwrap();
    let s = CsrView::new_checked(n, n, &sys.s_ptr, &sys.s_col, &sys.s_val).unwrap();
    let e: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
    let be: Vec<Rgb> = (0..n)
        .map(|i| if i % 50 == 0 { rng.rgb() } else { [0.0; 3] })
        .collect();
    let params = SolveParams {
        method: Method::Jacobi,
        tolerance: 1e-6,
        max_iterations: 400,
    };
    let gpu = GpuSystem::new(
        ctx,
        "random",
        &translux_engine::transport::Transport::dense(f),
        &s,
        params.max_iterations,
    )
    .unwrap();
    let (gb, gs) = gpu.solve(ctx, &be, &e, &params, None).unwrap();
    assert!(gs.stats.converged, "{gs:?}");
    // A cold solve records 8 iterations and continues while the residual is above the
    // tolerance; the next solve records enough from the start: one submission, one
    // read-back of the counter, the history and B (12 bytes a patch), stopping at the same
    // iteration.
    assert!(gs.submissions > 1, "{gs:?}");
    let (again, gs2) = gpu.solve(ctx, &be, &e, &params, None).unwrap();
    assert_eq!(gs2.submissions, 1, "{gs2:?}");
    assert_eq!(gs2.stats.iterations, gs.stats.iterations, "{gs2:?}");
    assert!(
        gs2.bytes_down <= 12 * n as u64 + 16 + 4 * (gs.stats.iterations as u64 * 2 + 4),
        "{gs2:?}"
    );
    assert_eq!(gs2.bytes_up, 24 * n as u64 + 32, "{gs2:?}");
    assert_eq!(again, gb);
    for method in [Method::Jacobi, Method::BiCgStab] {
        let p = SolveParams { method, ..params };
        let (cb, cs) = solve(
            &translux_engine::transport::Transport::dense(f),
            &SparseScatter(s),
            &be,
            &e,
            &p,
            None,
        )
        .unwrap();
        assert!(cs.converged, "{cs:?}");
        assert_close(&format!("GPU Jacobi vs CPU {method:?}"), &gb, &cb, 1e-4);
    }
    let (bf, bs) = (gpu.matrices().0.blocks(), gpu.matrices().1.blocks());
    gpu.release(ctx);
    (bf, bs)
}

/// Passes over F and S plain Jacobi takes on the device's rule, as the device took them
/// before it took the minimal-residual step: x₀ = b = Bₑ + S E, then pass k makes
/// r = b + S F x − x of the last x and x ← x + r, until ‖r‖ ≤ tol · ‖b‖ (all channels
/// together).
fn plain_jacobi_passes(
    f: &translux_engine::transport::Transport<'_>,
    s: &dyn translux_engine::radiosity::Scatter,
    be: &[Rgb],
    e: &[Rgb],
    tol: f32,
    max: u32,
) -> u32 {
    let n = be.len();
    let norm2 = |v: &[Rgb]| -> f64 { v.iter().flatten().map(|&a| a as f64 * a as f64).sum() };
    let mut se = vec![[0.0f32; 3]; n];
    s.apply(e, &mut se);
    let b: Vec<Rgb> = (0..n)
        .map(|i| std::array::from_fn(|c| be[i][c] + se[i][c]))
        .collect();
    let b2 = norm2(&b);
    let mut x = b.clone();
    let (mut fx, mut kx) = (vec![[0.0f32; 3]; n], vec![[0.0f32; 3]; n]);
    for k in 1..=max {
        f.apply_rgb(&x, &mut fx);
        s.apply(&fx, &mut kx);
        let r: Vec<Rgb> = (0..n)
            .map(|i| std::array::from_fn(|c| b[i][c] + kx[i][c] - x[i][c]))
            .collect();
        for (x, r) in x.iter_mut().zip(&r) {
            for c in 0..3 {
                x[c] += r[c];
            }
        }
        if norm2(&r) <= (tol as f64).powi(2) * b2 {
            return k;
        }
    }
    max
}

/// The device takes the CPU's minimal-residual Jacobi step (α per system and channel,
/// reduced and applied on the device): on the Cornell box it needs no more iterations than
/// the CPU's Jacobi, cold and warm, and at most 4/5 of the passes over F and S plain
/// Jacobi takes (what the device took before; measured on lavapipe at 300 patches, cold:
/// 11 passes at 0.5% and 20 at 1e-4, against 7 and 12 now; the CPU 7 and 13), with the
/// same answer.
#[test]
fn device_solve_takes_the_minimal_residual_step() {
    use translux_engine::transport::{Transport, subsurface_operator};
    let Some(ctx) = ctx() else { return };
    let b = translux_proto::bundle::Bundle::open(crate::support::bundle_dir()).unwrap();
    let f = Transport::of(&b);
    let s = b.subsurface();
    let op = subsurface_operator(&b, s);
    let n = f.n();
    let mut rng = Rng(47);
    let e: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
    let e2: Vec<Rgb> = e.iter().map(|v| v.map(|a| a * rng.f(0.8, 1.2))).collect();
    let be = vec![[0.0f32; 3]; n];
    let gpu = GpuSystem::new(ctx, "cornell", &f, &s, 400).unwrap();
    for tolerance in [5e-3f32, 1e-4] {
        let p = SolveParams {
            method: Method::Jacobi,
            tolerance,
            max_iterations: 400,
        };
        let what = format!("tolerance {tolerance}");
        let plain = plain_jacobi_passes(&f, op.as_ref(), &be, &e, tolerance, 400);
        let (cb, cs) = solve(&f, op.as_ref(), &be, &e, &p, None).unwrap();
        let (gb, gs) = gpu.solve(ctx, &be, &e, &p, None).unwrap();
        eprintln!(
            "{what}: plain Jacobi {plain} passes; CPU {} it. ({} products); device {} it. \
             ({} passes, {} submissions)",
            cs.iterations, cs.products, gs.stats.iterations, gs.stats.products, gs.submissions
        );
        assert!(cs.converged && gs.stats.converged, "{what}: {cs:?} {gs:?}");
        assert!(
            gs.stats.iterations <= cs.iterations,
            "{what}: device {gs:?} vs CPU {cs:?}"
        );
        assert!(
            gs.stats.products * 5 <= plain * 4,
            "{what}: device {gs:?}, plain Jacobi {plain} passes"
        );
        assert_close(&format!("{what}: device vs CPU"), &gb, &cb, 5.0 * tolerance);
        // Warm from the answer for another E (a dragged light): one pass for the start's
        // residual, then the same steps as the CPU's from the same start.
        let (cw, cws) = solve(&f, op.as_ref(), &be, &e2, &p, Some(&cb)).unwrap();
        let (gw, gws) = gpu.solve(ctx, &be, &e2, &p, Some(&cb)).unwrap();
        eprintln!(
            "{what}, warm: CPU {} it. ({} products); device {} it. ({} passes)",
            cws.iterations, cws.products, gws.stats.iterations, gws.stats.products
        );
        assert!(gws.stats.converged && gws.stats.warm, "{what}: {gws:?}");
        assert!(
            gws.stats.iterations <= cws.iterations,
            "{what}, warm: device {gws:?} vs CPU {cws:?}"
        );
        assert_eq!(
            gws.stats.products,
            gws.stats.iterations + 1,
            "{what}: {gws:?}"
        );
        assert_eq!(gws.submissions, 1, "{what}: {gws:?}");
        assert_close(
            &format!("{what}, warm: device vs CPU"),
            &gw,
            &cw,
            5.0 * tolerance,
        );
    }
    gpu.release(ctx);
}

#[test]
fn device_solve_matches_the_cpu_solvers_on_a_random_system() {
    let Some(ctx) = ctx() else { return };
    solve_both(ctx, &random_system(3000, 31), 32);
}

#[test]
fn device_solve_matches_the_cpu_solvers_when_tiled() {
    let Some(ctx) = tiny_ctx() else { return };
    let (bf, bs) = solve_both(ctx, &random_system(800, 41), 42);
    assert!(bf > 10 && bs > 1, "blocks: F {bf}, S {bs}");
}

#[test]
fn auto_takes_only_hardware_and_gpu_takes_any_adapter() {
    use translux_server::backend::{Backend, BackendChoice};
    let Some(ctx) = ctx() else { return };
    let auto = Backend::start(BackendChoice::Auto, None).unwrap();
    let health = auto.gpu_health();
    if ctx.adapter().software {
        // lavapipe/llvmpipe: a CPU in disguise; auto serves from the CPU and says why.
        assert_eq!(auto.name(), "cpu");
        assert!(!health.available);
        let reason = health.reason.unwrap();
        assert!(reason.contains("software"), "{reason}");
    } else {
        assert_eq!(auto.name(), "gpu");
        assert!(health.available && health.reason.is_none());
    }
    let gpu = Backend::start(BackendChoice::Gpu, None).unwrap();
    let health = gpu.gpu_health();
    let adapter = health.adapter.unwrap();
    assert_eq!(gpu.name(), "gpu");
    assert_eq!(adapter.software, ctx.adapter().software);
    assert_eq!(adapter.name, ctx.adapter().name);
    assert!(gpu.describe().contains(&adapter.name));
    assert_eq!(
        Backend::start(BackendChoice::Cpu, None).unwrap().name(),
        "cpu"
    );
}

mod relight_on_both_backends {
    use std::path::Path;

    use super::*;
    use translux_engine::backend::Backend as _;
    use translux_engine::relight;
    use translux_engine::scene::Scene;
    use translux_precompute::pipeline::{PrecomputeParams, precompute};
    use translux_precompute::scene::load_scene;
    use translux_proto::api::RelightRequest;
    use translux_server::backend::Backend;
    use translux_server::gpu::GpuOptions;

    /// The radiance, the solver, and where S for the overrides was built, relit on `backend`.
    fn radiance(dir: &Path, body: &str, backend: &Backend) -> (Vec<Rgb>, String, Option<String>) {
        // A fresh scene each time: no warm start carried over from the other backend.
        let scene = Scene::open_with("cornell", dir, &backend.resources()).unwrap();
        let req: RelightRequest = serde_json::from_str(body).unwrap();
        let mut plan = relight::plan(&scene, req).unwrap();
        plan.tolerance = 1e-6;
        let out = relight::run(&scene, &plan).unwrap();
        assert!(out.stats.converged, "{:?}", out.stats);
        (out.radiance, out.stats.solver, out.stats.materials_on)
    }

    /// Whole relights (shadowed direct light on the CPU, the solve on the device) agree with
    /// the CPU backend on a Cornell box with its marble block, with the bundle's S and with a
    /// translucency override (S built on the CPU, solved with on the device); a scene over
    /// the memory budget is served from the CPU, with its reason in the health report.
    #[test]
    fn whole_relights_agree_and_a_scene_over_budget_stays_on_the_cpu() {
        let Some(_) = ctx() else { return };
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("cornell");
        let params = PrecomputeParams {
            patches: Some(400),
            inverse: true,
            ..Default::default()
        };
        precompute(&load_scene("builtin:cornell").unwrap(), &dir, &params).unwrap();
        let bodies = [
            r#"{"solver":"iterative"}"#,
            r#"{"solver":"iterative","lights":[{"type":"point","position":[0.1,0.5,0.2],"intensity":[2,1,0.5]}],
                "materials":{"tall_block":{"type":"translucent","profile":{"type":"dipole","preset":"marble","scale":2}}}}"#,
            r#"{"solver":"inverse","lights":[{"type":"point","position":[-0.2,0.6,0.1],"intensity":[1,2,1]}]}"#,
        ];
        // A batch of 3 relights: one pass over T on the device for all of them.
        let batch: Vec<String> = (0..3)
            .map(|i| {
                format!(
                    r#"{{"solver":"inverse","lights":[{{"type":"point","position":[{},0.5,0.1],"intensity":[1,1,1]}}]}}"#,
                    0.1 * i as f32 - 0.1
                )
            })
            .collect();
        let run_batch = |dir: &Path, backend: &Backend| -> Vec<Vec<Rgb>> {
            let scene = Scene::open_with("cornell", dir, &backend.resources()).unwrap();
            let plans: Vec<_> = batch
                .iter()
                .map(|b| relight::plan(&scene, serde_json::from_str(b).unwrap()).unwrap())
                .collect();
            relight::run_batch(&scene, &plans)
                .into_iter()
                .map(|r| {
                    let r = r.unwrap();
                    assert_eq!((r.stats.solver.as_str(), r.stats.batch), ("inverse", 3));
                    r.radiance
                })
                .collect()
        };
        // Both backends in one process, each scene on its own.
        let cpu_backend = Backend::cpu("the test's CPU half");
        let gpu_backend = Backend::on_gpu(
            GpuContext::new(&GpuOptions {
                allow_software: true,
                ..Default::default()
            })
            .unwrap(),
        );
        let cpu_batch = run_batch(&dir, &cpu_backend);
        let cpu: Vec<(Vec<Rgb>, String, Option<String>)> = bodies
            .iter()
            .map(|b| radiance(&dir, b, &cpu_backend))
            .collect();
        assert_eq!(
            cpu[1].2.as_deref(),
            Some("cpu"),
            "the CPU backend rebuilds S"
        );
        assert_eq!(cpu[2].1, "inverse");
        assert_eq!(cpu_backend.gpu_health().scenes.len(), 0);
        for (body, (want, cpu_solver, _)) in bodies.iter().zip(&cpu) {
            let (got, solver, on) = radiance(&dir, body, &gpu_backend);
            if body.contains("materials") {
                // A translucency change's S is built on the CPU, uploaded, and solved with
                // on the device (by Jacobi).
                assert_eq!(on.as_deref(), Some("gpu"), "{body}");
                assert_eq!(solver, "jacobi", "{body}");
                assert_close(&format!("GPU vs CPU relight {body}"), &got, want, 1e-3);
            } else if cpu_solver == "inverse" {
                // The same stored f16 T on both: only the summation order differs.
                assert_eq!(solver, "inverse");
                assert_close(&format!("GPU vs CPU relight {body}"), &got, want, 1e-4);
            } else {
                assert_eq!(
                    solver, "jacobi",
                    "the device solves by Jacobi (CPU: {cpu_solver})"
                );
                assert_close(&format!("GPU vs CPU relight {body}"), &got, want, 1e-3);
            }
        }
        let gpu_batch = run_batch(&dir, &gpu_backend);
        for (v, (got, want)) in gpu_batch.iter().zip(&cpu_batch).enumerate() {
            assert_close(&format!("GPU vs CPU batched relight {v}"), got, want, 1e-4);
        }
        let h = gpu_backend.gpu_health();
        assert_eq!(h.scenes.len(), 1, "{h:?}");
        assert_eq!(h.scenes[0].on, "gpu");
        assert!(
            h.scenes[0].bytes > 0 && h.bytes >= h.scenes[0].bytes,
            "{h:?}"
        );

        // 1 MiB of budget: the scene does not fit, the CPU serves it and says why.
        let small = Backend::on_gpu(
            GpuContext::new(&GpuOptions {
                allow_software: true,
                max_binding_bytes: None,
                budget_bytes: Some(1 << 10),
            })
            .unwrap(),
        );
        let scene = Scene::open("cornell", &dir).unwrap();
        let n = scene.bundle.patch_areas().len();
        let e = vec![[1.0f32; 3]; n];
        assert!(!small.prepare(scene.view()));
        assert!(
            small
                .solve(scene.view(), None, &e, &e, &SolveParams::default())
                .is_none()
        );
        let h = small.gpu_health();
        assert_eq!(h.scenes[0].on, "cpu");
        let reason = h.scenes[0].reason.clone().unwrap();
        assert!(
            reason.contains("does not fit") && reason.contains("budget"),
            "{reason}"
        );
        assert_eq!(h.bytes, 0, "nothing stays reserved: {h:?}");
    }
}

/// On the GPU backend a translucency slider's S is written on the device: the first step
/// uploads S as the CPU built it, each later one writes the block's rows there from their
/// radial terms (2 submissions) and solves from the last answer, and every step answers as
/// the CPU backend does. A step the device cannot take (components other than `full`)
/// makes the CPU's S from the rows it left unwritten, and answers as the CPU backend too.
#[test]
fn a_translucency_slider_on_the_gpu_backend_writes_s_on_the_device() {
    use translux_engine::backend::Backend as _;
    use translux_engine::relight;
    use translux_engine::scene::Scene;
    use translux_proto::api::{PrepState, RelightRequest};
    use translux_server::backend::Backend;
    let Some(_) = ctx() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("cornell");
    hierarchical_cornell(&dir, 1500);
    let body = |scale: f32, components: &str| {
        format!(
            r#"{{"solver":"iterative","components":"{components}","lights":[{{"type":"point","position":[0.1,0.5,0.2],"intensity":[2,1,0.5]}}],
            "materials":{{"tall_block":{{"type":"translucent","profile":{{"type":"dipole","preset":"marble","scale":{scale}}}}}}}}}"#
        )
    };
    let gpu = Backend::on_gpu(
        GpuContext::new(&GpuOptions {
            allow_software: true,
            ..Default::default()
        })
        .unwrap(),
    );
    assert!(
        gpu.describe()
            .contains("translucency changes write S on the GPU"),
        "{}",
        gpu.describe()
    );
    let cpu = Backend::cpu("the test's CPU half");
    let steps = [
        (1.0f32, "full"),
        (1.25, "full"),
        (1.5, "full"),
        (0.75, "subsurface_only"),
        (0.5, "full"),
        (3.0, "full"),
    ];
    let slide = |backend: &Backend, on_device: bool| {
        let scene = Scene::open_with("cornell", &dir, &backend.resources()).unwrap();
        assert_eq!(backend.prepare(scene.view()), on_device);
        let p = scene.prepare_translucency();
        assert_eq!((p.state, p.on.as_deref()), (PrepState::Ready, Some("cpu")));
        steps
            .iter()
            .enumerate()
            .map(|(x, &(k, components))| {
                let req: RelightRequest = serde_json::from_str(&body(k, components)).unwrap();
                let mut plan = relight::plan(&scene, req).unwrap();
                plan.tolerance = 1e-6;
                let out = relight::run(&scene, &plan).unwrap();
                assert!(out.stats.converged, "{:?}", out.stats);
                let device = on_device && components == "full";
                let on = if device { "gpu" } else { "cpu" };
                assert_eq!(out.stats.materials_on.as_deref(), Some(on), "step {x}");
                if let Some(d) = out.stats.device {
                    eprintln!(
                        "step {x} ({k}, {components}): S {:.1} ms, solve {:.1} ms, {} it., {d:?}",
                        out.stats.materials_ms, out.stats.solve_ms, out.stats.iterations
                    );
                }
                if device && x > 0 {
                    // Written in place: 2 submissions for S, then the solve's.
                    let d = out.stats.device.expect("device stats");
                    assert!(d.submissions >= 3, "step {x}: {d:?}");
                    assert!(out.stats.materials_ms > 0.0, "step {x}");
                }
                out.radiance
            })
            .collect::<Vec<Vec<Rgb>>>()
    };
    let (got, want) = (slide(&gpu, true), slide(&cpu, false));
    for (k, (g, w)) in got.iter().zip(&want).enumerate() {
        // Jacobi on the device, the CPU's solver there, both to 1e-6.
        assert_close(&format!("slider step {k}, GPU vs CPU backend"), g, w, 1e-3);
    }
    let h = gpu.gpu_health();
    assert!(h.scenes[0].bytes > 0, "{h:?}");
}

/// A scene that fits the GPU budget while S of its material overrides does not: a `full`
/// relight with those overrides answers from the CPU (as the CPU backend does), also for
/// the slider's next step, and the device holds what it held.
#[test]
fn materials_over_the_budget_stay_on_the_cpu() {
    use translux_engine::backend::Backend as _;
    use translux_engine::relight;
    use translux_engine::scene::Scene;
    use translux_proto::api::RelightRequest;
    use translux_server::backend::Backend;
    let Some(_) = ctx() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("cornell");
    hierarchical_cornell(&dir, 1500);
    let body = |scale: f32| {
        format!(
            r#"{{"solver":"iterative","lights":[{{"type":"point","position":[0.1,0.5,0.2],"intensity":[2,1,0.5]}}],
            "materials":{{"tall_block":{{"type":"translucent","profile":{{"type":"dipole","preset":"marble","scale":{scale}}}}}}}}}"#
        )
    };
    let backend = |budget: Option<u64>| {
        Backend::on_gpu(
            GpuContext::new(&GpuOptions {
                allow_software: true,
                max_binding_bytes: None,
                budget_bytes: budget,
            })
            .unwrap(),
        )
    };
    // The scene's own bytes on the device, and a budget 64 KiB above them.
    let probe = backend(None);
    let scene = Scene::open_with("cornell", &dir, &probe.resources()).unwrap();
    assert!(probe.prepare(scene.view()));
    let base = probe.gpu_health().bytes;
    let tight = backend(Some(base + (64 << 10)));
    let cpu = Backend::cpu("the test's CPU half");
    let run = |b: &Backend, scale: f32| {
        let scene = Scene::open_with("cornell", &dir, &b.resources()).unwrap();
        let req: RelightRequest = serde_json::from_str(&body(scale)).unwrap();
        let mut plan = relight::plan(&scene, req).unwrap();
        plan.tolerance = 1e-6;
        relight::run(&scene, &plan).unwrap()
    };
    for scale in [1.0f32, 1.5] {
        let got = run(&tight, scale);
        assert_eq!(
            got.stats.materials_on.as_deref(),
            Some("cpu"),
            "{:?}",
            got.stats
        );
        assert!(got.stats.device.is_none(), "{:?}", got.stats);
        assert_eq!(tight.gpu_health().bytes, base, "nothing more is held");
        let want = run(&cpu, scale);
        assert_close(
            &format!("×{scale} over the budget"),
            &got.radiance,
            &want.radiance,
            1e-5,
        );
    }
}

mod server_start {
    use std::io::{BufRead, BufReader, Read, Write};
    use std::process::{Command, Stdio};

    const BIN: &str = env!("CARGO_BIN_EXE_translux-server");

    /// `--backend gpu` without any adapter (the Vulkan loader pointed at no driver) stops at
    /// start-up with a message that says what to install.
    #[test]
    fn backend_gpu_without_an_adapter_is_a_start_up_error() {
        let dir = tempfile::tempdir().unwrap();
        let out = Command::new(BIN)
            .args(["--bundles", dir.path().to_str().unwrap()])
            .args(["--addr", "127.0.0.1:0", "--backend", "gpu"])
            .env("VK_ICD_FILENAMES", "/nonexistent-icd.json")
            .env("VK_DRIVER_FILES", "/nonexistent-icd.json")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{err}");
        assert!(
            err.contains("--backend gpu: no GPU adapter found")
                && err.contains("mesa-vulkan-drivers"),
            "{err}"
        );
    }

    /// `--backend auto` passes over a software adapter: the server runs on the CPU and
    /// `/healthz` says why; with lavapipe, `--backend gpu` takes it and says "software".
    #[test]
    fn healthz_names_the_backend_and_the_adapter() {
        let Some(ctx) = super::ctx() else { return };
        let software = ctx.adapter().software;
        for choice in ["auto", "gpu"] {
            let dir = tempfile::tempdir().unwrap();
            let mut child = Command::new(BIN)
                .args(["--bundles", dir.path().to_str().unwrap()])
                .args(["--addr", "127.0.0.1:0", "--backend", choice])
                .env("RUST_LOG", "info")
                .stderr(Stdio::piped())
                .stdout(Stdio::null())
                .spawn()
                .unwrap();
            let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
            let mut log = String::new();
            let addr = loop {
                let Some(Ok(line)) = lines.next() else {
                    let _ = child.kill();
                    panic!("the server stopped before listening:\n{log}");
                };
                log.push_str(&line);
                log.push('\n');
                if let Some(rest) = line.split("listening on http://").nth(1) {
                    break rest.split('/').next().unwrap().to_string();
                }
            };
            let mut s = std::net::TcpStream::connect(&addr).unwrap();
            write!(s, "GET /healthz HTTP/1.0\r\nHost: {addr}\r\n\r\n").unwrap();
            let mut resp = String::new();
            s.read_to_string(&mut resp).unwrap();
            let _ = child.kill();
            let _ = child.wait();
            let body = resp.split("\r\n\r\n").nth(1).unwrap_or("");
            let h: serde_json::Value = serde_json::from_str(body).unwrap();
            let gpu = &h["gpu"];
            if choice == "auto" && software {
                assert_eq!(h["backend"], "cpu", "{h}");
                assert_eq!(gpu["available"], false, "{h}");
                let reason = gpu["reason"].as_str().unwrap();
                assert!(reason.contains("only software adapters"), "{reason}");
                assert!(log.contains("backend cpu: --backend auto"), "{log}");
            } else {
                assert_eq!(h["backend"], "gpu", "{h}");
                assert_eq!(gpu["available"], true, "{h}");
                assert_eq!(gpu["adapter"]["software"], software, "{h}");
                assert_eq!(gpu["bytes"], 0, "no scene yet: {h}");
                assert!(log.contains("backend gpu:"), "{log}");
                if software {
                    assert!(log.contains("software adapter"), "{log}");
                }
            }
        }
    }
}

/// A hierarchical F on the device (the pull P' = [I; P] then C, the same CSR kernel) solves
/// what the CPU solves with its prefix-sum pull; also split into 4 KiB blocks.
#[test]
fn device_solve_of_a_hierarchical_f_matches_the_cpu() {
    device_solve_of_hierarchical_f(false);
}

/// A two-sided F on the device (pull, C over patch and node rows, then the push Q' = [I | Q]
/// as a third CSR product) solves what the CPU solves with its difference-array push.
#[test]
fn device_solve_of_a_two_sided_f_matches_the_cpu() {
    device_solve_of_hierarchical_f(true);
}

fn device_solve_of_hierarchical_f(two_sided: bool) {
    use translux_engine::transport::Transport;
    use translux_precompute::hierarchy::HierarchyParams;
    use translux_precompute::pipeline::{FormFactorMethod, PrecomputeParams, precompute};
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cornell");
    let params = PrecomputeParams {
        patches: Some(700),
        transport: FormFactorMethod::Hierarchical(HierarchyParams {
            two_sided,
            ..Default::default()
        }),
        environment: translux_engine::envvis::EnvVisParams {
            bins: None,
            ..Default::default()
        },
        ..Default::default()
    };
    let loaded = translux_precompute::scene::load_scene("builtin:cornell").unwrap();
    precompute(&loaded, &out, &params).unwrap();
    let b = translux_proto::bundle::Bundle::open(&out).unwrap();
    let f = Transport::of(&b);
    assert!(f.is_hierarchical() && f.nodes() > 0);
    assert_eq!(f.has_node_rows(), two_sided);
    if two_sided {
        let node_rows = &f.matrix().row_ptr()[f.n()..];
        assert!(node_rows.last() > node_rows.first(), "nodes receive");
    }
    let n = f.n();
    let mut rng = Rng(41);
    let e: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
    let be = vec![[0.0f32; 3]; n];
    let p = SolveParams {
        method: Method::Jacobi,
        tolerance: 1e-6,
        max_iterations: 400,
    };
    let s = b.subsurface();
    let (cb, cs) = solve(&f, &SparseScatter(s), &be, &e, &p, None).unwrap();
    assert!(cs.converged, "{cs:?}");
    for ctx in [ctx(), tiny_ctx()] {
        let Some(ctx) = ctx else { return };
        let gpu = GpuSystem::new(ctx, "hierarchical", &f, &s, p.max_iterations).unwrap();
        let (gb, gs) = gpu.solve(ctx, &be, &e, &p, None).unwrap();
        assert!(gs.stats.converged, "{gs:?}");
        assert_close("GPU hierarchical vs CPU", &gb, &cb, 1e-4);
        gpu.release(ctx);
    }
}

/// A Cornell box whose marble block is 8 times as translucent (its profile reaches past
/// the near field), precomputed into `out` with a hierarchical S at `patches`.
pub(crate) fn hierarchical_cornell(
    out: &std::path::Path,
    patches: u64,
) -> translux_proto::bundle::Bundle {
    use translux_precompute::pipeline::{PrecomputeParams, precompute};
    use translux_precompute::slinks::SLinkParams;
    use translux_proto::scene::{Material, Profile};
    let mut loaded = translux_precompute::scene::load_scene("builtin:cornell").unwrap();
    let k = loaded
        .objects
        .iter()
        .position(|o| o.name == "tall_block")
        .unwrap();
    let m = Material::Translucent {
        profile: Profile::Dipole {
            preset: Some("marble".into()),
            sigma_a: None,
            sigma_s_prime: None,
            eta: None,
            scale: Some(8.0),
        },
        specular: None,
    };
    loaded.objects[k].material = m.clone();
    loaded.file.objects[k].material = m;
    let params = PrecomputeParams {
        patches: Some(patches),
        // Links cut by geometry alone (τ = 2 bounds nothing): this box is small against
        // marble's reach at ×8, and the error bound would leave it few links.
        subsurface_links: Some(SLinkParams {
            tolerance: translux_engine::linkbound::LinkTolerance {
                variation: 2.0,
                ..Default::default()
            },
            ..SLinkParams::default()
        }),
        environment: translux_engine::envvis::EnvVisParams {
            bins: None,
            ..Default::default()
        },
        ..Default::default()
    };
    precompute(&loaded, out, &params).unwrap();
    translux_proto::bundle::Bundle::open(out).unwrap()
}

/// A hierarchical S (links to F's cluster nodes) solved on the device: S reads the vector
/// F's pull makes, and the answer matches the CPU's prefix-sum pull.
#[test]
fn device_solve_of_a_hierarchical_s_matches_the_cpu() {
    use translux_engine::transport::{Transport, subsurface_operator};
    let dir = tempfile::tempdir().unwrap();
    let b = hierarchical_cornell(&dir.path().join("cornell"), 3000);
    let f = Transport::of(&b);
    let s = b.subsurface();
    let n = f.n();
    assert_eq!(s.n_cols(), n + f.nodes(), "S has node columns");
    assert!(s.col().iter().any(|&c| c as usize >= n), "S links to nodes");
    let mut rng = Rng(43);
    let e: Vec<Rgb> = (0..n).map(|_| rng.rgb()).collect();
    let be = vec![[0.0f32; 3]; n];
    let p = SolveParams {
        method: Method::Jacobi,
        tolerance: 1e-6,
        max_iterations: 400,
    };
    let op = subsurface_operator(&b, s);
    let (cb, cs) = solve(&f, op.as_ref(), &be, &e, &p, None).unwrap();
    assert!(cs.converged, "{cs:?}");
    // (The tiny context cannot bind the pull's root row at this size: a known limit of a
    // hierarchical F's pull, which then serves from the CPU.)
    if let Some(ctx) = ctx() {
        let gpu = GpuSystem::new(ctx, "hierarchical S", &f, &s, p.max_iterations).unwrap();
        let (gb, gs) = gpu.solve(ctx, &be, &e, &p, None).unwrap();
        assert!(gs.stats.converged, "{gs:?}");
        assert_close("GPU hierarchical S vs CPU", &gb, &cb, 1e-4);
        gpu.release(ctx);
    }
}
