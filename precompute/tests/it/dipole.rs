//! The default S against direct integration of the dipole: a sphere, a slab and a cube in
//! skim milk, marble and ketchup, each precomputed with `translux-precompute`'s defaults and
//! relit through the engine at translucency ×1 and, as a slider moves it, ×0.25 and ×4,
//! under a directional light.
//!
//! The reference is written here, independent of the engine's S code: Jensen et al. 2001's
//! dipole from the media's coefficients (their Table 1), integrated over the exact shape
//! (convex: straight-line distances) against the exact irradiance, E₀ max(0, n·l):
//! - on a box, each face's share ∫_face R(|x − y|) dA is a sum of signed wedges, one per
//!   edge, from x's foot on the face's plane at height h: ∫ [G(√(ρ(θ)² + h²)) − G(h)] dθ
//!   with G(s) = ∫₀^s R(u) u du in closed form (d/dD [−e^(−σD)/D] = (1 + σD) e^(−σD)/D²);
//! - on a sphere of radius a, the area within chord r of a point is π r² (Archimedes), so
//!   B(x) = E₀ ∫₀^{2a} R(r) r Φ(r) dr, Φ the irradiance integrated round the circle at
//!   chord r (in closed form: ∫ max(0, p + q cos φ) dφ).
//!
//! Both are integrated adaptively (Gauss–Legendre panels halved until they agree). A
//! patch's reference is the mean of B over the patch (what S's entries integrate), adaptive
//! too, and a vertex's is the area-weighted mean of its patches' (how the engine's vertex
//! colours are made), so what is compared is S alone, not the colours' interpolation.
//!
//! Per vertex and channel, over the vertices whose reference is above 1% of the lit side's
//! peak: the median error ≤ 1% and the 90th percentile ≤ 3%, apart on the lit side, the
//! terminator band (within 1 mm of the boundary between lit and unlit patches) and the
//! dark side, every shape, medium and scale ([`MEDIAN`], [`P90`]).

use std::f64::consts::PI;
use std::path::Path;
use std::process::Command;

use glam::{DVec2, DVec3, Vec3};
use rayon::prelude::*;
use translux_engine::relight;
use translux_engine::scene::Scene;
use translux_proto::api::RelightRequest;
use translux_proto::bundle::Bundle;

/// Jensen, Marschner, Levoy and Hanrahan 2001, Table 1: σs′ and σa (mm⁻¹, R G B); η 1.3
/// for the milk and the ketchup, 1.5 for marble.
const MEDIA: [(&str, [f64; 3], [f64; 3], f64); 3] = [
    (
        "skimmilk",
        [0.70, 1.22, 1.90],
        [0.0014, 0.0025, 0.0142],
        1.3,
    ),
    ("marble", [2.19, 2.62, 3.00], [0.0021, 0.0041, 0.0071], 1.5),
    ("ketchup", [0.18, 0.07, 0.03], [0.061, 0.97, 1.45], 1.3),
];

/// The translucency scales compared: the precompute's ×1, then a slider's ×4 and ×0.25.
const SCALES: [f64; 3] = [1.0, 4.0, 0.25];

/// Width of the terminator band, mm.
const BAND_MM: f64 = 1.0;

/// Where the light comes from (unit vector towards it): off every axis, so no face of a box
/// or ring of the sphere's mesh lines up with the terminator.
fn toward_light() -> DVec3 {
    DVec3::new(0.45, 1.0, 0.3).normalize()
}

/// One channel of the dipole: R(r) = (α′/4π) Σ z (1 + σ D) e^(−σD)/D³, D = √(r² + z²),
/// over the real source z_r = 1/σt′ and the virtual one z_v = z_r (1 + 4A/3).
#[derive(Debug, Clone, Copy)]
struct Channel {
    alpha: f64,
    sigma_tr: f64,
    z: [f64; 2],
}

impl Channel {
    /// Coefficients in mm⁻¹ with their mean free paths stretched by `scale`.
    fn new(sigma_s: f64, sigma_a: f64, eta: f64, scale: f64) -> Self {
        let (ss, sa) = (sigma_s / scale, sigma_a / scale);
        let st = ss + sa;
        // Diffuse Fresnel reflectance (the rational fit of Jensen et al.).
        let fdr = -1.440 / (eta * eta) + 0.710 / eta + 0.668 + 0.0636 * eta;
        let a = (1.0 + fdr) / (1.0 - fdr);
        let zr = 1.0 / st;
        Channel {
            alpha: ss / st,
            sigma_tr: (3.0 * sa * st).sqrt(),
            z: [zr, zr * (1.0 + 4.0 * a / 3.0)],
        }
    }

