//! Stage 4 of the relight, per group of plans with the same materials and components: E
//! and Bₑ stacked for the group, the lamps' collimated terms, then the path its components
//! and plans take (no solve, the product with T, or the iterative solve from the warm
//! start kept for these materials), the correction for the light from other surfaces
//! entering simulated objects, and the start kept for the next relight.

use std::borrow::Cow;

use translux_proto::api::{Components, DeviceStats};
use translux_proto::scene::Material;

use super::prepare::Prepared;
use crate::backend::WithMaterials;
use crate::collimated::{Tilt, TiltOf};
use crate::error::EngineError;
use crate::inverse;
use crate::radiosity::{Albedo, Scatter, SolveParams};
use crate::scene::{Kept, Scene, Warm};
use crate::solver::{Before, MAX_PRIMED_AGE, Primed, SolveError, SolveStats, solve_primed};
use crate::transport::{Pulled, Transport};

/// What the transport of one group did.
pub(super) struct TransportStats {
    pub(super) solver: &'static str,
    pub(super) iterations: u32,
    pub(super) products: u32,
    pub(super) residual: f32,
    pub(super) converged: bool,
    pub(super) warm: bool,
    /// Milliseconds spent writing S for the group's materials within the transport (a
    /// translucency change deferred to its first use, [`Scene::cpu_s`], or written by the
    /// backend).
    pub(super) materials_ms: f64,
    /// Where the backend wrote S for the materials and solved with it: its name and what
    /// crossed the bus; `None` on the CPU.
    pub(super) device: Option<(&'static str, DeviceStats)>,
}

impl TransportStats {
    /// A transport without a solve (`direct`, `subsurface_only`).
    fn none() -> Self {
        TransportStats {
            solver: "none",
            iterations: 0,
            products: 0,
            residual: 0.0,
            converged: true,
            warm: false,
            materials_ms: 0.0,
            device: None,
        }
    }
}

/// The transport for a group of plans with the same materials and components: radiosity
/// `[patch][k·3]` for the k plans.
pub(super) fn transport(
    scene: &Scene,
    components: Components,
    params: &SolveParams,
    first: &Prepared,
    preps: &[&Prepared],
    n: usize,
) -> Result<(Vec<f32>, TransportStats), EngineError> {
    // The group's operators: S and P = diag ρ̄ under its materials, and F; its stacked
    // E and Bₑ.
    let b = &scene.bundle;
    let (albedo, emission) = match &first.materials {
        Some(m) => (m.albedo.as_slice(), m.emission.as_slice()),
        None => (b.patch_albedo(), b.patch_emission()),
    };
    let mut src = Sources::stack(preps, emission, n);
    if let Some(done) = on_backend(scene, components, params, first, (&src, preps.len())) {
        return Ok(done);
    }
    // S for the materials, written here when it was deferred (its time is S's, not the
    // solve's).
    let ts = std::time::Instant::now();
    let mut materials_ms = 0.0;
    let (s_view, columns) = match &first.materials {
        Some(m) => {
            let deferred = m.made_s().is_none();
            let (values, columns) = scene.cpu_s(m)?;
            if deferred {
                materials_ms = ts.elapsed().as_secs_f64() * 1e3;
            }
            (values.view(), columns.factors())
        }
        None => (b.subsurface(), None),
    };
    let s = crate::transport::subsurface_operator_scaled(b, s_view, columns);
    let f = Transport::of(b);
    let k = preps.len();
    let sys = System {
        scene,
        components,
        params,
        first,
        n,
        k,
        ch: 3 * k,
        s: s.as_ref(),
        p: Albedo(albedo),
        f: &f,
        keys: Keys::of(components, &first.materials_key),
    };
    // The lamps' collimated entry (y).
    src.y = sys.collimated(preps);
    // The path: no solve, T, or the solver from the kept start (keeping the next one's).
    let (x, mut stats) = match route(components, first.use_t) {
        Route::None => (sys.without_solve(&src), TransportStats::none()),
        Route::Transfer => sys.through_t(&src)?,
        Route::Solve => sys.iterate(&src)?,
    };
    stats.materials_ms = materials_ms;
    Ok((x, stats))
}

/// The full transport of a group with overridden materials where the backend writes their
/// S and solves with it (the GPU's, [`crate::backend::Backend::solve_materials`]), for the
/// `k` plans whose E and Bₑ `src` stacks: radiosity `[patch][k·3]`, or `None` to transport
/// here (another backend; other components, T, or
/// simulated objects' collimated light, which the CPU's stages add).
fn on_backend(
    scene: &Scene,
    components: Components,
    params: &SolveParams,
    first: &Prepared,
    (src, k): (&Sources, usize),
) -> Option<(Vec<f32>, TransportStats)> {
    let m = first.materials.as_ref()?;
    let collimated = first.collimated.is_some() || first.slant.is_some();
    if components != Components::Full || first.use_t || collimated || first.lamp_walks.is_some() {
        return None;
    }
    let cpu = || {
        let s = scene.cpu_s(m).ok()?;
        crate::smatrix::scaled_s(s).ok()
    };
    let with = WithMaterials {
        materials: m,
        cpu: &cpu,
    };
    let backend = scene.backend();
    let a = backend.solve_materials(scene.view(), &with, (&src.e, &src.be), k, params)?;
    let device = DeviceStats {
        submissions: a.submissions,
        bytes_up: a.bytes_up,
        bytes_down: a.bytes_down,
    };
    let stats = TransportStats {
        solver: a.stats.method.as_str(),
        iterations: a.stats.iterations,
        products: a.stats.products,
        residual: a.stats.residual,
        converged: a.stats.converged,
        warm: a.stats.warm,
        materials_ms: a.s_seconds * 1e3,
        device: Some((backend.name(), device)),
    };
    Some((a.x, stats))
}

/// Which way a group's transport goes.
enum Route {
    /// No solve: `direct` (B = Bₑ + P E) and `subsurface_only` (B = Bₑ + S E).
    None,
    /// The product with the bundle's T (`full`, where T holds for the materials).
    Transfer,
    /// The iterative solve of (I − K F) x = rhs.
    Solve,
}

/// The route for `components`, `use_t` the prepared plans' choice of T.
fn route(components: Components, use_t: bool) -> Route {
    match components {
        Components::Direct | Components::SubsurfaceOnly => Route::None,
        _ if use_t => Route::Transfer,
        _ => Route::Solve,
    }
}

/// a += x, element by element.
fn add(a: &mut [f32], x: &[f32]) {
    for (a, x) in a.iter_mut().zip(x) {
        *a += x;
    }
}

/// The group's sources stacked `[patch][plan][rgb]`: E, Bₑ (the same for every plan) and,
/// with lamps entering simulated objects collimated, y = Δ E_t + G_u E_u + G_v E_v + U E_w,
/// added wherever S E is.
struct Sources {
    e: Vec<f32>,
    be: Vec<f32>,
    y: Option<Vec<f32>>,
}

impl Sources {
    /// E and Bₑ of the group's plans, without y.
    fn stack(preps: &[&Prepared], emission: &[crate::radiosity::Rgb], n: usize) -> Self {
        let k = preps.len();
        let ch = 3 * k;
        // Stacked E: [patch][plan][rgb].
        let mut e = vec![0.0f32; n * ch];
        for (slot, q) in preps.iter().enumerate() {
            for j in 0..n {
                e[j * ch + 3 * slot..j * ch + 3 * slot + 3].copy_from_slice(&q.irradiance[j]);
            }
        }
        // Bₑ repeated per plan.
        let be: Vec<f32> = (0..n)
            .flat_map(|j| std::iter::repeat_n(emission[j], k).flatten())
            .collect();
        Sources { e, be, y: None }
    }

