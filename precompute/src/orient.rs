//! Which way a mesh's faces point: finding the parts wound inside out, and turning only
//! those that provably are.
//!
//! In: an object's triangles (scene units), its [`Orientation`] mode, and *witness* points
//! that lie inside the scene's rooms if there are any (light positions, the camera, points
//! on the other objects). Out: the triangles with some connected parts' winding reversed,
//! and an [`OrientReport`] saying what was turned over and why.
//!
//! The test is per connected part (triangles that share a corner position). A part's
//! outside is decided by the generalised winding number w(p) = Σ Ω_t(p) / 4π (Jacobson,
//! Kavan & Sorkine-Hornung 2013): for a closed surface wound outward it is 1 inside and 0
//! outside. At points just in front of (p⁺) and just behind (p⁻) sampled faces,
//! w(p⁺) + w(p⁻) is +1 for a closed part wound outward, −1 for one wound inward and near
//! 0 for an open surface (a flat wall gives −½ + ½). The score is that sum averaged over
//! faces sampled by area. A part counts as closed only when the score says so *and* its
//! open border is short against its size, so a half-sphere or a petal (score about 0.6)
//! is never turned over. The signed volume is not used: for an open surface it depends only
//! on where the scene's origin is.
//!
//! Written by hand: the winding-number sum is a few lines, and no maintained crate offers
//! it over a triangle soup without a mesh-data-structure dependency.

use std::collections::HashMap;

use glam::{DVec3, Vec3};
use rayon::prelude::*;
use translux_proto::scene::Orientation;

/// |score| at or above this: the sampled faces separate an inside from an outside.
const CLOSED_SCORE: f64 = 0.8;
/// A part whose open border length L and area A have L² / (4π A) above this is open. A
/// sphere with one round hole of radius r passes while r < 0.45 R; a half-sphere is 0.5,
/// a square 1.27.
const MAX_BORDER_RATIO: f64 = 0.05;
/// Faces sampled per part for the score.
const SAMPLES: usize = 48;
/// |w| at a witness point at or above this: the part encloses it (a point on the surface
/// itself gives ½).
const ENCLOSES: f64 = 0.75;

/// How one connected part of a mesh was classified.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PartKind {
    /// Closed, wound outward.
    ClosedOutward,
    /// Closed, wound inward.
    ClosedInward,
    /// Open (or with too large a hole): has no inside; never turned over.
    Open,
}

/// What [`orient`] found and did for one object.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct OrientReport {
    /// Connected parts.
    pub parts: usize,
    /// Parts that are open surfaces.
    pub open_parts: usize,
    /// Parts whose faces were reversed.
    pub flipped_parts: usize,
    /// Triangles whose winding was reversed.
    pub flipped_triangles: usize,
    /// Closed parts wound inward that `auto` kept because they enclose a witness (rooms).
    pub kept_enclosures: usize,
    /// One line per decision worth telling the user (empty when nothing was decided).
    pub notes: Vec<String>,
}

/// One connected part's triangles and its classification.
struct Part {
    triangles: Vec<usize>,
    kind: PartKind,
    score: f64,
    border_ratio: f64,
}

