//! Iterative solvers for the transport system (I − K F) x = b.
//!
//! In: the form factors F (CSR, scalar), a scattering operator K ([`Scatter`]: the sparse S
//! of translucent scenes, or diag ρ), a right-hand side b of `channels` values per patch
//! and a warm start. Out: x and what the solve took ([`SolveStats`]).
//!
//! Vectors are row-major `[patch][channel]` f32 slices. Channel `c` uses K's colour
//! component `c % 3`, so `channels = 3k` holds k independent RGB systems that share every
//! pass over F and K: the three colour channels of one relight, or the k relights of a
//! batch. Each channel stops on its own relative residual ‖b − (I − K F) x‖₂ / ‖b‖₂ (so a
//! dim colour channel is solved as accurately as a bright one).
//!
//! Methods:
//! - **Jacobi**: x ← b + K F x. One product (a pass over F and K) per iteration; converges
//!   like ρⁿ, so a bright closed room (ρ → 1) crawls.
//! - **Gauss-Seidel**: the same update patch by patch with the newest values (diagonal K
//!   only; sequential).
//! - **BiCGSTAB** (van der Vorst 1992) per channel: two products per iteration, converges
//!   like a Krylov method (roughly with √κ rather than κ), so far fewer products in bright
//!   scenes. I − K F is not symmetric, which rules out conjugate gradients. Written here
//!   because it has to share each product among 3k independent systems with their own
//!   scalars, which no sparse-solver crate's single-vector API does. The recurrence residual
//!   drifts from the true one in f32, so after the recurrence says "converged" the true
//!   residual is computed and the method restarts from the current x if it is not.

use std::time::Instant;

use rayon::prelude::*;

use crate::transport::{Pulled, Transport};

use crate::linalg::Scatter;

/// Iteration scheme.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// x ← b + K F x, all patches at once (parallel).
    Jacobi,
    /// The same update patch by patch, using values already updated in this sweep
    /// (sequential; diagonal K only).
    GaussSeidel,
    /// Stabilised bi-conjugate gradients, per channel.
    BiCgStab,
    /// Jacobi while it converges fast, BiCGSTAB (from Jacobi's iterate) when the first
    /// sweeps predict more than [`AUTO_SWITCH`] more: Jacobi's error is the unsummed tail
    /// of the bounce series, smooth and positive, so dim patches are as accurate as bright
    /// ones at a given residual; a Krylov iterate at the same residual can be off by 10%
    /// on dim patches. Bright scenes, where Jacobi crawls, get the Krylov method.
    Auto,
}

/// [`Method::Auto`] switches to BiCGSTAB when Jacobi's observed contraction predicts more
/// than this many further sweeps.
pub const AUTO_SWITCH: u32 = 30;

impl Method {
    /// The name reported in stats (`jacobi`, `gauss_seidel`, `bicgstab`).
    pub fn as_str(self) -> &'static str {
        match self {
            Method::Jacobi => "jacobi",
            Method::GaussSeidel => "gauss_seidel",
            Method::BiCgStab => "bicgstab",
            Method::Auto => "auto",
        }
    }
}

/// Solver settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveParams {
    /// Default: [`Method::Auto`].
    pub method: Method,
    /// Stop when ‖b − (I − K F)x‖₂ / ‖b‖₂ falls below this in every channel. Default
    /// 0.005 (the paper's 0.5%).
    pub tolerance: f32,
    /// Give up after this many iterations. Default 500.
    pub max_iterations: u32,
}

impl Default for SolveParams {
    fn default() -> Self {
        Self {
            method: Method::Auto,
            tolerance: 0.005,
            max_iterations: 500,
        }
    }
}

/// What a solve did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveStats {
    pub method: Method,
    /// Iterations (the most any system needed).
    pub iterations: u32,
    /// Matrix-vector products: passes over F and K (Jacobi: one per iteration plus the
    /// residual check; BiCGSTAB: two per iteration plus one per true-residual check). A
    /// first check from [`Primed`] products counts none, even where it applies K alone.
    pub products: u32,
    /// Relative residual of the returned x (the largest over the channels).
    pub residual: f32,
    pub converged: bool,
    /// Whether it started from a given solution (not from b).
    pub warm: bool,
    pub seconds: f64,
}

