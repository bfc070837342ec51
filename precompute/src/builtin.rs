//! The built-in scenes, made only of procedural shapes (no files needed).
//!
//! In: a scene name (`cornell`, `cornell_paper`, `bowls`, `flower`, `cornell_checker`, and
//! the animated `rolling`). Out: the
//! [`SceneFile`] a user could have written by hand — objects with shapes, transforms and
//! materials, default lights, a camera and a patch density — which
//! [`crate::scene::load_scene`] (`builtin:NAME`) validates and turns into triangles like any
//! other scene. All are in metres (`unit_mm` = 1000).

use translux_proto::light::{Camera, Light};
use translux_proto::scene::{
    DEFAULT_UNIT_MM, ExpTerm, Material, MeshRef, ObjectDesc, PatchDensity, Pattern, Profile,
    SceneFile, Shape, Transform,
};

/// The names `builtin:NAME` accepts.
pub const BUILTIN_SCENES: [&str; 6] = [
    "cornell",
    "cornell_paper",
    "bowls",
    "flower",
    "cornell_checker",
    "rolling",
];

/// The built-in scene called `name`, or `None` if there is none.
pub fn builtin_scene(name: &str) -> Option<SceneFile> {
    match name {
        "cornell" => Some(cornell()),
        "cornell_paper" => Some(cornell_paper()),
        "bowls" => Some(bowls()),
        "flower" => Some(flower()),
        "cornell_checker" => Some(cornell_checker()),
        "rolling" => Some(rolling()),
        _ => None,
    }
}

/// Half the side of the Cornell box's interior (m).
pub const CORNELL_HALF: f32 = 0.2775;
/// Interior height of the Cornell box (m).
pub const CORNELL_HEIGHT: f32 = 0.555;

fn object(
    name: &str,
    shape: Shape,
    translate: [f32; 3],
    rotate_deg: [f32; 3],
    material: Material,
) -> ObjectDesc {
    ObjectDesc {
        keyframes: None,
        name: name.to_owned(),
        mesh: MeshRef::Shape(shape),
        transform: Some(Transform {
            translate,
            rotate_deg,
            scale: None,
        }),
        material,
        crease_deg: None,
        simplify_to: None,
        orientation: Default::default(),
    }
}

fn diffuse(albedo: [f32; 3]) -> Material {
    Material::Diffuse {
        albedo,
        specular: None,
    }
}

fn dipole_preset(name: &str) -> Material {
    Material::Translucent {
        profile: Profile::Dipole {
            preset: Some(name.to_owned()),
            sigma_a: None,
            sigma_s_prime: None,
            eta: None,
            scale: None,
        },
        specular: None,
    }
}

fn dipole(sigma_a: [f32; 3], sigma_s_prime: [f32; 3]) -> Material {
    Material::Translucent {
        profile: Profile::Dipole {
            preset: None,
            sigma_a: Some(sigma_a),
            sigma_s_prime: Some(sigma_s_prime),
            eta: Some(1.3),
            scale: None,
        },
        specular: None,
    }
}