    fn r(&self, r: f64) -> f64 {
        let s: f64 = self
            .z
            .iter()
            .map(|&z| {
                let d = (r * r + z * z).sqrt();
                z * (1.0 + self.sigma_tr * d) * (-self.sigma_tr * d).exp() / (d * d * d)
            })
            .sum();
        self.alpha / (4.0 * PI) * s
    }

    /// G(s) = ∫₀^s R(u) u du.
    fn g(&self, s: f64) -> f64 {
        let t: f64 = self
            .z
            .iter()
            .map(|&z| {
                let d = (s * s + z * z).sqrt();
                z * ((-self.sigma_tr * z).exp() / z - (-self.sigma_tr * d).exp() / d)
            })
            .sum();
        self.alpha / (4.0 * PI) * t
    }

    /// ∫ R 2πr dr over the plane: the total diffuse reflectance.
    fn total(&self) -> f64 {
        2.0 * PI * self.g(f64::INFINITY)
    }
}

type V3 = [f64; 3];

fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn scale3(a: V3, k: f64) -> V3 {
    a.map(|v| v * k)
}

/// The dipole of one medium, per channel.
#[derive(Debug, Clone, Copy)]
struct Dipole([Channel; 3]);

impl Dipole {
    fn of(medium: usize, scale: f64) -> Self {
        let (_, ss, sa, eta) = MEDIA[medium];
        Dipole(std::array::from_fn(|c| {
            Channel::new(ss[c], sa[c], eta, scale)
        }))
    }
    fn r(&self, r: f64) -> V3 {
        self.0.map(|c| c.r(r))
    }
    fn g(&self, s: f64) -> V3 {
        self.0.map(|c| c.g(s))
    }
    fn total(&self) -> V3 {
        self.0.map(|c| c.total())
    }
}

/// Gauss–Legendre nodes and weights on [−1, 1] (Newton on the Legendre recurrence).
fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
    (0..n)
        .map(|i| {
            let mut x = (PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            let mut dp = 0.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0, x);
                for k in 2..=n {
                    let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-15 {
                    break;
                }
            }
            (x, 2.0 / ((1.0 - x * x) * dp * dp))
        })
        .collect()
}

/// ∫_a^b f, each panel to `tol[c]` (absolute): 8-point Gauss–Legendre panels, halved
/// until both halves agree with their whole (at most 24 times).
fn integrate(f: &dyn Fn(f64) -> V3, a: f64, b: f64, tol: V3, gl: &[(f64, f64)]) -> V3 {
    let panel = |a: f64, b: f64| {
        let (m, h) = (0.5 * (a + b), 0.5 * (b - a));
        gl.iter()
            .fold([0.0; 3], |s, &(x, w)| add(s, scale3(f(m + h * x), w * h)))
    };
    fn go(panel: &dyn Fn(f64, f64) -> V3, a: f64, b: f64, whole: V3, tol: V3, depth: u32) -> V3 {
        let m = 0.5 * (a + b);
        let (l, r) = (panel(a, m), panel(m, b));
        let both = add(l, r);
        // Each panel to the same tolerance (halving it per level could ask for more than
        // f64 rounding allows, and the halving then never ends).
        if depth == 0 || (0..3).all(|c| (both[c] - whole[c]).abs() <= tol[c]) {
            return both;
        }
        add(
            go(panel, a, m, l, tol, depth - 1),
            go(panel, m, b, r, tol, depth - 1),
        )
    }
    if b <= a {
        return [0.0; 3];
    }
    go(&panel, a, b, panel(a, b), tol, 24)
}

/// ∫ over the triangle (x's foot, p1, p2) of R(√(ρ² + h²)), signed by the turn from p1 to
/// p2 (2-D coordinates about the foot): along the edge, s from the perpendicular's foot,
/// ρ² = p² + s² and dθ = p ds / ρ².
fn wedge(d: &Dipole, p1: DVec2, p2: DVec2, h: f64, tol: V3, gl: &[(f64, f64)]) -> V3 {
    let e = p2 - p1;
    let len = e.length();
    let cross = p1.perp_dot(p2);
    if len == 0.0 || cross.abs() <= 1e-12 * len * (p1.length() + p2.length()) {
        return [0.0; 3];
    }
    let p = cross.abs() / len;
    let dir = e / len;
    let (s1, s2) = (p1.dot(dir), p2.dot(dir));
    let gh = d.g(h);
    let f = |s: f64| {
        let rho2 = p * p + s * s;
        let g = d.g((rho2 + h * h).sqrt());
        std::array::from_fn(|c| (g[c] - gh[c]) * p / rho2)
    };
    let sum = if s1 < 0.0 && s2 > 0.0 {
        add(
            integrate(&f, s1, 0.0, tol, gl),
            integrate(&f, 0.0, s2, tol, gl),
        )
    } else {
        integrate(&f, s1, s2, tol, gl)
    };
    scale3(sum, cross.signum())
}