    /// a += y, where there is a y.
    fn add_y(&self, a: &mut [f32]) {
        if let Some(y) = &self.y {
            add(a, y);
        }
    }
}

/// The warm-start keys of a group: the answer's under its materials and components, and
/// the correction's for the light from other surfaces (each with the suffix that finds the
/// same components under other materials).
struct Keys {
    key: String,
    suffix: String,
    ckey: String,
    csuffix: String,
}

impl Keys {
    /// The keys of `components` under the materials of `materials_key`.
    fn of(components: Components, materials_key: &str) -> Self {
        let suffix = format!("|{}", components.as_str());
        let key = format!("{materials_key}{suffix}");
        // Where the correction for the light from other surfaces is kept
        // ([`System::correct`]).
        let (ckey, csuffix) = (format!("{key}|slant"), format!("{suffix}|slant"));
        Keys {
            key,
            suffix,
            ckey,
            csuffix,
        }
    }
}

/// A group's system: the scene, its operators (S under the group's materials, P = diag ρ̄
/// and F) and sizes (n patches, k plans, ch = 3k channels).
struct System<'a> {
    scene: &'a Scene,
    components: Components,
    params: &'a SolveParams,
    first: &'a Prepared,
    n: usize,
    k: usize,
    ch: usize,
    s: &'a dyn Scatter,
    p: Albedo<'a>,
    f: &'a Transport<'a>,
    keys: Keys,
}