/// Reorients `triangles` in place according to `mode`. `witnesses` are points that, if a
/// closed inward-wound part encloses one, make it a room (only used by `auto`).
pub fn orient(triangles: &mut [[Vec3; 3]], mode: Orientation, witnesses: &[Vec3]) -> OrientReport {
    let mut report = OrientReport::default();
    if mode == Orientation::AsIs || triangles.is_empty() {
        return report;
    }
    let parts = classify(triangles);
    report.parts = parts.len();
    // A point on each part: a part inside another one (furniture in a one-mesh room) is a
    // witness for it.
    let own: Vec<Vec3> = parts
        .iter()
        .map(|p| {
            let [a, b, c] = triangles[p.triangles[0]];
            (a + b + c) / 3.0
        })
        .collect();
    for (k, part) in parts.iter().enumerate() {
        let flip = match (mode, part.kind) {
            (_, PartKind::Open) => {
                report.open_parts += 1;
                false
            }
            (Orientation::Outward, k) => k == PartKind::ClosedInward,
            (Orientation::Inward, k) => k == PartKind::ClosedOutward,
            (Orientation::Auto, PartKind::ClosedInward) => {
                let others = own
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| *j != k)
                    .map(|(_, p)| *p);
                let all: Vec<Vec3> = witnesses.iter().copied().chain(others.take(64)).collect();
                match enclosed_witness(triangles, &part.triangles, &all) {
                    Some(w) => {
                        report.kept_enclosures += 1;
                        report.notes.push(format!(
                            "a closed part of {} faces is wound inward and encloses {}: kept \
                             facing inward, as a room seen from inside (\"orientation\": \
                             \"outward\" turns it over)",
                            part.triangles.len(),
                            describe_point(w)
                        ));
                        false
                    }
                    None => true,
                }
            }
            (Orientation::Auto, PartKind::ClosedOutward) => false,
            (Orientation::AsIs, _) => unreachable!("returned above"),
        };
        if flip {
            for &t in &part.triangles {
                triangles[t].swap(1, 2);
            }
            report.flipped_parts += 1;
            report.flipped_triangles += part.triangles.len();
            let why = match mode {
                Orientation::Inward => "\"orientation\": \"inward\"",
                Orientation::Outward => "\"orientation\": \"outward\"",
                _ => "it encloses nothing of the scene",
            };
            let (to, from) = if part.kind == PartKind::ClosedInward {
                ("outward", "inside out")
            } else {
                ("inward", "outward")
            };
            report.notes.push(format!(
                "a closed part of {} faces was wound {from} (winding number {:+.2} just off \
                 its faces, open border {:.3}); flipped to face {to} ({why})",
                part.triangles.len(),
                part.score,
                part.border_ratio,
            ));
        }
    }
    if report.open_parts > 0 && mode != Orientation::Auto {
        report.notes.push(format!(
            "{} of {} parts are open surfaces with no inside; kept as the file winds them",
            report.open_parts, report.parts
        ));
    }
    report
}

/// A point a note can name.
fn describe_point(p: Vec3) -> String {
    format!("the point ({:.3}, {:.3}, {:.3})", p.x, p.y, p.z)
}

/// Splits `tris` into connected parts (sharing a corner position) and classifies each.
fn classify(tris: &[[Vec3; 3]]) -> Vec<Part> {
    // Weld corners by exact position: OBJ faces that share a vertex share its coordinates
    // bit for bit, also after the transform.
    let mut ids: HashMap<[u32; 3], u32> = HashMap::new();
    let corners: Vec<[u32; 3]> = tris
        .iter()
        .map(|t| {
            t.map(|v| {
                let key = [v.x, v.y, v.z].map(|c| (c + 0.0).to_bits());
                let n = ids.len() as u32;
                *ids.entry(key).or_insert(n)
            })
        })
        .collect();
    let mut parent: Vec<u32> = (0..ids.len() as u32).collect();
    fn find(parent: &mut [u32], mut x: u32) -> u32 {
        while parent[x as usize] != x {
            parent[x as usize] = parent[parent[x as usize] as usize];
            x = parent[x as usize];
        }
        x
    }
    for c in &corners {
        let a = find(&mut parent, c[0]);
        for &v in &c[1..] {
            let b = find(&mut parent, v);
            if a != b {
                parent[b as usize] = a;
            }
        }
    }
    let mut by_root: HashMap<u32, Vec<usize>> = HashMap::new();
    for (t, c) in corners.iter().enumerate() {
        let r = find(&mut parent, c[0]);
        by_root.entry(r).or_default().push(t);
    }
    let mut groups: Vec<Vec<usize>> = by_root.into_values().collect();
    groups.sort_by_key(|g| g[0]);
    groups
        .into_par_iter()
        .map(|g| classify_part(tris, &corners, g))
        .collect()
}