/// The shapes the tests light.
#[derive(Debug, Clone, Copy)]
enum Shape {
    /// Centred at the origin, radius in mm; the reference integrates over the bundle's own
    /// facets (each lit by its own normal, as a renderer lights a mesh), since a smooth
    /// sphere's terminator differs from the facets' by a patch's width, which a sharp
    /// profile shows.
    Sphere(f64),
    /// Centred at the origin, half extents in mm: exact faces.
    Box(DVec3),
}

impl Shape {
    fn mesh_json(&self) -> String {
        match *self {
            Shape::Sphere(a) => format!(r#"{{"shape":"sphere","radius":{a},"segments":48}}"#),
            Shape::Box(h) => format!(
                r#"{{"shape":"box","size":[{},{},{}]}}"#,
                2.0 * h.x,
                2.0 * h.y,
                2.0 * h.z
            ),
        }
    }
}

/// A lit triangle of a mesh: its corners, plane (unit normal n, in-plane basis u, v),
/// area, longest edge and irradiance E₀ n·l.
struct Facet {
    corners: [DVec3; 3],
    centroid: DVec3,
    n: DVec3,
    u: DVec3,
    v: DVec3,
    area: f64,
    size: f64,
    irradiance: f64,
}

/// The facets of a convex mesh centred at `centre` that face `l`, with normals made here
/// from the corners (pointing away from the centre).
fn lit_facets(corners: &[[DVec3; 3]], centre: DVec3, l: DVec3) -> Vec<Facet> {
    corners
        .iter()
        .filter_map(|&c| {
            let cross = (c[1] - c[0]).cross(c[2] - c[0]);
            let centroid = (c[0] + c[1] + c[2]) / 3.0;
            let mut n = cross.normalize();
            if n.dot(centroid - centre) < 0.0 {
                n = -n;
            }
            let irradiance = n.dot(l);
            (irradiance > 0.0).then(|| {
                let u = (c[1] - c[0]).normalize();
                Facet {
                    corners: c,
                    centroid,
                    n,
                    u,
                    v: n.cross(u),
                    area: 0.5 * cross.length(),
                    size: [c[1] - c[0], c[2] - c[1], c[0] - c[2]]
                        .iter()
                        .map(|e| e.length())
                        .fold(0.0, f64::max),
                    irradiance,
                }
            })
        })
        .collect()
}

/// B(x) over lit facets: exact wedges for facets within 4 of their sizes of x, Dunavant's
/// degree-5 rule beyond (there R varies little across a facet).
fn facet_exitance(d: &Dipole, facets: &[Facet], x: DVec3, tol: V3, gl: &[(f64, f64)]) -> V3 {
    facets.iter().fold([0.0; 3], |sum, f| {
        let part = if x.distance(f.centroid) > 4.0 * f.size {
            DUNAVANT7.iter().fold([0.0; 3], |s, (b, w)| {
                let y = f.corners[0] * b[0] + f.corners[1] * b[1] + f.corners[2] * b[2];
                add(s, scale3(d.r(x.distance(y)), w * f.area))
            })
        } else {
            let h = (x - f.corners[0]).dot(f.n);
            let foot = x - f.n * h;
            let p = f
                .corners
                .map(|c| DVec2::new((c - foot).dot(f.u), (c - foot).dot(f.v)));
            (0..3)
                .fold([0.0; 3], |s, i| {
                    add(s, wedge(d, p[i], p[(i + 1) % 3], h.abs(), tol, gl))
                })
                .map(f64::abs)
        };
        add(sum, scale3(part, f.irradiance))
    })
}

/// Exitance B(x) under unit irradiance from `l` at a point of a smooth sphere of radius `a`
/// (x is moved onto it along its radius), per channel: the check of [`facet_exitance`].
fn sphere_exitance(d: &Dipole, a: f64, x: DVec3, l: DVec3, tol: V3, gl: &[(f64, f64)]) -> V3 {
    let n = x.normalize();
    let cos_alpha = n.dot(l).clamp(-1.0, 1.0);
    let (sin_alpha, alpha) = ((1.0 - cos_alpha * cos_alpha).sqrt(), cos_alpha.acos());
    // The irradiance round the circle at polar angle γ from x: ∫ max(0, p + q cos φ) dφ.
    let phi = |gamma: f64| {
        let (p, q) = (gamma.cos() * cos_alpha, gamma.sin() * sin_alpha);
        if p >= q {
            2.0 * PI * p
        } else if p <= -q {
            0.0
        } else {
            2.0 * (p * (PI - (p / q).acos()) + (q * q - p * p).sqrt())
        }
    };
    let chord = |gamma: f64| 2.0 * a * (0.5 * gamma).sin();
    let f = |r: f64| {
        let gamma = 2.0 * (r / (2.0 * a)).clamp(-1.0, 1.0).asin();
        scale3(d.r(r), r * phi(gamma))
    };
    // Panels broken where Φ changes form (γ = |π/2 ± α|) and graded towards r = 0.
    let mut cuts = vec![0.0, 2.0 * a];
    for g in [(0.5 * PI - alpha).abs(), 0.5 * PI + alpha, 1.5 * PI - alpha] {
        if g > 0.0 && g < PI {
            cuts.push(chord(g));
        }
    }
    let zr = d.0.iter().map(|c| c.z[0]).fold(f64::INFINITY, f64::min);
    let mut r = 0.25 * zr;
    while r < 2.0 * a {
        cuts.push(r);
        r *= 2.0;
    }
    cuts.sort_by(f64::total_cmp);
    cuts.windows(2)
        .fold([0.0; 3], |s, w| add(s, integrate(&f, w[0], w[1], tol, gl)))
}

/// Exitance B(x) under unit irradiance from `l` on a box of half extents `h`: each face's
/// wedges, weighed by the face's irradiance.
fn box_exitance(d: &Dipole, h: DVec3, x: DVec3, l: DVec3, tol: V3, gl: &[(f64, f64)]) -> V3 {
    let mut sum = [0.0; 3];
    for k in 0..3 {
        for sign in [-1.0, 1.0] {
            let mut n = DVec3::ZERO;
            n[k] = sign;
            let e = n.dot(l);
            if e <= 0.0 {
                continue;
            }
            let (k1, k2) = ((k + 1) % 3, (k + 2) % 3);
            let height = (x[k] - sign * h[k]).abs();
            let corner = |s1: f64, s2: f64| DVec2::new(s1 * h[k1] - x[k1], s2 * h[k2] - x[k2]);
            let poly = [
                corner(-1.0, -1.0),
                corner(1.0, -1.0),
                corner(1.0, 1.0),
                corner(-1.0, 1.0),
            ];
            let face = (0..4).fold([0.0; 3], |s, i| {
                add(s, wedge(d, poly[i], poly[(i + 1) % 4], height, tol, gl))
            });
            sum = add(sum, scale3(face.map(f64::abs), e));
        }
    }
    sum
}

/// Dunavant's 7-point rule (degree 5) on a triangle: barycentric points and weights.
const DUNAVANT7: [([f64; 3], f64); 7] = [
    ([1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0], 0.225),
    (
        [0.059715871789770, 0.470142064105115, 0.470142064105115],
        0.132394152788506,
    ),
    (
        [0.470142064105115, 0.059715871789770, 0.470142064105115],
        0.132394152788506,
    ),
    (
        [0.470142064105115, 0.470142064105115, 0.059715871789770],
        0.132394152788506,
    ),
    (
        [0.797426985353087, 0.101286507302466, 0.101286507302466],
        0.125939180544827,
    ),
    (
        [0.101286507302466, 0.797426985353087, 0.101286507302466],
        0.125939180544827,
    ),
    (
        [0.101286507302466, 0.101286507302466, 0.797426985353087],
        0.125939180544827,
    ),
];

/// The weight of each of [`DUNAVANT7`]'s outer three points (barycentric 0.797, 0.101,
/// 0.101) in a degree-2 rule on them and the centroid (which takes 1 − 3w): the embedded
/// lower-order rule [`triangle_mean`] compares with, at no extra evaluation (w from the
/// mean of λ₁² over a triangle, 1/6).
const EMBEDDED2: f64 = 0.171959027245884;

/// The mean of `f` over a triangle: Dunavant's degree-5 rule where the degree-2 rule on
/// four of its points ([`EMBEDDED2`]) agrees with it to `tol` plus 2·10⁻³ of the value (the
/// degree-5 rule is then far closer), else the mean of the four midpoint children's.
fn triangle_mean(f: &dyn Fn(DVec3) -> V3, t: [DVec3; 3], tol: V3, depth: u32) -> V3 {
    let at = |b: &[f64; 3]| f(t[0] * b[0] + t[1] * b[1] + t[2] * b[2]);
    let vals: Vec<V3> = DUNAVANT7.iter().map(|(b, _)| at(b)).collect();
    let fine = DUNAVANT7
        .iter()
        .zip(&vals)
        .fold([0.0; 3], |s, ((_, w), v)| add(s, scale3(*v, *w)));
    // The degree-2 rule on the same points: the centroid and the outer orbit.
    let coarse = add(
        scale3(vals[0], 1.0 - 3.0 * EMBEDDED2),
        scale3(add(add(vals[4], vals[5]), vals[6]), EMBEDDED2),
    );
    if depth == 0 || (0..3).all(|c| (fine[c] - coarse[c]).abs() <= tol[c] + 2e-3 * fine[c].abs()) {
        return fine;
    }
    let (a, b, c) = (
        (t[0] + t[1]) * 0.5,
        (t[1] + t[2]) * 0.5,
        (t[2] + t[0]) * 0.5,
    );
    [[t[0], a, c], [a, t[1], b], [c, b, t[2]], [a, b, c]]
        .iter()
        .fold([0.0; 3], |s, &k| {
            add(s, scale3(triangle_mean(f, k, tol, depth - 1), 0.25))
        })
}

/// Where a vertex stands against the light.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Side {
    Lit,
    Band,
    Dark,
}