impl System<'_> {
    /// Lamps' collimated entry into simulated objects: y = Δ E_t + G_u E_u + G_v E_v + U E_w
    /// of the plans' moments, the walked first scattering added where a plan walked its
    /// lamps' own beams; `None` without a tilt.
    fn collimated(&self, preps: &[&Prepared]) -> Option<Vec<f32>> {
        let (n, k, ch) = (self.n, self.k, self.ch);
        let t = self
            .first
            .collimated
            .as_ref()
            .and_then(|(t, _)| match t.as_ref() {
                TiltOf::Some(t) => Some(t),
                _ => None,
            })?;
        // [E_t, E_u, E_v, E_w] per patch and plan.
        let mut e_t = vec![0.0f32; n * 4 * ch];
        for (slot, q) in preps.iter().enumerate() {
            if let Some((_, et)) = &q.collimated {
                for (j, v) in et.iter().enumerate() {
                    let at = j * 4 * ch + 12 * slot;
                    e_t[at..at + 12].copy_from_slice(v.as_flattened());
                }
            }
        }
        let mut y = vec![0.0f32; n * ch];
        crate::collimated::add_first_scatter(t, &e_t, k, &mut y);
        self.add_walked(preps, t, &mut y);
        Some(y)
    }

    /// Where a plan walked its lamps' own beams: the walked first scattering in place of
    /// the model's ([`crate::lampwalk`]), added to its channels of `y`.
    fn add_walked(&self, preps: &[&Prepared], t: &Tilt, y: &mut [f32]) {
        let (n, ch) = (self.n, self.ch);
        for (slot, q) in preps.iter().enumerate() {
            if let Some((w, materials)) = &q.lamp_walks {
                let mut c = vec![0.0f32; 3 * n];
                let materials: Vec<&Material> = materials.iter().collect();
                w.add_correction(&materials, self.s, t, &mut c);
                for j in 0..n {
                    for ch3 in 0..3 {
                        y[j * ch + 3 * slot + ch3] += c[3 * j + ch3];
                    }
                }
            }
        }
    }

    /// The routes without a solve: B = Bₑ + P E (`direct`), B = Bₑ + S E + y
    /// (`subsurface_only`).
    fn without_solve(&self, src: &Sources) -> Vec<f32> {
        let mut se = vec![0.0f32; self.n * self.ch];
        match self.components {
            Components::Direct => {
                self.p.apply_multi(&src.e, &mut se, self.ch);
                add(&mut se, &src.be);
            }
            _ => {
                self.s.apply_multi(&src.e, &mut se, self.ch);
                add(&mut se, &src.be);
                src.add_y(&mut se);
            }
        }
        se
    }

    /// The route through T: B = Bₑ + S v + R v, v = E + F Bₑ (R = T − S, stored). With
    /// lamps' collimated entry (y): B = Bₑ + y + T(E + F (Bₑ + y)). Then the correction for
    /// the light from other surfaces ([`Self::correct`]).
    fn through_t(&self, src: &Sources) -> Result<(Vec<f32>, TransportStats), EngineError> {
        let (scene, n, k, ch) = (self.scene, self.n, self.k, self.ch);
        let t = scene
            .bundle
            .transfer()
            .ok_or_else(|| EngineError::internal("the transfer matrix vanished"))?;
        let mut v = vec![0.0f32; n * ch];
        let mut lit = src.be.clone();
        src.add_y(&mut lit);
        self.f.apply_multi(&lit, &mut v, ch, &mut Pulled::default());
        add(&mut v, &src.e);
        let mut bvec = vec![0.0f32; n * ch];
        self.s.apply_multi(&v, &mut bvec, ch);
        let mut rv = vec![0.0f32; n * ch];
        // The product over T on the scene's backend ([`crate::backend`]) when it takes it, else on the CPU.
        if !scene
            .backend()
            .transfer_product(scene.view(), &v, k, &mut rv)
        {
            inverse::apply_stored(t.bits, t.scale, t.n, &v, k, &mut rv);
        }
        add(&mut bvec, &rv);
        add(&mut bvec, &lit);
        // The light from other surfaces, entering simulated objects from where it comes.
        let more = self.correct(&mut bvec)?;
        Ok((
            bvec,
            TransportStats {
                solver: "inverse",
                iterations: more.map_or(0, |m| m.iterations),
                products: 1 + more.map_or(0, |m| m.products),
                residual: more.map_or(0.0, |m| m.residual),
                converged: more.is_none_or(|m| m.converged),
                warm: false,
                materials_ms: 0.0,
                device: None,
            },
        ))
    }

    /// The iterative route: (I − K F) x = rhs solved from the start kept for these
    /// materials ([`Self::solve_warm`]), its answer kept for the next relight, then the
    /// correction for the light from other surfaces, and with `heuristic_b` its S E part.
    fn iterate(&self, src: &Sources) -> Result<(Vec<f32>, TransportStats), EngineError> {
        let (n, ch) = (self.n, self.ch);
        let (mut x, mut st, products) = self.solve_warm(src)?;
        // Keep the last system's answer for the next relight with these materials (never one
        // that overflowed: it would poison the next solve), with its products when the CPU
        // solved it. (The kept answers were let go when the solve returned, so the one
        // replaced here moves instead of copying.)
        keep(self.scene, self.keys.key.clone(), &x, products, n, ch);
        // The light from other surfaces entering simulated objects from where it comes (kept
        // above without it: the next solve's start and products are this system's).
        if let Some(more) = self.correct(&mut x)? {
            st.iterations += more.iterations;
            st.products += more.products;
            st.residual = st.residual.max(more.residual);
            st.converged &= more.converged;
        }
        if self.components == Components::HeuristicB {
            // B = Bₑ + S E + Y.
            let mut sev = vec![0.0f32; n * ch];
            self.s.apply_multi(&src.e, &mut sev, ch);
            add(&mut x, &sev);
            add(&mut x, &src.be);
            src.add_y(&mut x);
        }
        Ok((
            x,
            TransportStats {
                solver: st.method.as_str(),
                iterations: st.iterations,
                products: st.products,
                residual: st.residual,
                converged: st.converged,
                warm: st.warm,
                materials_ms: 0.0,
                device: None,
            },
        ))
    }

    /// (I − K F) x = rhs solved from the answer kept under these materials (or the last
    /// under others), extrapolated along its last step where the one before it is kept:
    /// x, the solve's stats and, from the CPU, its products to keep.
    fn solve_warm(
        &self,
        src: &Sources,
    ) -> Result<(Vec<f32>, SolveStats, Option<Products>), EngineError> {
        let (n, k) = (self.n, self.k);
        let kept = self.scene.warm.history(&self.keys.key, &self.keys.suffix);
        let KeptStart {
            x: warm,
            fx,
            mut kfx,
            age,
        } = kept
            .as_ref()
            .map(|h| KeptStart::of(h, n, k))
            .unwrap_or_default();
        // The answer before it, to extrapolate along the last step.
        let mut before = kept.as_ref().and_then(|h| before_of(h, n, k));
        // How many solves ago the kept products last came out of a pass over F.
        let age = age.max(before.as_ref().map_or(0, |b| b.3));
        let (kop, rhs) = self.rhs(src, &fx, &mut kfx, &mut before, age);
        let primed = fx.as_deref().map(|fx| Primed {
            fx,
            kfx: kfx.as_deref(),
            before: before.as_ref().map(|(x, fx, kfx, _)| Before {
                x,
                fx,
                kfx: kfx.as_deref(),
            }),
            age,
        });
        let on = Solve {
            f: self.f,
            kop,
            k,
            params: self.params,
            device: self.components == Components::Full,
        };
        on.run(self.scene, self.first, &rhs, warm.as_deref(), primed)
    }

    /// K and the right-hand side of (I − K F) x = rhs for the group's components; with
    /// `full` on the CPU, S E and the kept products S F x₀ and S F x₋₁ in one pass over S
    /// where the start needs them (`kfx`, `before`'s, filled in).
    fn rhs<'k>(
        &self,
        src: &Sources,
        fx: &Option<Cow<'k, [f32]>>,
        kfx: &mut Option<Cow<'k, [f32]>>,
        before: &mut Option<Spread<'k>>,
        age: u32,
    ) -> (&dyn Scatter, Vec<f32>) {
        let (s, p, ch) = (self.s, &self.p, self.ch);
        let e = &src.e;
        let mut se = vec![0.0f32; self.n * ch];
        let (kop, mut rhs): (&dyn Scatter, Vec<f32>) = match self.components {
            Components::Full => {
                // A translucency change on the CPU extrapolated along its last step needs S E
                // (for b), S F x₀ and S F x₋₁ under the new S: one pass over S for all three
                // (S is read once, not twice), up to the fixed widths' 8 RGB systems.
                let fuse = self.scene.backend().name() == "cpu"
                    && kfx.is_none()
                    && 3 * ch <= 24
                    && age < MAX_PRIMED_AGE;
                match (fx, before) {
                    (Some(fx0), Some((_, fx1, kfx1 @ None, _))) if fuse => {
                        let [se1, k0, k1]: [Vec<f32>; 3] =
                            crate::linalg::scatter_each(s, &[e, fx0, fx1], ch)
                                .try_into()
                                .expect("one product per vector");
                        se = se1;
                        *kfx = Some(Cow::Owned(k0));
                        *kfx1 = Some(Cow::Owned(k1));
                    }
                    _ => s.apply_multi(e, &mut se, ch),
                }
                add(&mut se, &src.be);
                src.add_y(&mut se);
                (s, se)
            }
            Components::InterreflectionOnly | Components::HeuristicB => {
                p.apply_multi(e, &mut se, ch);
                add(&mut se, &src.be);
                (p, se)
            }
            Components::HeuristicA => {
                s.apply_multi(e, &mut se, ch);
                add(&mut se, &src.be);
                src.add_y(&mut se);
                (p, se)
            }
            Components::Direct | Components::SubsurfaceOnly => unreachable!("routed elsewhere"),
        };
        if self.components == Components::HeuristicB {
            // Y = (I − P F)⁻¹ P F (Bₑ + P E) solves (I − P F) Y = P F (Bₑ + P E).
            let mut fx = vec![0.0f32; self.n * ch];
            self.f
                .apply_multi(&rhs, &mut fx, ch, &mut Pulled::default());
            p.apply_multi(&fx, &mut rhs, ch);
        }
        (kop, rhs)
    }

    /// B += c, c = (I − S F)⁻¹ y for y = Δ E_t + G_u E_u + G_v E_v of F B entering the
    /// simulated objects from where it comes (the full transport only: elsewhere F B reaches
    /// them through P or not at all). Solved to the answer's own tolerance relative to B (c
    /// is a few per cent of it), from the last correction kept (under these materials with
    /// its products, like the answer's: a request made again costs no product); `None`
    /// without simulated objects or such light.
    fn correct(&self, x: &mut [f32]) -> Result<Option<SolveStats>, EngineError> {
        let slant = match self.first.slant.as_deref() {
            Some(TiltOf::Some(t)) if self.components == Components::Full => t,
            _ => return Ok(None),
        };
        let Some((y, scale)) = self.slant_rhs(slant, x) else {
            return Ok(None);
        };
        let (n, k, ch) = (self.n, self.k, self.ch);
        let params = self.params;
        let cparams = SolveParams {
            tolerance: (f64::from(params.tolerance) * scale).clamp(f64::from(params.tolerance), 0.5)
                as f32,
            ..*params
        };
        let kept = self.scene.warm.history(&self.keys.ckey, &self.keys.csuffix);
        let start = kept
            .as_ref()
            .map(|h| KeptStart::of(h, n, k))
            .unwrap_or_default();
        let primed = start.fx.as_deref().map(|fx| Primed {
            fx,
            kfx: start.kfx.as_deref(),
            before: None,
            age: start.age,
        });
        let on = Solve {
            f: self.f,
            kop: self.s,
            k,
            params: &cparams,
            device: true,
        };
        let (c, more, products) = on.run(self.scene, self.first, &y, start.x.as_deref(), primed)?;
        drop(start);
        drop(kept);
        keep(self.scene, self.keys.ckey.clone(), &c, products, n, ch);
        for (x, c) in x.iter_mut().zip(&c) {
            *x += c;
        }
        // Its residual on the answer's scale (relative to B, not to y).
        Ok(Some(SolveStats {
            residual: (f64::from(more.residual) / scale) as f32,
            ..more
        }))
    }

    /// y = Δ E_t + G_u E_u + G_v E_v of F x for the tilt `t`, and the scale from y to x (the
    /// least over the channels of ‖x‖ / ‖y‖); `None` where no channel has such light.
    fn slant_rhs(&self, t: &Tilt, x: &[f32]) -> Option<(Vec<f32>, f64)> {
        let (n, k, ch) = (self.n, self.k, self.ch);
        let mut y = vec![0.0f32; n * ch];
        let weights = self.scene.slant_for(t);
        crate::collimated::add_interreflected_first_scatter(t, &weights, self.f, x, k, &mut y);
        let norms = |v: &[f32]| -> Vec<f64> {
            (0..ch)
                .map(|c| {
                    v.iter()
                        .skip(c)
                        .step_by(ch)
                        .map(|a| f64::from(*a).powi(2))
                        .sum::<f64>()
                        .sqrt()
                })
                .collect()
        };
        let scale = norms(x)
            .iter()
            .zip(norms(&y))
            .filter(|(_, y)| *y > 0.0)
            .map(|(x, y)| x / y)
            .fold(f64::INFINITY, f64::min);
        scale.is_finite().then_some((y, scale))
    }
}