fn classify_part(tris: &[[Vec3; 3]], corners: &[[u32; 3]], part: Vec<usize>) -> Part {
    // Border: edges used by one face only.
    let mut edges: HashMap<(u32, u32), (u32, f64)> = HashMap::new();
    let mut area = 0.0;
    for &t in &part {
        let [a, b, c] = tris[t].map(|v| v.as_dvec3());
        area += 0.5 * (b - a).cross(c - a).length();
        for k in 0..3 {
            let (i, j) = (corners[t][k], corners[t][(k + 1) % 3]);
            let len = (tris[t][k] - tris[t][(k + 1) % 3]).as_dvec3().length();
            edges.entry((i.min(j), i.max(j))).or_insert((0, len)).0 += 1;
        }
    }
    let border: f64 = edges
        .values()
        .filter(|(n, _)| *n == 1)
        .map(|(_, l)| l)
        .sum();
    let border_ratio = if area > 0.0 {
        border * border / (4.0 * std::f64::consts::PI * area)
    } else {
        f64::INFINITY
    };
    let score = if border_ratio > MAX_BORDER_RATIO {
        0.0
    } else {
        side_score(tris, &part, area)
    };
    let kind = if border_ratio > MAX_BORDER_RATIO || score.abs() < CLOSED_SCORE {
        PartKind::Open
    } else if score > 0.0 {
        PartKind::ClosedOutward
    } else {
        PartKind::ClosedInward
    };
    Part {
        triangles: part,
        kind,
        score,
        border_ratio,
    }
}

/// Mean of w(p⁺) + w(p⁻) over up to [`SAMPLES`] faces chosen by area (stratified), p± a
/// short step in front of and behind each face's centroid.
fn side_score(tris: &[[Vec3; 3]], part: &[usize], area: f64) -> f64 {
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for &t in part {
        for v in tris[t] {
            lo = lo.min(v.as_dvec3());
            hi = hi.max(v.as_dvec3());
        }
    }
    let diagonal = (hi - lo).length();
    let n = SAMPLES.min(part.len());
    let mut picks = Vec::with_capacity(n);
    let mut cumulative = 0.0;
    let mut next = 0;
    for &t in part {
        let [a, b, c] = tris[t].map(|v| v.as_dvec3());
        cumulative += 0.5 * (b - a).cross(c - a).length();
        while next < n && cumulative >= (next as f64 + 0.5) / n as f64 * area {
            picks.push(t);
            next += 1;
        }
    }
    let sums: Vec<f64> = picks
        .par_iter()
        .filter_map(|&t| {
            let [a, b, c] = tris[t].map(|v| v.as_dvec3());
            let cross = (b - a).cross(c - a);
            let face_area = 0.5 * cross.length();
            if face_area <= 0.0 {
                return None;
            }
            let normal = cross.normalize();
            let centroid = (a + b + c) / 3.0;
            let step = (0.1 * (2.0 * face_area).sqrt()).min(1e-3 * diagonal);
            let w = |p: DVec3| winding_number(tris, part, p);
            Some(w(centroid + step * normal) + w(centroid - step * normal))
        })
        .collect();
    if sums.is_empty() {
        0.0
    } else {
        sums.iter().sum::<f64>() / sums.len() as f64
    }
}

/// The generalised winding number of the faces `part` of `tris` at `p`: the signed solid
/// angle they subtend over 4π (Van Oosterom & Strackee's formula per triangle).
pub fn winding_number(tris: &[[Vec3; 3]], part: &[usize], p: DVec3) -> f64 {
    let total: f64 = part
        .iter()
        .map(|&t| {
            let [a, b, c] = tris[t].map(|v| v.as_dvec3() - p);
            let (la, lb, lc) = (a.length(), b.length(), c.length());
            let num = a.dot(b.cross(c));
            let den = la * lb * lc + a.dot(b) * lc + a.dot(c) * lb + b.dot(c) * la;
            2.0 * num.atan2(den)
        })
        .sum();
    total / (4.0 * std::f64::consts::PI)
}