/// Why a solve could not run.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SolveError {
    #[error(
        "Gauss-Seidel needs a diagonal S (an opaque scene); use Jacobi or BiCGSTAB for \
         translucent objects"
    )]
    GaussSeidelNeedsDiagonal,
    #[error("the right-hand side has {got} values, expected patches × channels = {expected}")]
    Length { got: usize, expected: usize },
    #[error("channels must be a positive multiple of 3 (RGB systems), got {0}")]
    Channels(usize),
    /// The right-hand side or the iterates left f32's range: the lights are too strong for
    /// the scene. Never answered with a warm start or any other stale vector.
    #[error(
        "the solve overflows (values beyond f32's range); use smaller intensities or \
         irradiances"
    )]
    Overflow,
}

pub use crate::linalg::spmv_multi;

/// The operator A = I − K F with its scratch space.
struct System<'a> {
    f: &'a Transport<'a>,
    k: &'a dyn Scatter,
    ch: usize,
    /// F x and K F x of the last x passed to [`System::kf`].
    fx: Vec<f32>,
    kfx: Vec<f32>,
    pulled: Pulled,
    products: u32,
    /// F x₀ (and K F x₀) of the start, known from the solve that answered x₀: the first
    /// call of [`System::kf`], which every method makes on the start, takes them instead.
    primed: Option<(Vec<f32>, Option<Vec<f32>>)>,
    /// `fx` and `kfx` are those of the x a Jacobi run returned: a run that follows it on
    /// the same x takes them instead of a product.
    known: bool,
}

impl System<'_> {
    /// `self.kfx` = K F x (one product), `self.fx` = F x.
    fn kf(&mut self, x: &[f32]) {
        match self.primed.take() {
            Some((fx, Some(kfx))) => {
                self.fx = fx;
                self.kfx = kfx;
            }
            Some((fx, None)) => {
                self.fx = fx;
                self.k.apply_multi(&self.fx, &mut self.kfx, self.ch);
            }
            None => {
                self.f
                    .apply_multi(x, &mut self.fx, self.ch, &mut self.pulled);
                self.k.apply_multi(&self.fx, &mut self.kfx, self.ch);
                self.products += 1;
            }
        }
    }

    /// y = (I − K F) x.
    fn apply(&mut self, x: &[f32], y: &mut [f32]) {
        self.kf(x);
        y.par_iter_mut()
            .zip(x.par_iter().zip(self.kfx.par_iter()))
            .for_each(|(y, (x, k))| {
                *y = *x - *k;
            });
    }
}

/// Per-channel dot products Σ_i a[i·ch + c]·b[i·ch + c], in f64.
fn dots(a: &[f32], b: &[f32], ch: usize) -> Vec<f64> {
    const ROWS: usize = 512;
    a.par_chunks(ch * ROWS)
        .zip(b.par_chunks(ch * ROWS))
        .map(|(a, b)| {
            let mut acc = vec![0.0f64; ch];
            for (ra, rb) in a.chunks_exact(ch).zip(b.chunks_exact(ch)) {
                for c in 0..ch {
                    acc[c] += ra[c] as f64 * rb[c] as f64;
                }
            }
            acc
        })
        .reduce(
            || vec![0.0f64; ch],
            |mut x, y| {
                for (a, b) in x.iter_mut().zip(y) {
                    *a += b;
                }
                x
            },
        )
}

/// Relative residual ‖r_c‖/‖b_c‖ per channel from squared norms (0 where b_c = 0).
fn channel_residuals(r2: &[f64], b2: &[f64]) -> Vec<f64> {
    r2.iter()
        .zip(b2)
        .map(|(&r, &b)| if b == 0.0 { 0.0 } else { (r / b).sqrt() })
        .collect()
}

/// What the solve that answered x₀ computed last, so a solve started from x₀ skips (part
/// of) its first product: F x₀, valid as long as F is the same (a bundle's F never
/// changes), and K F x₀, valid only under the same K. Both `ch` values per patch, as x₀.
#[derive(Debug, Clone, Copy)]
pub struct Primed<'a> {
    pub fx: &'a [f32],
    pub kfx: Option<&'a [f32]>,
    /// The answer kept before x₀ with its products ([`Before`]): the solve then starts
    /// from x₀ + α (x₀ − x₋₁), α per channel the least-squares minimiser of the start's
    /// residual — a slider moved at a steady pace is extrapolated along its last step.
    pub before: Option<Before<'a>>,
    /// Solves since `fx` and `kfx` (and `before`'s) last came out of a pass over F
    /// ([`Solved::age`]); past [`MAX_PRIMED_AGE`] they are not used.
    pub age: u32,
}