const SIDES: [(Side, &str); 3] = [
    (Side::Lit, "lit"),
    (Side::Band, "terminator"),
    (Side::Dark, "dark"),
];

/// Each vertex's side: lit when one of its patches faces the light; in the band when a
/// vertex of the other kind lies within [`BAND_MM`].
fn sides(b: &Bundle, l: DVec3) -> Vec<Side> {
    let pos = b.vertex_positions();
    let mut lit = vec![false; pos.len()];
    for (t, n) in b.triangle_vertices().iter().zip(b.patch_normals()) {
        if Vec3::from(*n).as_dvec3().dot(l) > 0.0 {
            for &v in t {
                lit[v as usize] = true;
            }
        }
    }
    let p: Vec<DVec3> = pos.iter().map(|&p| Vec3::from(p).as_dvec3()).collect();
    (0..p.len())
        .into_par_iter()
        .map(|v| {
            let near = (0..p.len()).any(|u| lit[u] != lit[v] && p[u].distance(p[v]) < BAND_MM);
            match (near, lit[v]) {
                (true, _) => Side::Band,
                (false, true) => Side::Lit,
                (false, false) => Side::Dark,
            }
        })
        .collect()
}

/// Where [`stored_reference`] keeps the references, in the repository.
const STORE: &str = "tests/references/dipole";