/// A kept answer before the last, spread over the batch: x₋₁, F x₋₁, K F x₋₁ (only under
/// the same materials) and the age of its products.
type Spread<'a> = (Cow<'a, [f32]>, Cow<'a, [f32]>, Option<Cow<'a, [f32]>>, u32);

/// The answer kept before the last one, to extrapolate along the last step; `None` where
/// there is none or its products are too old.
fn before_of(h: &Kept, n: usize, k: usize) -> Option<Spread<'_>> {
    h.before
        .as_ref()
        // Products that old end the chain (the start stays at x₀), so they never hold
        // back x₀'s own: right after a fresh check the next solve still takes them.
        .filter(|(w, _)| w.age < MAX_PRIMED_AGE)
        .and_then(|(w, same)| {
            Some((
                spread(&w.x, n, k)?,
                spread(w.fx.as_ref()?, n, k)?,
                w.kfx
                    .as_ref()
                    .filter(|_| *same)
                    .and_then(|v| spread(v, n, k)),
                w.age,
            ))
        })
}

/// One solve of (I − K F) x = rhs for k stacked RGB systems.
struct Solve<'a> {
    f: &'a Transport<'a>,
    kop: &'a dyn Scatter,
    k: usize,
    params: &'a SolveParams,
    /// K is the materials' S (the full transport): the scene's backend may take it.
    device: bool,
}