/// Kept products derived from kept products (a start extrapolated, or accepted as it is)
/// carry their rounding on: after this many solves without a pass over F, a solve computes
/// its first check afresh.
pub const MAX_PRIMED_AGE: u32 = 4;

/// x₋₁, an answer kept before the start x₀ of a [`Primed`] solve, with F x₋₁ and, when
/// its K is this solve's (and so is x₀'s), K F x₋₁.
#[derive(Debug, Clone, Copy)]
pub struct Before<'a> {
    pub x: &'a [f32],
    pub fx: &'a [f32],
    pub kfx: Option<&'a [f32]>,
}

/// A solve's answer and its last products, which are those of x itself (every method
/// returns right after the residual check of its answer): `fx` = F x and `kfx` = K F x, to
/// keep beside x as the next solve's [`Primed`].
#[derive(Debug, Clone)]
pub struct Solved {
    pub x: Vec<f32>,
    pub stats: SolveStats,
    pub fx: Vec<f32>,
    pub kfx: Vec<f32>,
    /// 0 when `fx` and `kfx` came out of a pass over F, else 1 + the age of the [`Primed`]
    /// products they were taken or derived from.
    pub age: u32,
}

/// Solves (I − K F) x = b for `ch` channels per patch (`ch` a multiple of 3). `warm`
/// starts from a previous solution of the same length (another length, or a non-finite
/// value, is ignored and reported as a cold start). A system whose b is 0 gets x = 0.
pub fn solve_system(
    f: &Transport<'_>,
    k: &dyn Scatter,
    b: &[f32],
    ch: usize,
    params: &SolveParams,
    warm: Option<&[f32]>,
) -> Result<(Vec<f32>, SolveStats), SolveError> {
    solve_primed(f, k, b, ch, params, warm, None).map(|s| (s.x, s.stats))
}