/// [`reference`], read from [`STORE`] when it was computed for exactly this input, else
/// computed and written there (stderr asks for the file to be committed): the integration
/// is most of these tests' time, and its answer is a function of its input alone. A file is
/// named by the SHA-256 of this source file (the integrator, the media and the bounds), the
/// bundle's mesh (patch corners and areas, the vertices' triangles), the shape, the dipole
/// and the light, so any change to them names a new one and no stale answer is read.
/// `TRANSLUX_DIPOLE_INTEGRATE=1` integrates every one again and replaces the stored file.
/// The integrator is checked against closed forms on every run
/// (`the_reference_integrator_meets_closed_forms`).
fn stored_reference(b: &Bundle, shape: Shape, d: &Dipole, l: DVec3) -> Vec<V3> {
    let path = store_path(b, shape, d, l);
    let n = b.vertex_positions().len();
    let fresh = std::env::var("TRANSLUX_DIPOLE_INTEGRATE").as_deref() == Ok("1");
    if !fresh && let Ok(text) = std::fs::read_to_string(&path) {
        let stored: Vec<[f64; 3]> = serde_json::from_str(&text)
            .unwrap_or_else(|e| panic!("{}: not a stored reference: {e}", path.display()));
        assert_eq!(stored.len(), n, "{}: one value per vertex", path.display());
        return stored;
    }
    let reference = reference(b, shape, d, l);
    // Single precision: the references agree with ten times tighter tolerances to 0.15%
    // (see `reference`), far coarser than f32's rounding; a third of the file's size.
    let rounded: Vec<[f32; 3]> = reference.iter().map(|v| v.map(|x| x as f32)).collect();
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(&path, serde_json::to_string(&rounded).unwrap()).unwrap();
    eprintln!(
        "dipole reference integrated; stored as {} (commit it: CI reads it instead of \
         integrating)",
        path.display()
    );
    rounded.iter().map(|v| v.map(f64::from)).collect()
}

/// The store's file for one reference (see [`stored_reference`]).
fn store_path(b: &Bundle, shape: Shape, d: &Dipole, l: DVec3) -> std::path::PathBuf {
    use sha2::{Digest, Sha256};
    let mut h = Sha256::new();
    h.update(include_bytes!("dipole.rs"));
    h.update(bytemuck::cast_slice::<_, u8>(b.patch_corners()));
    h.update(bytemuck::cast_slice::<_, u8>(b.patch_areas()));
    h.update(bytemuck::cast_slice::<_, u8>(b.triangle_vertices()));
    h.update((b.vertex_positions().len() as u64).to_le_bytes());
    h.update(format!("{shape:?} {d:?} {l:?}").as_bytes());
    let hex: String = h.finalize()[..16]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join(STORE)
        .join(format!("{hex}.json"))
}