/// The paper's Cornell box (Table 1, Figs. 5–6): a 0.555 m room (x, z ∈ [−0.2775, 0.2775],
/// y ∈ [0, 0.555]) of six inward-facing quads, a short yellow diffuse box and a tall block of
/// real marble (Jensen et al.'s measured coefficients), lit by one lamp under the ceiling.
/// At 16.5 cm, real marble carries light about a centimetre: the block looks opaque.
fn cornell_paper() -> SceneFile {
    let (h, top) = (CORNELL_HALF, CORNELL_HEIGHT);
    let wall = [2.0 * h, 2.0 * h];
    let white = [0.725, 0.71, 0.68];
    // A quad faces +Y; rotating by a about X sends +Y to (0, cos a, sin a), and by a about
    // Z to (−sin a, cos a, 0). So: ceiling 180° about X (−Y), back wall +90° about X (+Z),
    // front wall −90° about X (−Z), left wall −90° about Z (+X), right wall +90° about Z (−X).
    let walls = [
        ("floor", [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], white),
        ("ceiling", [0.0, top, 0.0], [180.0, 0.0, 0.0], white),
        ("back_wall", [0.0, 0.5 * top, -h], [90.0, 0.0, 0.0], white),
        ("front_wall", [0.0, 0.5 * top, h], [-90.0, 0.0, 0.0], white),
        (
            "left_wall",
            [-h, 0.5 * top, 0.0],
            [0.0, 0.0, -90.0],
            [0.63, 0.065, 0.05],
        ),
        (
            "right_wall",
            [h, 0.5 * top, 0.0],
            [0.0, 0.0, 90.0],
            [0.14, 0.45, 0.091],
        ),
    ];
    let mut objects: Vec<ObjectDesc> = walls
        .iter()
        .map(|&(name, t, r, albedo)| {
            object(name, Shape::Quad { size: wall }, t, r, diffuse(albedo))
        })
        .collect();
    // Boxes are centred on their origin, so the centre height is half the box height: the
    // bottom sits exactly on the floor. Footprint circumradius 0.0825·√2 = 0.1167 each and the
    // centres are |(0.18, 0.15)| = 0.234 apart, so they cannot touch.
    let short = 0.165;
    objects.push(object(
        "short_box",
        Shape::Box {
            size: [short, short, short],
            inward: false,
        },
        [0.09, 0.5 * short, 0.07],
        [0.0, -17.0, 0.0],
        diffuse([0.75, 0.65, 0.15]),
    ));
    objects.push(object(
        "tall_block",
        Shape::Box {
            size: [short, 2.0 * short, short],
            inward: false,
        },
        [-0.09, short, -0.08],
        [0.0, 17.0, 0.0],
        dipole_preset("marble"),
    ));
    SceneFile {
        animation: None,
        name: Some("cornell_paper".to_owned()),
        objects,
        lights: vec![Light::Point {
            position: [0.0, 0.50, 0.0],
            intensity: [0.8, 0.8, 0.8],
        }],
        unit_mm: DEFAULT_UNIT_MM,
        patches: Some(PatchDensity {
            target: Some(24_640),
            max_edge: None,
        }),
        camera: Some(Camera {
            position: [0.0, 0.5 * top, 1.3],
            target: [0.0, 0.5 * top, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_deg: 40.0,
        }),
    }
}

/// How many times marble's mean free path the block of `builtin:cornell` has (the dipole's
/// `scale`): the look of a 1:16 model of the box, whose block would be about 1 cm thick.
pub const CORNELL_BLOCK_SCALE: f32 = 16.0;

/// The spot light hidden behind the tall block of `builtin:cornell`, aimed at the block's
/// back face. The block (0.165 m square, turned 17° about Y, centred at x = −0.09, z =
/// −0.08) has its back face centred at (−0.114, 0.165, −0.159) with outward normal
/// (−sin 17°, 0, −cos 17°) = (−0.292, 0, −0.956); the spot stands 7 cm out along that
/// normal (5 cm in front of the back wall). Its full-intensity 40° inner cone falls wholly
/// on the face; the falloff out to 55° spills a little past the face's sides.
pub fn cornell_back_spot() -> Light {
    Light::Spot {
        position: [-0.134, 0.165, -0.226],
        intensity: [4.0, 4.0, 4.0],
        direction: [0.292, 0.0, 0.956],
        inner_deg: 40.0,
        outer_deg: 55.0,
    }
}

/// The Cornell box as translux shows it first: the paper's box ([`cornell_paper`]) with the
/// tall block's marble at [`CORNELL_BLOCK_SCALE`] × its mean free path and a spot light
/// hidden behind the block ([`cornell_back_spot`]) besides the ceiling lamp (dimmed to
/// [`CORNELL_CEILING_DIMMING`] of the paper's), so light that
/// crossed the block makes its edges and front glow warm (a diffuse block of the same
/// colour would stay flat and hard-edged). The translucency slider goes from ×2 to ×128 of
/// real marble; `builtin:cornell_paper` is the paper's scene as it was measured.
fn cornell() -> SceneFile {
    let mut s = cornell_paper();
    s.name = Some("cornell".to_owned());
    for o in s.objects.iter_mut().filter(|o| o.name == "tall_block") {
        o.material = Material::Translucent {
            profile: Profile::Dipole {
                preset: Some("marble".to_owned()),
                sigma_a: None,
                sigma_s_prime: None,
                eta: None,
                scale: Some(CORNELL_BLOCK_SCALE),
            },
            specular: None,
        };
    }
    // The ceiling lamp at 3/8 of the paper's, so that the glow is not washed out.
    for l in &mut s.lights {
        if let Light::Point { intensity, .. } = l {
            *intensity = intensity.map(|x| x * CORNELL_CEILING_DIMMING);
        }
    }
    s.lights.push(cornell_back_spot());
    s
}

/// The ceiling lamp of `builtin:cornell` against the paper's (0.8 W/sr → 0.3 W/sr).
pub const CORNELL_CEILING_DIMMING: f32 = 0.375;

/// Edge of the checkerboard cells of `cornell_checker`'s tall block (m): about a third of
/// the block's 0.165 m width.
pub const CHECKER_CELL: f32 = 0.06;

/// The orange, more absorbing medium of `cornell_checker` (σa, σs′ in mm⁻¹, η = 1.3):
/// absorption 2–40× marble's, rising from red to blue, so its total diffuse reflectance is
/// orange (≈ 0.79, 0.52, 0.14) and its light travels less far than marble's.
pub fn checker_orange() -> Profile {
    Profile::Dipole {
        preset: None,
        sigma_a: Some([0.004, 0.03, 0.3]),
        sigma_s_prime: Some([1.8, 1.6, 1.4]),
        eta: Some(1.3),
        scale: None,
    }
}

/// The paper's Fig. 7: the Cornell box with the tall block a 3-D checkerboard of marble and
/// an orange, more absorbing medium ([`checker_orange`]), combined per optical path by eq. 9.
/// Cells of [`CHECKER_CELL`] in the block's own frame, offset by half a cell across the
/// footprint so that three cells span the width (0.0525 + 0.06 + 0.0525 m), and on the
/// block's mid-height vertically (six layers, none thinner than 0.045 m); no face of the
/// block lies on a cell plane.
fn cornell_checker() -> SceneFile {
    let mut s = cornell_paper();
    s.name = Some("cornell_checker".to_owned());
    let marble = Profile::Dipole {
        preset: Some("marble".to_owned()),
        sigma_a: None,
        sigma_s_prime: None,
        eta: None,
        scale: None,
    };
    for o in s.objects.iter_mut().filter(|o| o.name == "tall_block") {
        o.material = Material::Heterogeneous {
            materials: vec![marble.clone(), checker_orange()],
            pattern: Pattern::Checkerboard {
                cell: CHECKER_CELL,
                origin: [0.5 * CHECKER_CELL, 0.0, 0.5 * CHECKER_CELL],
            },
            specular: None,
        };
    }
    s
}

/// Radius and wall thickness of the bowls (m).
const BOWL_RADIUS: f32 = 0.09;
const BOWL_THICKNESS: f32 = 0.008;
/// Where the three bowls stand on the table (x, z).
const BOWL_SPOTS: [[f32; 2]; 3] = [[-0.22, -0.06], [0.0, -0.13], [0.22, -0.06]];

/// Three translucent coloured bowls and a translucent blob on a diffuse table, lit by a point
/// light inside each bowl.
fn bowls() -> SceneFile {
    let mut objects = vec![object(
        "table",
        Shape::Quad { size: [1.2, 0.8] },
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0],
        diffuse([0.7, 0.7, 0.7]),
    )];
    // Dipole media in mm⁻¹: σs′ ≈ 2 like dense milky glass-ceramics, with absorption one to
    // two orders of magnitude lower in the channel that gives the colour (the albedo
    // σs′/(σs′ + σa) is ≈ 0.999 there and ≈ 0.93–0.95 in the others).
    let media = [
        ("red_bowl", [0.003, 0.12, 0.15], [2.2, 2.0, 1.9]),
        ("green_bowl", [0.14, 0.004, 0.11], [2.0, 2.2, 2.0]),
        ("blue_bowl", [0.16, 0.09, 0.003], [1.9, 2.0, 2.2]),
    ];
    for (&(name, sa, ss), [x, z]) in media.iter().zip(BOWL_SPOTS) {
        objects.push(object(
            name,
            Shape::Bowl {
                radius: BOWL_RADIUS,
                thickness: BOWL_THICKNESS,
                segments: None,
            },
            [x, 0.0, z],
            [0.0, 0.0, 0.0],
            dipole(sa, ss),
        ));
    }
    let blob = 0.06;
    objects.push(object(
        "blob",
        Shape::Sphere {
            radius: blob,
            segments: None,
        },
        [0.0, blob, 0.12],
        [0.0, 0.0, 0.0],
        dipole_preset("skimmilk"),
    ));
    // One light in each cavity, 5 cm above the table: the inner wall (radius 0.082 about
    // (x, 0.09, z)) is 4–8 cm away, and the lights stay below the rim at 0.09.
    let lights = BOWL_SPOTS
        .iter()
        .map(|&[x, z]| Light::Point {
            position: [x, 0.05, z],
            intensity: [0.05, 0.05, 0.05],
        })
        .collect();
    SceneFile {
        animation: None,
        name: Some("bowls".to_owned()),
        objects,
        lights,
        unit_mm: DEFAULT_UNIT_MM,
        patches: Some(PatchDensity {
            target: Some(20_000),
            max_edge: None,
        }),
        camera: Some(Camera {
            position: [0.0, 0.5, 0.7],
            target: [0.0, 0.04, -0.03],
            up: [0.0, 1.0, 0.0],
            fov_deg: 40.0,
        }),
    }
}