/// [`solve_system`] from a warm start whose products a previous solve already computed
/// ([`Solved::fx`], [`Solved::kfx`]): the first residual check then takes K F x₀ as given,
/// or applies K alone to F x₀, and counts no product. Without [`Primed::before`] the
/// answer is the one [`solve_system`] gives from the same start (the products are
/// deterministic); with it the start moves along the last step first (one pass over K on
/// two vectors at most, none when K F x₋₁ is given), and the answer is another iterate
/// that meets the same tolerance. `primed` is ignored with a cold start, when older than
/// [`MAX_PRIMED_AGE`], or when its lengths or values are not those of a finite
/// `ch`-channel vector.
pub fn solve_primed(
    f: &Transport<'_>,
    k: &dyn Scatter,
    b: &[f32],
    ch: usize,
    params: &SolveParams,
    warm: Option<&[f32]>,
    primed: Option<Primed<'_>>,
) -> Result<Solved, SolveError> {
    let t0 = Instant::now();
    if ch == 0 || !ch.is_multiple_of(3) {
        return Err(SolveError::Channels(ch));
    }
    let n = f.n();
    if b.len() != n * ch {
        return Err(SolveError::Length {
            got: b.len(),
            expected: n * ch,
        });
    }
    if params.method == Method::GaussSeidel && k.diagonal().is_none() {
        return Err(SolveError::GaussSeidelNeedsDiagonal);
    }
    if !b.iter().all(|v| v.is_finite()) {
        return Err(SolveError::Overflow);
    }
    // A warm start of another length, or one that is not finite (a previous answer that
    // overflowed), would poison every iterate: start cold instead.
    let warm = warm.filter(|w| w.len() == b.len() && w.iter().all(|v| v.is_finite()));
    let mut x: Vec<f32> = match warm {
        Some(w) => w.to_vec(),
        None => b.to_vec(),
    };
    let usable = |v: &[f32]| v.len() == b.len() && v.iter().all(|v| v.is_finite());
    let primed_before = primed.and_then(|p| p.before);
    let age = primed.map_or(0, |p| p.age);
    let mut primed = warm
        .and(primed)
        .filter(|p| p.age < MAX_PRIMED_AGE)
        .filter(|p| usable(p.fx) && p.kfx.is_none_or(usable))
        .map(|p| (p.fx.to_vec(), p.kfx.map(<[f32]>::to_vec)));
    let b2 = dots(b, b, ch);
    // Channels with b = 0 have the answer 0 (and F 0 = K F 0 = 0).
    for (c, &bc) in b2.iter().enumerate() {
        if bc == 0.0 {
            let (fx, kfx) = match &mut primed {
                Some((fx, kfx)) => (Some(fx), kfx.as_mut()),
                None => (None, None),
            };
            for v in [Some(&mut x), fx, kfx].into_iter().flatten() {
                for v in v.chunks_exact_mut(ch) {
                    v[c] = 0.0;
                }
            }
        }
    }
    // Along the last step between two kept answers, d = x₀ − x₋₁: the start x₀ + α d with
    // F and K F of it from the kept products (F d = F x₀ − F x₋₁: F is linear) and one
    // pass over K for what K has not seen, so its residual check is still free.
    let before = warm
        .and(primed.as_ref())
        .and(primed_before)
        .filter(|p| usable(p.x) && usable(p.fx) && p.kfx.is_none_or(usable));
    if let (Some((fx0, kfx0)), Some(p)) = (&mut primed, before) {
        let d: Vec<f32> = x.par_iter().zip(p.x).map(|(a, b)| a - b).collect();
        let fd: Vec<f32> = fx0.par_iter().zip(p.fx).map(|(a, b)| a - b).collect();
        let (k0, kd) = match (kfx0.take(), p.kfx) {
            (Some(k0), Some(k1)) => {
                let kd = k0.par_iter().zip(k1).map(|(a, b)| a - b).collect();
                (k0, kd)
            }
            (Some(k0), None) => {
                let mut kd = vec![0.0f32; n * ch];
                k.apply_multi(&fd, &mut kd, ch);
                (k0, kd)
            }
            (None, _) => {
                // K on F x₀ and F d in one pass over K.
                let [k0, kd]: [Vec<f32>; 2] = crate::linalg::scatter_each(k, &[fx0, &fd], ch)
                    .try_into()
                    .expect("one product per vector");
                (k0, kd)
            }
        };
        // r(α) = r₀ + α v with r₀ = b + K F x₀ − x₀ and v = K F d − d.
        let r0: Vec<f32> = (b.par_iter().zip(&k0).zip(&x))
            .map(|((b, k), x)| b + k - x)
            .collect();
        let v: Vec<f32> = kd.par_iter().zip(&d).map(|(k, d)| k - d).collect();
        let (rv, vv) = (dots(&r0, &v, ch), dots(&v, &v, ch));
        let alpha: Vec<f32> = (0..ch)
            .map(|c| {
                let a = -rv[c] / vv[c];
                if b2[c] > 0.0 && vv[c] > 0.0 && a.is_finite() {
                    a as f32
                } else {
                    0.0
                }
            })
            .collect();
        let along = |v: &mut [f32], by: &[f32]| {
            v.par_chunks_mut(ch)
                .zip(by.par_chunks(ch))
                .for_each(|(v, by)| {
                    for c in 0..ch {
                        v[c] += alpha[c] * by[c];
                    }
                });
        };
        let mut k0 = k0;
        along(&mut x, &d);
        along(fx0, &fd);
        along(&mut k0, &kd);
        *kfx0 = Some(k0);
    }
    let mut sys = System {
        f,
        k,
        ch,
        fx: vec![0.0; n * ch],
        kfx: vec![0.0; n * ch],
        pulled: Pulled::default(),
        products: 0,
        primed,
        known: false,
    };
    let mut method = params.method;
    let (iterations, residual) = match params.method {
        Method::Jacobi | Method::GaussSeidel => {
            let (it, res, _) = jacobi(&mut sys, b, &b2, &mut x, params);
            (it, res)
        }
        Method::BiCgStab => bicgstab(&mut sys, b, &b2, &mut x, params),
        Method::Auto => {
            // A few Jacobi sweeps measure the contraction q; (tol/r)^(1/ln q) more to go.
            const PROBE: u32 = 4;
            let first = SolveParams {
                method: Method::Jacobi,
                max_iterations: PROBE.min(params.max_iterations),
                ..*params
            };
            // The probe's first residual check is the start's own residual (r0): no product
            // of its own.
            let (it, res, r0) = jacobi(&mut sys, b, &b2, &mut x, &first);
            let tol = params.tolerance as f64;
            if res <= tol || it >= params.max_iterations {
                method = Method::Jacobi;
                (it, res)
            } else {
                let q = if r0 > 0.0 && it > 0 {
                    (res / r0).powf(1.0 / it as f64)
                } else {
                    1.0
                };
                let more = if q < 1.0 {
                    (tol / res).ln() / q.ln()
                } else {
                    f64::INFINITY
                };
                let rest = SolveParams {
                    max_iterations: params.max_iterations - it,
                    ..*params
                };
                let (it2, res2) = if more <= AUTO_SWITCH as f64 {
                    method = Method::Jacobi;
                    let (it, res, _) = jacobi(&mut sys, b, &b2, &mut x, &rest);
                    (it, res)
                } else {
                    method = Method::BiCgStab;
                    bicgstab(&mut sys, b, &b2, &mut x, &rest)
                };
                (it + it2, res2)
            }
        }
    };
    // An overflow mid-solve makes the residual NaN or infinite; x may then still be the
    // warm start (another request's answer), which must never be returned as this one's.
    if !residual.is_finite() || !x.iter().all(|v| v.is_finite()) {
        return Err(SolveError::Overflow);
    }
    let stats = SolveStats {
        method,
        iterations,
        products: sys.products,
        residual: residual as f32,
        converged: residual <= params.tolerance as f64,
        warm: warm.is_some(),
        seconds: t0.elapsed().as_secs_f64(),
    };
    Ok(Solved {
        x,
        stats,
        age: if sys.products > 0 { 0 } else { age + 1 },
        fx: sys.fx,
        kfx: sys.kfx,
    })
}