/// The reference vertex radiance (B/π) of the bundle's mesh on `shape` in `d`.
fn reference(b: &Bundle, shape: Shape, d: &Dipole, l: DVec3) -> Vec<V3> {
    let gl = gauss_legendre(8);
    // Tolerances far below the checked 1% of 1% of the peak (the peak is about the total
    // reflectance under unit irradiance): against ten times tighter ones and a separate
    // degree-2 rule (Strang's three points), the references differ by at most 0.15% per
    // vertex (the slab at ×0.25; the sphere 0.03%) and take 20–45% longer.
    let total = d.total();
    let tol_point = total.map(|t| 1e-7 * t);
    let tol_patch = total.map(|t| 1e-5 * t);
    let corners: Vec<[DVec3; 3]> = b
        .patch_corners()
        .iter()
        .map(|c| c.map(|p| Vec3::from(p).as_dvec3()))
        .collect();
    let facets = match shape {
        Shape::Sphere(_) => lit_facets(&corners, DVec3::ZERO, l),
        Shape::Box(_) => Vec::new(),
    };
    let exitance = |x: DVec3| match shape {
        Shape::Sphere(_) => facet_exitance(d, &facets, x, tol_point, &gl),
        Shape::Box(h) => box_exitance(d, h, x, l, tol_point, &gl),
    };
    let patch: Vec<V3> = corners
        .par_iter()
        .map(|&t| triangle_mean(&exitance, t, tol_patch, 3))
        .collect();
    let mut sum = vec![[0.0f64; 3]; b.vertex_positions().len()];
    let mut weight = vec![0.0f64; sum.len()];
    for ((t, &a), v) in b
        .triangle_vertices()
        .iter()
        .zip(b.patch_areas())
        .zip(&patch)
    {
        for &k in t {
            sum[k as usize] = add(sum[k as usize], scale3(*v, a as f64));
            weight[k as usize] += a as f64;
        }
    }
    sum.iter()
        .zip(&weight)
        .map(|(s, &w)| scale3(*s, if w > 0.0 { 1.0 / (w * PI) } else { 0.0 }))
        .collect()
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// One comparison's figures on one side: vertices, median and p90 of the error over every
/// channel, and the median ratio (ours / reference) per channel.
struct Figures {
    count: usize,
    median: f64,
    p90: f64,
    ratio: V3,
}

fn figures(ours: &[[f32; 3]], reference: &[V3], side: &[Side], want: Side) -> Figures {
    let peak: V3 = std::array::from_fn(|c| {
        (0..reference.len())
            .filter(|&v| side[v] == Side::Lit)
            .map(|v| reference[v][c])
            .fold(0.0, f64::max)
    });
    let mut errors = Vec::new();
    let mut ratios: [Vec<f64>; 3] = Default::default();
    for v in (0..reference.len()).filter(|&v| side[v] == want) {
        for c in 0..3 {
            let r = reference[v][c];
            if r > 0.01 * peak[c] {
                let q = ours[v][c] as f64 / r;
                errors.push((q - 1.0).abs());
                ratios[c].push(q);
            }
        }
    }
    Figures {
        count: errors.len(),
        median: percentile(&mut errors.clone(), 0.5),
        p90: percentile(&mut errors, 0.9),
        ratio: std::array::from_fn(|c| percentile(&mut ratios[c], 0.5)),
    }
}

/// Precomputes `shape` in each medium with the CLI's defaults, relights it at each scale
/// and compares every side with the reference; prints a table and fails on any bound
/// missed (after printing all of them).
fn check(name: &str, shape: Shape, patches: u32) {
    let l = toward_light();
    let mut failed = Vec::new();
    eprintln!(
        "{name}: medium ×scale side: vertex-channels, median / p90 error, median ratio R G B"
    );
    for (m, (medium, ..)) in MEDIA.iter().enumerate() {
        let dir = tempfile::tempdir().unwrap();
        let scene = dir.path().join("scene.json");
        std::fs::write(
            &scene,
            format!(
                r#"{{"unit_mm": 1,
                  "objects":[{{"name":"object","mesh":{mesh},
                    "material":{{"type":"translucent",
                                 "profile":{{"type":"dipole","preset":"{medium}"}}}}}}],
                  "lights":[{{"type":"directional","direction":[{},{},{}],
                              "irradiance":[1,1,1]}}],
                  "patches":{{"target":{patches}}}}}"#,
                -l.x,
                -l.y,
                -l.z,
                mesh = shape.mesh_json(),
            ),
        )
        .unwrap();
        let out = dir.path().join("bundle");
        let t = std::time::Instant::now();
        precompute(&scene, &out);
        let precompute_s = t.elapsed().as_secs_f64();
        let bundle = Bundle::open(&out).unwrap();
        let manifest = bundle.manifest();
        let n = manifest.patch_count as f64;
        let o = &manifest.subsurface.objects[0];
        eprintln!(
            "{name}: {medium}: {} patches, S {:.0} entries per patch ({:.0} links), \
             precompute {precompute_s:.1} s",
            manifest.patch_count,
            o.entries as f64 / n,
            o.links as f64 / n
        );
        let side = sides(&bundle, l);
        let scene = Scene::open("object", &out).unwrap();
        for scale in SCALES {
            let d = Dipole::of(m, scale);
            let t = std::time::Instant::now();
            let reference = stored_reference(&bundle, shape, &d, l);
            let reference_s = t.elapsed().as_secs_f64();
            let ours = relight_at(&scene, medium, scale, l);
            eprintln!("{name}: {medium} ×{scale}: reference {reference_s:.1} s");
            for (want, label) in SIDES {
                let f = figures(&ours, &reference, &side, want);
                let line = format!(
                    "{name}: {medium} ×{scale} {label}: {}, {:.2}% / {:.2}%, {:.3} {:.3} {:.3}",
                    f.count,
                    100.0 * f.median,
                    100.0 * f.p90,
                    f.ratio[0],
                    f.ratio[1],
                    f.ratio[2]
                );
                eprintln!("{line}");
                if f.median > MEDIAN || f.p90 > P90 {
                    failed.push(line);
                }
            }
        }
    }
    assert!(
        failed.is_empty(),
        "against the dipole's direct integration (median ≤ 1%, p90 ≤ 3%):\n{}",
        failed.join("\n")
    );
}