/// F x, K F x and their age from a CPU solve ([`keep`]).
type Products = (Vec<f32>, Vec<f32>, u32);

impl Solve<'_> {
    /// On the scene's backend ([`crate::backend`]) when it takes the system, else on the
    /// CPU from `warm` and the kept products `primed`: x, the solve's stats and, from the
    /// CPU, the products to keep.
    fn run(
        &self,
        scene: &Scene,
        first: &Prepared,
        rhs: &[f32],
        warm: Option<&[f32]>,
        primed: Option<Primed<'_>>,
    ) -> Result<(Vec<f32>, SolveStats, Option<Products>), EngineError> {
        let on_device = self
            .device
            .then(|| {
                scene.backend().solve_rhs(
                    scene.view(),
                    first.materials.as_ref(),
                    rhs,
                    self.k,
                    self.params,
                    warm,
                )
            })
            .flatten();
        if let Some((x, st)) = on_device {
            return Ok((x, st, None));
        }
        let s = solve_primed(self.f, self.kop, rhs, 3 * self.k, self.params, warm, primed)
            .map_err(|e| match e {
                SolveError::Overflow => EngineError::invalid(format!("lights: {e}")),
                e => EngineError::internal(e.to_string()),
            })?;
        Ok((s.x, s.stats, Some((s.fx, s.kfx, s.age))))
    }
}