/// Largest step along the residual a Jacobi iteration takes (`minimal_residual_step`).
/// Below 2 so the products derived for the new x carry at most 0.9 of the last ones'
/// rounding (x + α r's are (1 − α) of x's plus α of a fresh pass): over a slider's chain
/// of steps it stays a bounded multiple of one pass's.
pub const MAX_STEP: f64 = 1.9;

/// One Jacobi iteration from x with residual r = b + K F x − x (`sys` holding F x and K F x),
/// stretched to the step along r with the least residual, channel by channel: with one
/// product at y = x + r (plain Jacobi's next iterate), K F r = K F y − K F x, so
/// r(α) = r + α (K F r − r) for every α and its minimiser α = −⟨r, v⟩/⟨v, v⟩ (v = K F r − r)
/// costs no product. x becomes x + α r, and `sys` its products (derived from x's and y's,
/// so its residual check is free). In radiosity the slow error of Jacobi is K F's dominant
/// mode (eigenvalue λ, the ambient part of the light); there α = 1/(1 − λ) removes it in one
/// step where Jacobi leaves λ of it. α = 1 is Jacobi; α is clamped to [0.1, [`MAX_STEP`]].
/// A channel with b = 0 (x and r 0) stays at α = 1.
fn minimal_residual_step(sys: &mut System<'_>, x: &mut [f32], r: &[f32], b2: &[f64]) {
    let ch = sys.ch;
    let fx0 = std::mem::take(&mut sys.fx);
    let kfx0 = std::mem::take(&mut sys.kfx);
    let y: Vec<f32> = x.par_iter().zip(r).map(|(x, r)| x + r).collect();
    sys.fx = vec![0.0; x.len()];
    sys.kfx = vec![0.0; x.len()];
    sys.kf(&y);
    // v = K F r − r = (K F y − K F x) − r.
    let v: Vec<f32> = (sys.kfx.par_iter().zip(&kfx0).zip(r))
        .map(|((ky, k0), r)| ky - k0 - r)
        .collect();
    let (rv, vv) = (dots(r, &v, ch), dots(&v, &v, ch));
    let alpha: Vec<f32> = (0..ch)
        .map(|c| {
            let a = -rv[c] / vv[c];
            if b2[c] > 0.0 && vv[c] > 0.0 && a.is_finite() {
                a.clamp(0.1, MAX_STEP) as f32
            } else {
                1.0
            }
        })
        .collect();
    // x += α r; F x and K F x move the same way, from x's towards y's.
    x.par_chunks_mut(ch)
        .zip(r.par_chunks(ch))
        .for_each(|(x, r)| {
            for c in 0..ch {
                x[c] += alpha[c] * r[c];
            }
        });
    for (now, was) in [(&mut sys.fx, &fx0), (&mut sys.kfx, &kfx0)] {
        now.par_chunks_mut(ch)
            .zip(was.par_chunks(ch))
            .for_each(|(now, was)| {
                for c in 0..ch {
                    now[c] = was[c] + alpha[c] * (now[c] - was[c]);
                }
            });
    }
}