/// The first witness the part encloses (|w| ≥ [`ENCLOSES`]), if any.
fn enclosed_witness(tris: &[[Vec3; 3]], part: &[usize], witnesses: &[Vec3]) -> Option<Vec3> {
    witnesses
        .par_iter()
        .find_first(|w| winding_number(tris, part, w.as_dvec3()).abs() >= ENCLOSES)
        .copied()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An axis-aligned box from `lo` to `hi`, two triangles a side, wound outward.
    fn box_tris(lo: Vec3, hi: Vec3) -> Vec<[Vec3; 3]> {
        let c = |x: usize, y: usize, z: usize| {
            Vec3::new(
                if x == 1 { hi.x } else { lo.x },
                if y == 1 { hi.y } else { lo.y },
                if z == 1 { hi.z } else { lo.z },
            )
        };
        // Each face's corners counter-clockwise seen from outside.
        let quads = [
            [c(0, 0, 0), c(0, 0, 1), c(0, 1, 1), c(0, 1, 0)], // -x
            [c(1, 0, 0), c(1, 1, 0), c(1, 1, 1), c(1, 0, 1)], // +x
            [c(0, 0, 0), c(1, 0, 0), c(1, 0, 1), c(0, 0, 1)], // -y
            [c(0, 1, 0), c(0, 1, 1), c(1, 1, 1), c(1, 1, 0)], // +y
            [c(0, 0, 0), c(0, 1, 0), c(1, 1, 0), c(1, 0, 0)], // -z
            [c(0, 0, 1), c(1, 0, 1), c(1, 1, 1), c(0, 1, 1)], // +z
        ];
        quads
            .iter()
            .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
            .collect()
    }

    fn flipped(tris: &[[Vec3; 3]]) -> Vec<[Vec3; 3]> {
        tris.iter().map(|t| [t[0], t[2], t[1]]).collect()
    }

    fn volume(tris: &[[Vec3; 3]]) -> f64 {
        crate::shapes::signed_volume(tris)
    }

    /// A UV sphere (or the part of it with polar angle below `theta_max`), wound outward.
    fn sphere_cap(theta_max: f32, segments: usize) -> Vec<[Vec3; 3]> {
        let rings = segments / 2;
        let p = |i: usize, j: usize| {
            let th = theta_max * i as f32 / rings as f32;
            let ph = std::f32::consts::TAU * (j % segments) as f32 / segments as f32;
            Vec3::new(th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin())
        };
        let mut out = Vec::new();
        for i in 0..rings {
            for j in 0..segments {
                let (a, b, c, d) = (p(i, j), p(i + 1, j), p(i + 1, j + 1), p(i, j + 1));
                for t in [[a, c, b], [a, d, c]] {
                    if (t[1] - t[0]).cross(t[2] - t[0]).length() > 1e-9 {
                        out.push(t);
                    }
                }
            }
        }
        out
    }

    #[test]
    fn winding_number_is_one_inside_a_closed_outward_box_and_zero_outside() {
        let b = box_tris(Vec3::ZERO, Vec3::ONE);
        let all: Vec<usize> = (0..b.len()).collect();
        let w_in = winding_number(&b, &all, DVec3::splat(0.3));
        let w_out = winding_number(&b, &all, DVec3::new(2.0, 0.5, 0.5));
        assert!((w_in - 1.0).abs() < 1e-9, "{w_in}");
        assert!(w_out.abs() < 1e-9, "{w_out}");
    }

    #[test]
    fn a_closed_inside_out_box_is_turned_outward_wherever_the_origin_is() {
        for offset in [Vec3::ZERO, Vec3::splat(-0.5), Vec3::new(40.0, -7.0, 3.0)] {
            let mut t = flipped(&box_tris(offset, offset + Vec3::ONE));
            let r = orient(&mut t, Orientation::Auto, &[]);
            assert_eq!((r.parts, r.flipped_parts, r.open_parts), (1, 1, 0), "{r:?}");
            assert!(volume(&t) > 0.0, "{offset}");
            assert!(
                r.notes[0].contains("flipped to face outward"),
                "{:?}",
                r.notes
            );
        }
    }

    #[test]
    fn a_single_triangle_or_quad_is_never_flipped_in_any_mode() {
        let tri = vec![[Vec3::ZERO, Vec3::X, Vec3::Y]];
        let quad = vec![
            [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 0.0, -1.0)],
            [Vec3::ZERO, Vec3::new(1.0, 0.0, -1.0), Vec3::NEG_Z],
        ];
        for mesh in [tri, quad.clone(), flipped(&quad)] {
            for mode in [
                Orientation::Auto,
                Orientation::Outward,
                Orientation::Inward,
                Orientation::AsIs,
            ] {
                for shift in [Vec3::ZERO, Vec3::splat(5.0), Vec3::splat(-5.0)] {
                    let mut t: Vec<_> = mesh.iter().map(|t| t.map(|v| v + shift)).collect();
                    let before = t.clone();
                    let r = orient(&mut t, mode, &[Vec3::splat(0.2)]);
                    assert_eq!(t, before, "{mode:?} {shift}");
                    assert_eq!(r.flipped_parts, 0);
                }
            }
        }
    }

    #[test]
    fn an_open_half_sphere_is_kept_either_way_round() {
        let cap = sphere_cap(std::f32::consts::FRAC_PI_2, 32);
        for mesh in [cap.clone(), flipped(&cap)] {
            for mode in [Orientation::Auto, Orientation::Outward, Orientation::Inward] {
                let mut t = mesh.clone();
                let r = orient(&mut t, mode, &[]);
                assert_eq!(t, mesh, "{mode:?}: {r:?}");
                assert_eq!(r.open_parts, 1);
            }
        }
        // A sphere with a small hole at the pole (a scan's open bottom) is still closed.
        let nearly = flipped(&sphere_cap(0.9 * std::f32::consts::PI, 48));
        let mut t = nearly.clone();
        let r = orient(&mut t, Orientation::Auto, &[]);
        assert_eq!(r.flipped_parts, 1, "{r:?}");
        assert!(volume(&t) > 0.0);
    }

    #[test]
    fn a_closed_room_that_encloses_a_witness_is_kept_inward_by_auto_only() {
        let room = flipped(&box_tris(Vec3::ZERO, Vec3::splat(2.0)));
        let light = Vec3::new(1.0, 1.8, 1.0);
        let mut t = room.clone();
        let r = orient(&mut t, Orientation::Auto, &[Vec3::splat(9.0), light]);
        assert_eq!(t, room);
        assert_eq!((r.kept_enclosures, r.flipped_parts), (1, 0));
        assert!(r.notes[0].contains("room"), "{:?}", r.notes);
        // Without a witness inside it is an inside-out box.
        let mut t = room.clone();
        assert_eq!(
            orient(&mut t, Orientation::Auto, &[Vec3::splat(9.0)]).flipped_parts,
            1
        );
        // The explicit modes do what they say whatever is inside.
        let mut t = room.clone();
        assert_eq!(orient(&mut t, Orientation::Inward, &[]).flipped_parts, 0);
        assert_eq!(t, room);
        let mut t = room.clone();
        assert_eq!(
            orient(&mut t, Orientation::Outward, &[light]).flipped_parts,
            1
        );
        assert!(volume(&t) > 0.0);
        let mut t = flipped(&room);
        assert_eq!(orient(&mut t, Orientation::Inward, &[]).flipped_parts, 1);
        assert_eq!(t, room);
        let mut t = room.clone();
        assert_eq!(orient(&mut t, Orientation::AsIs, &[]).flipped_parts, 0);
    }

    #[test]
    fn parts_are_judged_one_by_one() {
        // An outward box and an inside-out box in one mesh: only the second turns over.
        let good = box_tris(Vec3::ZERO, Vec3::ONE);
        let bad = flipped(&box_tris(Vec3::splat(3.0), Vec3::splat(4.0)));
        let mut t: Vec<_> = good.iter().chain(&bad).copied().collect();
        let r = orient(&mut t, Orientation::Auto, &[]);
        assert_eq!((r.parts, r.flipped_parts), (2, 1));
        assert_eq!(&t[..good.len()], &good[..]);
        assert!(volume(&t[good.len()..]) > 0.0);
        // A room modelled in one mesh with a box inside it: the box is a witness for the
        // room, so the room stays inward and the box outward.
        let room = flipped(&box_tris(Vec3::splat(-5.0), Vec3::splat(5.0)));
        let mut t: Vec<_> = room.iter().chain(&good).copied().collect();
        let before = t.clone();
        let r = orient(&mut t, Orientation::Auto, &[]);
        assert_eq!(
            (r.parts, r.flipped_parts, r.kept_enclosures),
            (2, 0, 1),
            "{r:?}"
        );
        assert_eq!(t, before);
    }
}