/// The bound on one side's median error.
const MEDIAN: f64 = 0.01;
/// The bound on one side's 90th-percentile error.
const P90: f64 = 0.03;

/// `translux-precompute SCENE --out OUT` with its defaults (progress off).
fn precompute(scene: &Path, out: &Path) {
    let run = Command::new(env!("CARGO_BIN_EXE_translux-precompute"))
        .arg(scene)
        .arg("--out")
        .arg(out)
        .arg("--quiet")
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "translux-precompute failed: {}",
        String::from_utf8_lossy(&run.stderr)
    );
}

/// Vertex radiance of a relight request with the light of the scene and, away from ×1, the
/// object's medium at translucency ×`scale` (a slider's override, written in place).
fn relight_at(scene: &Scene, medium: &str, scale: f64, l: DVec3) -> Vec<[f32; 3]> {
    let mut req = serde_json::json!({
        "lights": [{"type":"directional","direction":[-l.x, -l.y, -l.z],"irradiance":[1,1,1]}],
    });
    if scale != 1.0 {
        req["materials"] = serde_json::json!({"object": {
            "type": "translucent",
            "profile": {"type": "dipole", "preset": medium, "scale": scale},
        }});
    }
    let req: RelightRequest = serde_json::from_value(req).unwrap();
    let plan = relight::plan(scene, req).unwrap();
    relight::run(scene, &plan).unwrap().radiance
}

#[test]
fn a_lit_sphere_matches_the_integrated_dipole() {
    check("sphere 5 mm", Shape::Sphere(5.0), 2000);
}

#[test]
fn a_lit_slab_matches_the_integrated_dipole() {
    check(
        "slab 20 × 4 × 20 mm",
        Shape::Box(DVec3::new(10.0, 2.0, 10.0)),
        3000,
    );
}

#[test]
fn a_lit_cube_matches_the_integrated_dipole() {
    check("cube 10 mm", Shape::Box(DVec3::splat(5.0)), 3000);
}