/// One term of an exponential-sum profile with total diffuse reflectance `rd` per channel:
/// ∫₀^∞ a e^(−b r) 2πr dr = 2πa / b², so a = rd · b² / (2π) (a in mm⁻², b in mm⁻¹).
fn exp_term(rd: [f32; 3], b: [f32; 3]) -> ExpTerm {
    let a = std::array::from_fn(|c| rd[c] * b[c] * b[c] / std::f32::consts::TAU);
    ExpTerm { a, b }
}

/// Number of petals of the flower.
const PETALS: usize = 8;
/// Petal width (m). Petal bases are tangent to a circle of radius [`PETAL_BASE_RADIUS`]; two
/// neighbouring base edges (360°/8 apart) would meet at a half-width of r₀·tan(22.5°) =
/// 0.0157 m, safely more than 0.014.
const PETAL_WIDTH: f32 = 0.028;
const PETAL_BASE_RADIUS: f32 = 0.038;
const PETAL_BASE_HEIGHT: f32 = 0.01;
/// Petal thickness (m).
const PETAL_THICKNESS: f32 = 0.001;

/// Curled translucent petals (two-sided thin sheets) around a light, over a diffuse ground.
fn flower() -> SceneFile {
    let mut objects = vec![object(
        "ground",
        Shape::Quad { size: [0.4, 0.4] },
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0],
        diffuse([0.35, 0.45, 0.3]),
    )];
    // A pink petal, after the paper's rose: R (same side) and T (through to the other side)
    // are each a1 e^(−b1 r) + a2 e^(−b2 r), a short term plus a weaker, longer one that
    // carries red furthest. Totals (Σ 2πa/b²): R ≈ (0.45, 0.20, 0.30), T ≈ (0.35, 0.12,
    // 0.22) — light crossing the 1 mm petal spreads more (smaller b) and loses more green —
    // so R + T ≈ (0.80, 0.32, 0.52) < 1: the petal never creates energy.
    let petal = Material::ThinSheet {
        reflectance: Profile::Exponentials {
            terms: vec![
                exp_term([0.36, 0.16, 0.24], [1.0, 1.6, 1.3]),
                exp_term([0.09, 0.04, 0.06], [0.3, 0.5, 0.4]),
            ],
        },
        transmittance: Profile::Exponentials {
            terms: vec![
                exp_term([0.25, 0.08, 0.15], [0.7, 1.1, 0.9]),
                exp_term([0.10, 0.04, 0.07], [0.22, 0.35, 0.3]),
            ],
        },
        thickness_mm: PETAL_THICKNESS * DEFAULT_UNIT_MM as f32,
        specular: None,
    };
    let tilt_deg = 25.0f32;
    for k in 0..PETALS {
        let yaw_deg = 360.0 * k as f32 / PETALS as f32;
        let (s, c) = yaw_deg.to_radians().sin_cos();
        // A sheet runs along +Z from its base; tilting by −25° about X raises it, the yaw
        // about Y turns +Z to (sin ψ, 0, cos ψ), and the base moves out along that direction.
        objects.push(object(
            &format!("petal_{k}"),
            Shape::Sheet {
                length: 0.06,
                width: PETAL_WIDTH,
                thickness: PETAL_THICKNESS,
                curl: 0.8,
                segments: None,
            },
            [
                PETAL_BASE_RADIUS * s,
                PETAL_BASE_HEIGHT,
                PETAL_BASE_RADIUS * c,
            ],
            [-tilt_deg, yaw_deg, 0.0],
            petal.clone(),
        ));
    }
    SceneFile {
        animation: None,
        name: Some("flower".to_owned()),
        objects,
        lights: vec![Light::Point {
            position: [0.0, 0.035, 0.0],
            intensity: [0.02, 0.02, 0.02],
        }],
        unit_mm: DEFAULT_UNIT_MM,
        patches: Some(PatchDensity {
            target: Some(20_000),
            max_edge: None,
        }),
        camera: Some(Camera {
            position: [0.0, 0.17, 0.18],
            target: [0.0, 0.03, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_deg: 40.0,
        }),
    }
}