/// A kept answer spread over a batch of k RGB systems: a single relight borrows it as it
/// is, a batch's systems all start from it.
fn spread(w: &[f32], n: usize, k: usize) -> Option<Cow<'_, [f32]>> {
    (w.len() == 3 * n).then(|| match k {
        1 => Cow::Borrowed(w),
        _ => Cow::Owned(
            (0..n)
                .flat_map(|j| {
                    std::iter::repeat_n(&w[3 * j..3 * j + 3], k)
                        .flatten()
                        .copied()
                })
                .collect(),
        ),
    })
}

/// Where a solve starts from the answer kept for its key: x₀, F x₀ (F is the bundle's: it
/// holds under any materials) and K F x₀ (only under the same ones), each spread over the
/// batch, and how many solves ago those products came out of a pass over F.
#[derive(Default)]
struct KeptStart<'a> {
    x: Option<Cow<'a, [f32]>>,
    fx: Option<Cow<'a, [f32]>>,
    kfx: Option<Cow<'a, [f32]>>,
    age: u32,
}

impl<'a> KeptStart<'a> {
    fn of(kept: &'a crate::scene::Kept, n: usize, k: usize) -> Self {
        KeptStart {
            x: spread(&kept.last.x, n, k),
            fx: kept.last.fx.as_ref().and_then(|w| spread(w, n, k)),
            kfx: (kept.same)
                .then_some(kept.last.kfx.as_ref())
                .flatten()
                .and_then(|w| spread(w, n, k)),
            age: kept.last.age,
        }
    }
}

/// Keeps the batch's last system of `x` under `key` for the next solve, with its products
/// F x and K F x when the CPU solved it (`products`); never an answer that is not finite
/// (it would poison the next solve).
fn keep(scene: &Scene, key: String, x: &[f32], products: Option<Products>, n: usize, ch: usize) {
    if !x.iter().all(|v| v.is_finite()) {
        return;
    }
    let last = |v: &[f32]| -> Vec<f32> {
        (0..n)
            .flat_map(|j| v[j * ch + ch - 3..j * ch + ch].iter().copied())
            .collect()
    };
    let (fx, kfx, age) = match &products {
        Some((fx, kfx, age)) => (Some(last(fx)), Some(last(kfx)), *age),
        None => (None, None, 0),
    };
    scene.warm.put(
        key,
        Warm {
            x: last(x),
            fx,
            kfx,
            age,
            prev: None,
        },
    );
}