#[test]
fn the_reference_integrator_meets_closed_forms() {
    // The plane's total reflectance: a disc of radius ρ from its centre is 2π G(ρ), which
    // the wedges of a large square about the point must give, and a sphere's flat limit.
    let d = Dipole::of(0, 1.0);
    let gl = gauss_legendre(8);
    let tol = [1e-12; 3];
    let big = 1e4;
    let square = [
        DVec2::new(-big, -big),
        DVec2::new(big, -big),
        DVec2::new(big, big),
        DVec2::new(-big, big),
    ];
    let sum = (0..4).fold([0.0; 3], |s, i| {
        add(s, wedge(&d, square[i], square[(i + 1) % 4], 0.0, tol, &gl))
    });
    let total = d.total();
    for c in 0..3 {
        assert!(
            (sum[c] - total[c]).abs() < 1e-6 * total[c],
            "channel {c}: {} against {}",
            sum[c],
            total[c]
        );
    }
    // Half-plane: a point on the edge of a huge square sees half the total.
    let edge = square.map(|p| p + DVec2::new(big, 0.0));
    let half = (0..4).fold([0.0; 3], |s, i| {
        add(s, wedge(&d, edge[i], edge[(i + 1) % 4], 0.0, tol, &gl))
    });
    for c in 0..3 {
        assert!((half[c].abs() - 0.5 * total[c]).abs() < 1e-6 * total[c]);
    }
    // Total reflectance against the closed form (α′/2)(1 + e^(−(4/3)A√(3(1−α′)))) e^(−√(3(1−α′))).
    let (_, ss, sa, eta) = MEDIA[0];
    for c in 0..3 {
        let alpha = ss[c] / (ss[c] + sa[c]);
        let fdr = -1.440 / (eta * eta) + 0.710 / eta + 0.668 + 0.0636 * eta;
        let a = (1.0 + fdr) / (1.0 - fdr);
        let s = (3.0 * (1.0 - alpha)).sqrt();
        let rd = 0.5 * alpha * (1.0 + (-(4.0 / 3.0) * a * s).exp()) * (-s).exp();
        assert!((total[c] - rd).abs() < 1e-9, "{} against {rd}", total[c]);
    }
    // A huge sphere under light straight on: the pole sees the plane's total reflectance.
    let a = 1e4;
    let pole = sphere_exitance(&d, a, DVec3::new(0.0, a, 0.0), DVec3::Y, [1e-10; 3], &gl);
    for c in 0..3 {
        assert!(
            (pole[c] - total[c]).abs() < 1e-4 * total[c],
            "channel {c}: the pole of a huge sphere gives {} against {}",
            pole[c],
            total[c]
        );
    }
    // A sphere's facets (96 × 48) against the smooth sphere, away from the terminator.
    let (a, l) = (5.0, DVec3::Y);
    let (nu, nv) = (96usize, 48usize);
    let point = |i: usize, k: usize| {
        let (phi, theta) = (2.0 * PI * i as f64 / nu as f64, PI * k as f64 / nv as f64);
        DVec3::new(
            theta.sin() * phi.cos(),
            theta.cos(),
            theta.sin() * phi.sin(),
        ) * a
    };
    let mut tris = Vec::new();
    for k in 0..nv {
        for i in 0..nu {
            let (p00, p10, p01, p11) = (
                point(i, k),
                point(i + 1, k),
                point(i, k + 1),
                point(i + 1, k + 1),
            );
            if k > 0 {
                tris.push([p00, p10, p11]);
            }
            if k + 1 < nv {
                tris.push([p00, p11, p01]);
            }
        }
    }
    let facets = lit_facets(&tris, DVec3::ZERO, l);
    let marble = Dipole::of(1, 1.0);
    for polar in [0.3f64, 1.0, 2.2, 2.9] {
        let x = DVec3::new(polar.sin(), polar.cos(), 0.0) * a;
        let smooth = sphere_exitance(&marble, a, x, l, [1e-10; 3], &gl);
        // The facet's own point under x (x lies on a facet's corner ring otherwise).
        let flat = facet_exitance(
            &marble,
            &facets,
            x * (PI / nu as f64).cos(),
            [1e-10; 3],
            &gl,
        );
        for c in 0..3 {
            assert!(
                (flat[c] / smooth[c] - 1.0).abs() < 5e-3,
                "polar {polar} channel {c}: facets {} against the sphere's {}",
                flat[c],
                smooth[c]
            );
        }
    }
    // The wedge sum on a face against brute force (a fine midpoint grid) from a point
    // above a small square.
    let h = 0.7;
    let sq = [
        DVec2::new(-0.3, -0.9),
        DVec2::new(1.7, -0.9),
        DVec2::new(1.7, 1.1),
        DVec2::new(-0.3, 1.1),
    ];
    let exact = (0..4).fold([0.0; 3], |s, i| {
        add(s, wedge(&d, sq[i], sq[(i + 1) % 4], h, [1e-12; 3], &gl))
    });
    let k = 800;
    let mut brute = [0.0; 3];
    for i in 0..k {
        for j in 0..k {
            let u = -0.3 + 2.0 * (i as f64 + 0.5) / k as f64;
            let v = -0.9 + 2.0 * (j as f64 + 0.5) / k as f64;
            let r = (u * u + v * v + h * h).sqrt();
            brute = add(brute, scale3(d.r(r), 4.0 / (k * k) as f64));
        }
    }
    for c in 0..3 {
        assert!(
            (exact[c] - brute[c]).abs() < 1e-4 * brute[c],
            "channel {c}: wedges {} against a grid's {}",
            exact[c],
            brute[c]
        );
    }
}