/// Frames of `builtin:rolling` (two seconds at 24 fps, as the paper's 48-frame gallop).
pub const ROLLING_FRAMES: u32 = 48;

/// An animated scene: a skim-milk ball (Jensen et al.'s measured medium, as the bowls' blob)
/// rolls across a floor past a lamp standing behind it, an apple cube slides the other way
/// and turns; lit from behind, each glows through as it
/// crosses in front of the lamp (a sequence: one bundle per frame, see
/// [`translux_proto::animation`]).
fn rolling() -> SceneFile {
    use translux_proto::animation::{Animation, Keyframe};
    let last = ROLLING_FRAMES - 1;
    let radius = 0.025f32;
    let (x0, x1) = (-0.3f32, 0.3f32);
    // Rolling without slipping: the ball turns (x1 − x0) / r radians about −Z.
    let turn = -((x1 - x0) / radius).to_degrees();
    let key = |frame: u32, translate: [f32; 3], rotate_deg: [f32; 3]| Keyframe {
        frame,
        translate,
        rotate_deg,
        scale: None,
    };
    let mut ball = object(
        "ball",
        Shape::Sphere {
            radius,
            segments: Some(24),
        },
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0],
        dipole_preset("skimmilk"),
    );
    ball.transform = None;
    ball.keyframes = Some(vec![
        key(0, [x0, radius, 0.0], [0.0, 0.0, 0.0]),
        key(last, [x1, radius, 0.0], [0.0, 0.0, turn]),
    ]);
    let side = 0.04f32;
    let mut cube = object(
        "cube",
        Shape::Box {
            size: [side, side, side],
            inward: false,
        },
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0],
        dipole_preset("apple"),
    );
    cube.transform = None;
    cube.keyframes = Some(vec![
        key(0, [0.28, side / 2.0, 0.09], [0.0, 0.0, 0.0]),
        key(last, [-0.28, side / 2.0, 0.09], [0.0, 90.0, 0.0]),
    ]);
    let objects = vec![
        object(
            "floor",
            Shape::Quad { size: [0.9, 0.5] },
            [0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0],
            diffuse([0.45, 0.5, 0.42]),
        ),
        ball,
        cube,
    ];
    SceneFile {
        animation: Some(Animation {
            frames: ROLLING_FRAMES,
            fps: 24.0,
            first_number: 0,
        }),
        name: Some("rolling".to_owned()),
        objects,
        lights: vec![
            // The lamp behind the path, low: what glows through the ball and the cube.
            Light::Point {
                position: [0.0, 0.03, -0.09],
                intensity: [0.02, 0.018, 0.015],
            },
            Light::Point {
                position: [0.2, 0.5, 0.4],
                intensity: [0.02, 0.02, 0.02],
            },
        ],
        unit_mm: DEFAULT_UNIT_MM,
        patches: Some(PatchDensity {
            target: Some(2_000),
            max_edge: None,
        }),
        camera: Some(Camera {
            position: [0.0, 0.14, 0.5],
            target: [0.0, 0.02, -0.03],
            up: [0.0, 1.0, 0.0],
            fov_deg: 40.0,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{LoadedObject, LoadedScene, load_scene};
    use glam::Vec3;

    fn load(name: &str) -> LoadedScene {
        match load_scene(&format!("builtin:{name}")) {
            Ok(s) => s,
            Err(e) => panic!("builtin:{name}: {e}"),
        }
    }

    /// The scene of a built-in, or for an animated one its first, middle and last frames.
    fn load_frames(name: &str) -> Vec<LoadedScene> {
        let file = builtin_scene(name).expect(name);
        let Some(a) = file.animation else {
            return vec![load(name)];
        };
        [0, a.frames / 2, a.frames - 1]
            .into_iter()
            .map(|k| {
                crate::scene::resolve_frame(
                    &file,
                    std::path::Path::new("."),
                    name.into(),
                    format!("builtin:{name}"),
                    k,
                )
                .unwrap_or_else(|e| panic!("builtin:{name} frame {k}: {e}"))
            })
            .collect()
    }

    fn normal(t: &[Vec3; 3]) -> Vec3 {
        (t[1] - t[0]).cross(t[2] - t[0]).normalize()
    }

    fn object<'a>(s: &'a LoadedScene, name: &str) -> &'a LoadedObject {
        s.objects
            .iter()
            .find(|o| o.name == name)
            .unwrap_or_else(|| panic!("no {name}"))
    }

    fn bbox(o: &LoadedObject) -> (Vec3, Vec3) {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for v in o.triangles.iter().flatten() {
            lo = lo.min(*v);
            hi = hi.max(*v);
        }
        (lo, hi)
    }

    /// Does the segment p→q cross the interior of triangle t (Möller–Trumbore, with the ends
    /// of the segment and the triangle's border excluded so that touching does not count)?
    fn segment_hits(p: Vec3, q: Vec3, t: &[Vec3; 3]) -> bool {
        let eps = 1e-4;
        let d = q - p;
        let (e1, e2) = (t[1] - t[0], t[2] - t[0]);
        let h = d.cross(e2);
        let det = e1.dot(h);
        if det.abs() < 1e-12 {
            return false; // parallel or coplanar
        }
        let f = 1.0 / det;
        let s = p - t[0];
        let u = f * s.dot(h);
        let qv = s.cross(e1);
        let v = f * d.dot(qv);
        let w = f * e2.dot(qv);
        u > eps && v > eps && u + v < 1.0 - eps && w > eps && w < 1.0 - eps
    }

    /// Do two triangle soups cross each other? Two triangles in general position intersect
    /// iff an edge of one crosses the other.
    fn objects_cross(a: &LoadedObject, b: &LoadedObject) -> bool {
        let ((alo, ahi), (blo, bhi)) = (bbox(a), bbox(b));
        if alo.cmpgt(bhi).any() || blo.cmpgt(ahi).any() {
            return false;
        }
        let crosses = |x: &LoadedObject, y: &LoadedObject| {
            x.triangles.iter().any(|tx| {
                (0..3).any(|i| {
                    let (p, q) = (tx[i], tx[(i + 1) % 3]);
                    y.triangles.iter().any(|ty| segment_hits(p, q, ty))
                })
            })
        };
        crosses(a, b) || crosses(b, a)
    }

    #[test]
    fn names_match_and_unknown_is_none() {
        for name in BUILTIN_SCENES {
            let s = builtin_scene(name).expect(name);
            assert_eq!(s.name.as_deref(), Some(name));
        }
        assert!(builtin_scene("teapot").is_none());
    }

    #[test]
    fn every_builtin_validates_loads_and_does_not_self_intersect() {
        for name in BUILTIN_SCENES {
            let file = builtin_scene(name).expect(name);
            if let Err(e) = file.validate() {
                panic!("{name}: {e}");
            }
            assert_eq!(file.unit_mm, 1000.0);
            assert!(file.camera.is_some() && !file.lights.is_empty());
            for s in load_frames(name) {
                assert_eq!(s.name, name);
                assert_eq!(s.source, format!("builtin:{name}"));
                assert_eq!(s.objects.len(), file.objects.len());
                for o in &s.objects {
                    assert!(!o.triangles.is_empty(), "{name}/{}", o.name);
                    assert_eq!(o.dropped_degenerate, 0, "{name}/{}", o.name);
                }
                for (i, a) in s.objects.iter().enumerate() {
                    for b in &s.objects[i + 1..] {
                        assert!(
                            !objects_cross(a, b),
                            "{name}: {} crosses {}",
                            a.name,
                            b.name
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn the_crossing_check_can_fail() {
        let s = load("cornell");
        let mut moved = object(&s, "short_box").clone();
        for v in moved.triangles.iter_mut().flatten() {
            *v -= Vec3::new(0.12, 0.0, 0.1);
        }
        assert!(objects_cross(&moved, object(&s, "tall_block")));
    }

    #[test]
    fn cornell_walls_face_into_the_room() {
        let s = load("cornell");
        assert_eq!(s.file.patches.and_then(|p| p.target), Some(24_640));
        let (h, top) = (CORNELL_HALF, CORNELL_HEIGHT);
        let walls = [
            ("floor", Vec3::Y, 1, 0.0),
            ("ceiling", -Vec3::Y, 1, top),
            ("back_wall", Vec3::Z, 2, -h),
            ("front_wall", -Vec3::Z, 2, h),
            ("left_wall", Vec3::X, 0, -h),
            ("right_wall", -Vec3::X, 0, h),
        ];
        let centre = Vec3::new(0.0, 0.5 * top, 0.0);
        let mut area = 0.0;
        for (name, n, axis, at) in walls {
            let o = object(&s, name);
            for t in &o.triangles {
                assert!((normal(t) - n).length() < 1e-5, "{name}: {}", normal(t));
                let c = (t[0] + t[1] + t[2]) / 3.0;
                assert!(normal(t).dot(centre - c) > 0.0, "{name} faces out");
                for v in t {
                    assert!((v[axis] - at).abs() < 1e-6, "{name}: {v}");
                    assert!(v.x.abs() <= h + 1e-6 && v.z.abs() <= h + 1e-6);
                    assert!(v.y >= -1e-6 && v.y <= top + 1e-6);
                }
            }
            area += crate::shapes::total_area(&o.triangles);
        }
        assert!((area - 6.0 * 0.555f64.powi(2)).abs() < 1e-4, "{area}");
        let albedo = |name: &str| match object(&s, name).material {
            Material::Diffuse { albedo, .. } => albedo,
            ref m => panic!("{name}: {m:?}"),
        };
        assert_eq!(albedo("left_wall"), [0.63, 0.065, 0.05]);
        assert_eq!(albedo("right_wall"), [0.14, 0.45, 0.091]);
        assert_eq!(albedo("short_box"), [0.75, 0.65, 0.15]);
        assert!(matches!(
            &object(&s, "tall_block").material,
            Material::Translucent { profile: Profile::Dipole { preset: Some(p), .. }, .. } if p == "marble"
        ));
    }

    #[test]
    fn cornell_boxes_stand_on_the_floor_inside_the_room() {
        let s = load("cornell");
        for (name, height, volume) in [
            ("short_box", 0.165, 0.165f64.powi(3)),
            ("tall_block", 0.33, 0.33 * 0.165f64.powi(2)),
        ] {
            let o = object(&s, name);
            let (lo, hi) = bbox(o);
            assert!(lo.y.abs() < 1e-6, "{name} bottom at {}", lo.y);
            assert!((hi.y - height).abs() < 1e-6, "{name} top at {}", hi.y);
            let inner = CORNELL_HALF - 0.01;
            assert!(
                lo.x > -inner && hi.x < inner && lo.z > -inner && hi.z < inner,
                "{name}"
            );
            // Rotation about Y keeps the box upright and closed with outward normals.
            let v = crate::shapes::signed_volume(&o.triangles);
            assert!(
                (v - volume).abs() < 1e-6 * volume.max(1.0) + 1e-9,
                "{name}: {v}"
            );
            // The bottom face lies on the floor and faces down.
            let bottom: Vec<_> = o
                .triangles
                .iter()
                .filter(|t| t.iter().all(|v| v.y.abs() < 1e-6))
                .collect();
            assert_eq!(bottom.len(), 2);
            assert!(bottom.iter().all(|t| normal(t).y < -0.999));
        }
    }

    #[test]
    fn cornell_hides_a_spot_behind_a_translucent_block_and_cornell_paper_does_not() {
        let paper = builtin_scene("cornell_paper").unwrap();
        let shown = builtin_scene("cornell").unwrap();
        assert_eq!(
            paper.lights.len(),
            1,
            "the paper's box has the ceiling lamp only"
        );
        assert_eq!(shown.lights.len(), 2);
        match (&shown.lights[0], &paper.lights[0]) {
            (
                Light::Point {
                    position: a,
                    intensity: ia,
                },
                Light::Point {
                    position: b,
                    intensity: ib,
                },
            ) => {
                assert_eq!(a, b, "the ceiling lamp stays where it was");
                assert_eq!(ia[0], CORNELL_CEILING_DIMMING * ib[0]);
            }
            other => panic!("{other:?}"),
        }
        let scale_of = |f: &SceneFile| match &f.objects.iter().find(|o| o.name == "tall_block") {
            Some(ObjectDesc {
                material:
                    Material::Translucent {
                        profile: Profile::Dipole { preset, scale, .. },
                        ..
                    },
                ..
            }) if preset.as_deref() == Some("marble") => scale.unwrap_or(1.0),
            o => panic!("{o:?}"),
        };
        assert_eq!(scale_of(&paper), 1.0);
        assert_eq!(scale_of(&shown), CORNELL_BLOCK_SCALE);
        // Same geometry otherwise.
        let (a, b) = (load("cornell"), load("cornell_paper"));
        for (x, y) in a.objects.iter().zip(&b.objects) {
            assert_eq!(x.triangles, y.triangles, "{}", x.name);
        }

        // The spot: inside the room, between the block's back face and the back wall, not
        // inside the block, and its inner cone (full intensity) all on the back face.
        let Light::Spot {
            position,
            direction,
            inner_deg,
            outer_deg,
            ..
        } = cornell_back_spot()
        else {
            panic!("not a spot")
        };
        assert!(inner_deg < outer_deg);
        let (p, d) = (Vec3::from(position), Vec3::from(direction).normalize());
        assert!(p.x.abs() < CORNELL_HALF - 0.02 && p.z > -CORNELL_HALF + 0.02);
        assert!(p.y > 0.0 && p.y < CORNELL_HEIGHT);
        let block = object(&a, "tall_block");
        let back: Vec<&[Vec3; 3]> = block
            .triangles
            .iter()
            .filter(|t| normal(t).dot(-d) > 0.99)
            .collect();
        assert_eq!(back.len(), 2, "the spot faces one face of the block");
        let n = normal(back[0]);
        assert!(
            n.dot(p - back[0][0]) > 0.05,
            "the spot is not 5 cm behind the face"
        );
        let inside = |x: Vec3, t: &[Vec3; 3]| {
            (0..3).all(|i| (t[(i + 1) % 3] - t[i]).cross(x - t[i]).dot(n) >= 0.0)
        };
        let u = d.any_orthonormal_vector();
        let v = d.cross(u);
        let (sin, cos) = inner_deg.to_radians().sin_cos();
        for k in 0..16 {
            let phi = k as f32 * std::f32::consts::TAU / 16.0;
            let ray = cos * d + sin * (phi.cos() * u + phi.sin() * v);
            let hit = p + ray * (n.dot(back[0][0] - p) / n.dot(ray));
            assert!(
                back.iter().any(|t| inside(hit, t)),
                "the inner cone's edge at {phi} rad misses the back face ({hit})"
            );
        }
        let (lo, hi) = bbox(block);
        assert!(
            p.cmplt(lo).any() || p.cmpgt(hi).any(),
            "inside the block's box"
        );
        // Behind the block as the camera looks: farther from the camera than the block.
        let cam = Vec3::from(shown.camera.unwrap().position);
        let centre = (lo + hi) * 0.5;
        assert!((p - cam).length() > (centre - cam).length() + 0.1);
    }

    #[test]
    fn bowls_and_flower_are_what_they_say() {
        let s = load("bowls");
        assert_eq!(s.file.lights.len(), 3);
        assert_eq!(s.file.patches.and_then(|p| p.target), Some(20_000));
        let table = object(&s, "table");
        assert!(table.triangles.iter().all(|t| normal(t).y > 0.999));
        // Each light sits inside one bowl's cavity: closer to the bowl's centre of curvature
        // than the inner radius, and below the rim.
        for (light, [x, z]) in s.file.lights.iter().zip(BOWL_SPOTS) {
            let Light::Point { position, .. } = light else {
                panic!("{light:?}")
            };
            let centre = Vec3::new(x, BOWL_RADIUS, z);
            let p = Vec3::from(*position);
            assert!(p.distance(centre) < BOWL_RADIUS - BOWL_THICKNESS && p.y < BOWL_RADIUS);
            assert!(p.y > BOWL_THICKNESS);
        }
        for name in ["red_bowl", "green_bowl", "blue_bowl", "blob"] {
            let o = object(&s, name);
            assert!(matches!(o.material, Material::Translucent { .. }), "{name}");
            let (lo, _) = bbox(o);
            assert!(lo.y.abs() < 1e-6, "{name} floats at {}", lo.y);
        }
        // The colour channel has the lowest absorption.
        for (name, channel) in [("red_bowl", 0), ("green_bowl", 1), ("blue_bowl", 2)] {
            let Material::Translucent {
                profile:
                    Profile::Dipole {
                        sigma_a: Some(sa), ..
                    },
                ..
            } = &object(&s, name).material
            else {
                panic!("{name}")
            };
            let lowest = (0..3).min_by(|&a, &b| sa[a].total_cmp(&sa[b]));
            assert_eq!(lowest, Some(channel), "{name}");
        }

        let s = load("flower");
        let petals: Vec<_> = s
            .objects
            .iter()
            .filter(|o| o.name.starts_with("petal"))
            .collect();
        assert!((8..=10).contains(&petals.len()));
        for p in &petals {
            // Thin sheets with two-term exponential R and T (the paper's rose), as thick as
            // the sheet shape.
            let Material::ThinSheet {
                reflectance: Profile::Exponentials { terms: r },
                transmittance: Profile::Exponentials { terms: t },
                thickness_mm,
                ..
            } = &p.material
            else {
                panic!("{}: {:?}", p.name, p.material)
            };
            assert_eq!((r.len(), t.len()), (2, 2));
            assert_eq!(*thickness_mm, PETAL_THICKNESS * 1000.0);
            // R + T (Σ 2πa/b² of both) stays below 1 in every channel, each a real part.
            let total = |terms: &[ExpTerm], c: usize| -> f32 {
                terms
                    .iter()
                    .map(|t| std::f32::consts::TAU * t.a[c] / (t.b[c] * t.b[c]))
                    .sum()
            };
            for c in 0..3 {
                let (rd, td) = (total(r, c), total(t, c));
                assert!(rd > 0.1 && td > 0.1, "{}: channel {c}: {rd}, {td}", p.name);
                assert!(rd + td > 0.3 && rd + td < 1.0, "{}: channel {c}", p.name);
            }
            let (lo, _) = bbox(p);
            assert!(lo.y > 0.0, "{} goes under the ground", p.name);
        }
        let Light::Point { position, .. } = s.file.lights[0] else {
            panic!()
        };
        let p = Vec3::from(position);
        assert!(p.x.hypot(p.z) < PETAL_BASE_RADIUS && p.y > PETAL_BASE_HEIGHT);
    }
}