/// Jacobi or Gauss-Seidel; returns (iterations, largest relative residual of the answer,
/// that of the start: the first check, which the automatic choice reuses as r0).
fn jacobi(
    sys: &mut System<'_>,
    b: &[f32],
    b2: &[f64],
    x: &mut [f32],
    params: &SolveParams,
) -> (u32, f64, f64) {
    let ch = sys.ch;
    let tol = params.tolerance as f64;
    let mut r = vec![0.0f32; b.len()];
    let mut iterations = 0;
    let mut first = None;
    // The products of x are known from the step before (its last iterate's, derived
    // below) when this follows another Jacobi run on the same system.
    let mut known = std::mem::take(&mut sys.known);
    loop {
        // r = b + K F x − x: the residual of x, and also the Jacobi step.
        if !known {
            sys.kf(x);
        }
        known = false;
        r.par_iter_mut()
            .zip(b.par_iter().zip(sys.kfx.par_iter().zip(x.par_iter())))
            .for_each(|(r, (b, (k, x)))| *r = b + k - x);
        let residual = channel_residuals(&dots(&r, &r, ch), b2)
            .into_iter()
            .fold(0.0, f64::max);
        let first = *first.get_or_insert(residual);
        if residual <= tol || iterations >= params.max_iterations {
            // x itself, not the step x + r already paid for: a request made again starts
            // from its own answer and must answer the same.
            sys.known = true;
            return (iterations, residual, first);
        }
        iterations += 1;
        match (params.method, sys.k.diagonal()) {
            (Method::GaussSeidel, Some(rho)) => {
                // Patches are read as they are updated; cluster nodes (hierarchical F) hold
                // their means from the start of the sweep, and what nodes receive (a
                // two-sided F's node rows) is gathered once then.
                let n = x.len() / ch;
                sys.f.pull(x, ch, &mut sys.pulled);
                let nodes = &sys.pulled.values;
                let held = sys.f.node_rows_pushed(nodes, ch);
                let mut acc = vec![0.0f32; ch];
                for i in 0..n {
                    match &held {
                        Some(h) => acc.copy_from_slice(&h[i * ch..(i + 1) * ch]),
                        None => acc.fill(0.0),
                    }
                    let (cols, vals) = sys.f.matrix().row(i);
                    for (&j, &v) in cols.iter().zip(vals) {
                        let j = j as usize;
                        let xj = if j < n {
                            &x[j * ch..(j + 1) * ch]
                        } else {
                            &nodes[j * ch..(j + 1) * ch]
                        };
                        for (a, &xv) in acc.iter_mut().zip(xj) {
                            *a += v * xv;
                        }
                    }
                    for c in 0..ch {
                        x[i * ch + c] = b[i * ch + c] + rho[i][c % 3] * acc[c];
                    }
                }
            }
            _ => {
                minimal_residual_step(sys, x, &r, b2);
                known = true;
            }
        }
    }
}

/// BiCGSTAB per channel with true-residual restarts; returns (iterations, largest relative
/// residual).
fn bicgstab(
    sys: &mut System<'_>,
    b: &[f32],
    b2: &[f64],
    x: &mut [f32],
    params: &SolveParams,
) -> (u32, f64) {
    let ch = sys.ch;
    let len = b.len();
    let tol = params.tolerance as f64;
    let mut r = vec![0.0f32; len];
    let mut r_hat = vec![0.0f32; len];
    let mut p = vec![0.0f32; len];
    let mut v = vec![0.0f32; len];
    let mut s = vec![0.0f32; len];
    let mut t = vec![0.0f32; len];
    let mut iterations = 0u32;
    // A channel stops once ‖r_c‖ ≤ tol·‖b_c‖.
    let limit2: Vec<f64> = b2.iter().map(|b| tol * tol * b).collect();
    let mut restarts = 0;
    loop {
        // The true residual r = b − A x.
        sys.apply(x, &mut r);
        r.par_iter_mut()
            .zip(b.par_iter())
            .for_each(|(r, b)| *r = b - *r);
        let r2 = dots(&r, &r, ch);
        let res = channel_residuals(&r2, b2);
        let worst = res.iter().copied().fold(0.0, f64::max);
        if worst <= tol || iterations >= params.max_iterations || restarts > 20 {
            return (iterations, worst);
        }
        restarts += 1;
        // A channel is active while its residual is above the tolerance.
        let active: Vec<bool> = res.iter().map(|&r| r > tol).collect();
        let mut active = active;
        r_hat.copy_from_slice(&r);
        p.fill(0.0);
        v.fill(0.0);
        let mut rho_prev = vec![1.0f64; ch];
        let mut alpha = vec![1.0f64; ch];
        let mut omega = vec![1.0f64; ch];
        while iterations < params.max_iterations && active.iter().any(|&a| a) {
            iterations += 1;
            let rho = dots(&r_hat, &r, ch);
            let mut beta = vec![0.0f64; ch];
            for c in 0..ch {
                if !active[c] {
                    continue;
                }
                // Breakdown (ρ = 0 or ω = 0): end this cycle; the restart takes over.
                if rho[c] == 0.0 || omega[c] == 0.0 || !rho[c].is_finite() {
                    active[c] = false;
                    continue;
                }
                beta[c] = (rho[c] / rho_prev[c]) * (alpha[c] / omega[c]);
            }
            // p = r + β(p − ω v); inactive channels keep p = 0 so their x stays put.
            p.par_chunks_mut(ch)
                .zip(r.par_chunks(ch).zip(v.par_chunks(ch)))
                .for_each(|(p, (r, v))| {
                    for c in 0..ch {
                        p[c] = if active[c] {
                            r[c] + (beta[c] * (p[c] as f64 - omega[c] * v[c] as f64)) as f32
                        } else {
                            0.0
                        };
                    }
                });
            sys.apply(&p, &mut v);
            let rv = dots(&r_hat, &v, ch);
            for c in 0..ch {
                if active[c] {
                    if rv[c] == 0.0 || !rv[c].is_finite() {
                        active[c] = false;
                        alpha[c] = 0.0;
                    } else {
                        alpha[c] = rho[c] / rv[c];
                    }
                } else {
                    alpha[c] = 0.0;
                }
            }
            // s = r − α v; x += α p.
            s.par_chunks_mut(ch)
                .zip(r.par_chunks(ch).zip(v.par_chunks(ch)))
                .zip(x.par_chunks_mut(ch).zip(p.par_chunks(ch)))
                .for_each(|((s, (r, v)), (x, p))| {
                    for c in 0..ch {
                        s[c] = r[c] - (alpha[c] * v[c] as f64) as f32;
                        x[c] += (alpha[c] * p[c] as f64) as f32;
                    }
                });
            let s2 = dots(&s, &s, ch);
            let mut half_done = vec![false; ch];
            for c in 0..ch {
                if active[c] && s2[c] <= limit2[c] {
                    // Converged half-way: x + α p is the answer for this channel.
                    half_done[c] = true;
                }
            }
            sys.apply(&s, &mut t);
            let ts = dots(&t, &s, ch);
            let tt = dots(&t, &t, ch);
            for c in 0..ch {
                omega[c] = if active[c] && !half_done[c] && tt[c] > 0.0 {
                    ts[c] / tt[c]
                } else {
                    0.0
                };
            }
            // x += ω s; r = s − ω t.
            x.par_chunks_mut(ch)
                .zip(r.par_chunks_mut(ch))
                .zip(s.par_chunks(ch).zip(t.par_chunks(ch)))
                .for_each(|((x, r), (s, t))| {
                    for c in 0..ch {
                        x[c] += (omega[c] * s[c] as f64) as f32;
                        r[c] = s[c] - (omega[c] * t[c] as f64) as f32;
                    }
                });
            let r2 = dots(&r, &r, ch);
            for c in 0..ch {
                if !active[c] {
                    continue;
                }
                if half_done[c] || r2[c] <= limit2[c] || omega[c] == 0.0 {
                    active[c] = false;
                }
            }
            rho_prev = rho;
        }
    }
}
