//! A CPU rasterizer for relit meshes: per-vertex linear radiance in, an 8-bit sRGB image out.
//!
//! In: vertex positions (scene units), triangles (indices into the positions, counter-clockwise
//! seen from the front: the front normal is (b − a) × (c − a), the winding every translux mesh
//! uses), linear outgoing radiance B/π per vertex (what a relight answers), a pinhole
//! [`Camera`] and [`RenderParams`]. Out: an [`RgbImage`] of `width × height` pixels, row 0 at
//! the top; [`encode_png`] turns it into PNG bytes. [`render_linear`] stops before step 7 and
//! gives the exposed linear radiance as an [`Rgb32FImage`], which [`encode_exr`] writes as
//! OpenEXR (half float, for compositing).
//!
//! The pipeline, per triangle and then per pixel:
//!
//! 1. **View space.** With f = normalize(target − position), r = normalize(f × up) and
//!    u = r × f, a point p has view coordinates x = (p − eye)·r, y = (p − eye)·u,
//!    z = (p − eye)·f (z is the depth along the view direction, positive in front).
//! 2. **Back faces.** With n = (b − a) × (c − a) in world space, a triangle faces the camera
//!    when n · (eye − a) > 0. With `cull_backfaces` (the default) the others are
//!    skipped, so a closed room such as the Cornell box is seen from outside through its front
//!    wall, whose front faces the inside.
//! 3. **Clipping** (Sutherland–Hodgman, in view space) against the near plane z ≥ z_near
//!    (z_near = [`NEAR_FRACTION`] × |target − position|) and the four side planes
//!    |x| ≤ g·tx·z, |y| ≤ g·ty·z with tx = aspect·ty, ty = tan(fov/2) and a guard band
//!    g = [`GUARD`]. A triangle crossing the near plane becomes a polygon of up to 4 vertices
//!    (up to 8 with the side planes), re-triangulated as a fan; nothing is dropped and
//!    nothing is projected from behind the eye. New vertices interpolate the radiance
//!    linearly along the clipped edge, which is exact: radiance is affine over the triangle
//!    in 3-D, and the clip is done in 3-D.
//! 4. **Projection.** ndc_x = x / (z·tx), ndc_y = y / (z·ty); pixel coordinates
//!    X = (ndc_x + 1)/2 · W, Y = (1 − ndc_y)/2 · H; pixel (i, j) is sampled at its centre
//!    (i + ½, j + ½).
//! 5. **Rasterization** with edge functions: with e_k(P) the signed area of P and the edge
//!    opposite vertex k, the screen barycentrics are λ_k = e_k / (e_0 + e_1 + e_2); a pixel is
//!    covered when every λ_k ≥ 0.
//! 6. **Perspective-correct interpolation and depth.** 1/z and c/z are affine in screen
//!    space, so w = Σ λ_k / z_k and c = (Σ λ_k c_k / z_k) / w. The z-buffer keeps the largest
//!    w (the nearest surface); an equal w keeps the triangle drawn first.
//! 7. **Display.** c ← c · 2^EV (exposure), then the tone curve ([`ToneMap::Srgb`]: clamp to
//!    [0, 1]; [`ToneMap::Filmic`]: the ACES fit of Narkowicz 2016, see [`aces_filmic`]), then
//!    the sRGB OETF ([`srgb_oetf`]), then round(255 v).
//!
//! Work is parallel over bands of [`BAND_ROWS`] rows (rayon): triangles are set up in
//! parallel, binned by the rows they touch, and each band owns its part of the depth buffer
//! and of the image. Memory beyond the 3-byte-per-pixel image is one band's buffers per
//! thread. Bad parameters and bad meshes are errors ([`RenderError`]) naming the field, never
//! panics.

use glam::Vec3;
use image::{Rgb32FImage, RgbImage};
use rayon::prelude::*;
use translux_proto::light::Camera;
use translux_proto::validate::{FieldError, check_range, check_vec_range};

pub use translux_proto::api::ToneMap;

/// Largest `width` and `height`, each.
pub const MAX_SIZE: u32 = 8192;

/// Exposure limit in EV stops, each way: 2^±64 keeps every product with an f32 radiance in
/// range, and no display value changes past it.
pub const MAX_EXPOSURE: f32 = 64.0;

/// The near plane's distance as a fraction of the camera's distance to its target.
pub const NEAR_FRACTION: f32 = 1e-3;

/// Side-plane guard band: triangles are clipped 5% outside the view so that clipped screen
/// coordinates stay small; the pixel loop clamps to the image.
pub const GUARD: f32 = 1.05;

/// Rows per band of parallel work.
pub const BAND_ROWS: u32 = 16;

/// How to picture the radiance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderParams {
    /// Pixels, 1..=[`MAX_SIZE`].
    pub width: u32,
    /// Pixels, 1..=[`MAX_SIZE`].
    pub height: u32,
    /// Exposure in EV stops: radiance is multiplied by 2^exposure before the tone curve.
    pub exposure: f32,
    /// The tone curve.
    pub tone: ToneMap,
    /// The colour where no triangle is seen, as linear display RGB in [0, 1]: encoded with
    /// the sRGB OETF only (neither exposed nor tone mapped), so `[1, 1, 1]` is white.
    pub background: [f32; 3],
    /// Skip triangles whose front faces away from the camera (default `true`).
    pub cull_backfaces: bool,
}

impl Default for RenderParams {
    fn default() -> Self {
        RenderParams {
            width: 800,
            height: 600,
            exposure: 0.0,
            tone: ToneMap::Srgb,
            background: [0.0; 3],
            cull_backfaces: true,
        }
    }
}

impl RenderParams {
    /// Checks every field; the error names it (`width must be an integer in 1..=8192`).
    pub fn validate(&self) -> Result<(), RenderError> {
        for (name, v) in [("width", self.width), ("height", self.height)] {
            if !(1..=MAX_SIZE).contains(&v) {
                return Err(FieldError::new(
                    name,
                    format!("must be an integer in 1..={MAX_SIZE} (got {v})"),
                )
                .into());
            }
        }
        check_range("exposure", self.exposure, -MAX_EXPOSURE, MAX_EXPOSURE)?;
        check_vec_range("background", &self.background, 0.0, 1.0)?;
        Ok(())
    }
}

/// Why a render failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    /// A parameter or the camera broke a rule; the path names the field (`width`,
    /// `camera.fov_deg`).
    #[error("{0}")]
    Invalid(#[from] FieldError),
    /// The mesh is inconsistent (an index out of range, a non-finite position, a radiance
    /// array of the wrong length).
    #[error("bad mesh: {0}")]
    Mesh(String),
    /// The PNG or EXR encoder failed.
    #[error("cannot encode the image: {0}")]
    Encode(String),
}

/// The camera's view frame: eye, right, up, forward, and the tangents of the half angles.
#[derive(Debug, Clone, Copy)]
struct ViewFrame {
    eye: Vec3,
    right: Vec3,
    up: Vec3,
    forward: Vec3,
    /// tan(fov_x / 2) = aspect · tan(fov_y / 2).
    tx: f32,
    /// tan(fov_y / 2).
    ty: f32,
    near: f32,
}

/// Checks a camera for rendering (at the field path `camera`): [`Camera::validate`]'s rules,
/// plus an `up` that is not parallel to the view direction.
pub fn check_camera(camera: &Camera) -> Result<(), RenderError> {
    frame(camera, 1.0).map(|_| ())
}

fn frame(camera: &Camera, aspect: f32) -> Result<ViewFrame, RenderError> {
    camera.validate("camera")?;
    let eye = Vec3::from(camera.position);
    let to_target = Vec3::from(camera.target) - eye;
    let distance = to_target.length();
    let forward = to_target / distance;
    let up_hint = Vec3::from(camera.up).normalize();
    let right = forward.cross(up_hint);
    // |f × û| = sin of the angle between them.
    if right.length_squared() <= 1e-8 {
        return Err(FieldError::new(
            "camera.up",
            "must not be parallel to the view direction (target - position)",
        )
        .into());
    }
    let right = right.normalize();
    let up = right.cross(forward);
    let ty = (0.5 * camera.fov_deg.to_radians()).tan();
    Ok(ViewFrame {
        eye,
        right,
        up,
        forward,
        tx: ty * aspect,
        ty,
        near: NEAR_FRACTION * distance,
    })
}

/// A vertex in view space with its radiance and its barycentric coordinates in the source
/// triangle (a corner is a unit vector; a clipped vertex interpolates them).
#[derive(Debug, Clone, Copy, Default)]
struct ClipVertex {
    p: Vec3,
    c: [f32; 3],
    b: [f32; 3],
}

/// A convex polygon of at most 3 + 5 vertices (each clip plane adds at most one).
#[derive(Debug, Clone, Copy)]
struct Poly {
    v: [ClipVertex; 9],
    n: usize,
}

impl Poly {
    /// Sutherland–Hodgman against the half-space d(p) ≥ 0. Along an edge a → b with
    /// d(a) ≥ 0 > d(b) (or the reverse) the crossing is at t = d(a) / (d(a) − d(b)), and both
    /// position and radiance are interpolated linearly there.
    fn clip(&self, d: impl Fn(Vec3) -> f32) -> Poly {
        let mut out = Poly {
            v: [ClipVertex::default(); 9],
            n: 0,
        };
        for k in 0..self.n {
            let a = self.v[k];
            let b = self.v[(k + 1) % self.n];
            let (da, db) = (d(a.p), d(b.p));
            if da >= 0.0 {
                out.push(a);
            }
            if (da >= 0.0) != (db >= 0.0) {
                let t = da / (da - db);
                out.push(ClipVertex {
                    p: a.p + (b.p - a.p) * t,
                    c: std::array::from_fn(|i| a.c[i] + (b.c[i] - a.c[i]) * t),
                    b: std::array::from_fn(|i| a.b[i] + (b.b[i] - a.b[i]) * t),
                });
            }
        }
        out
    }

    fn push(&mut self, v: ClipVertex) {
        // A convex polygon clipped by a plane gains at most one vertex, so 3 + 5 ≤ 9 holds;
        // the guard keeps a degenerate numeric case from indexing out of bounds.
        if self.n < self.v.len() {
            self.v[self.n] = v;
            self.n += 1;
        }
    }
}

/// A projected vertex: pixel coordinates, w = 1/z, radiance / z and source-triangle
/// barycentrics / z.
#[derive(Debug, Clone, Copy)]
struct ScreenVertex {
    x: f64,
    y: f64,
    w: f32,
    c_w: [f32; 3],
    b_w: [f32; 3],
}

/// A screen triangle, counter-clockwise in pixel coordinates (positive edge-function area),
/// with its rows.
#[derive(Debug, Clone, Copy)]
struct ScreenTri {
    v: [ScreenVertex; 3],
    /// The index of the mesh triangle it was cut from.
    source: u32,
    /// 1 / (e_0 + e_1 + e_2).
    inv_area: f64,
    x_min: f64,
    x_max: f64,
    y_min: f64,
    y_max: f64,
}

/// Renders the mesh as seen from `camera`; see the module documentation for the math.
///
/// `positions` and `vertex_radiance` have one entry per vertex; `triangles` index them.
/// Errors: parameters out of range or a bad camera ([`RenderError::Invalid`], naming the
/// field), an index out of range or a non-finite position or radiance ([`RenderError::Mesh`]).
pub fn render(
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
    vertex_radiance: &[[f32; 3]],
    camera: &Camera,
    params: &RenderParams,
) -> Result<RgbImage, RenderError> {
    render_with(positions, triangles, vertex_radiance, camera, params, None)
}

/// Radiance a [`Surface`] adds at a pixel, on top of the interpolated vertex radiance: the
/// specular pass ([`crate::specular`]).
pub trait PixelShade: Sync {
    /// Whether mesh triangle `triangle` gets anything (a cheap test made before the rest).
    fn shades(&self, triangle: u32) -> bool;
    /// The radiance (W·m⁻²·sr⁻¹) added at world point `p` of mesh triangle `triangle`, with
    /// the interpolated unit normal `n`, seen along the unit direction `to_eye`; `pixel` is
    /// the pixel's row-major index (a seed for sampled terms).
    fn shade(&self, triangle: u32, p: Vec3, n: Vec3, to_eye: Vec3, pixel: u32) -> [f32; 3];
}

/// What per-pixel shading reads of the mesh: its vertex normals (one per position; they
/// need not be unit length) and the shader.
#[derive(Clone, Copy)]
pub struct Surface<'a> {
    pub normals: &'a [[f32; 3]],
    pub shade: &'a dyn PixelShade,
}

impl std::fmt::Debug for Surface<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Surface")
            .field("normals", &self.normals.len())
            .finish_non_exhaustive()
    }
}

/// [`render`] with per-pixel shading: at each pixel whose triangle the shader takes, the
/// world position and the normal are interpolated perspective-correctly from the mesh
/// triangle's corners (barycentrics carried through clipping), and the shader's radiance is
/// added to the interpolated vertex radiance before exposure.
pub fn render_with(
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
    vertex_radiance: &[[f32; 3]],
    camera: &Camera,
    params: &RenderParams,
    surface: Option<&Surface<'_>>,
) -> Result<RgbImage, RenderError> {
    let scale = exposure_scale(params.exposure);
    let background = params.background.map(|v| to_u8(srgb_oetf(v)));
    let pixels = rasterize(
        positions,
        triangles,
        vertex_radiance,
        camera,
        params,
        surface,
        |c| match c {
            Some(c) => display_rgb8(c, scale, params.tone),
            None => background,
        },
    )?;
    RgbImage::from_raw(params.width, params.height, pixels)
        .ok_or_else(|| RenderError::Encode("the pixel buffer does not match the size".into()))
}

/// Renders the mesh as [`render`] does but stops before display: each pixel is the linear
/// radiance (B/π, W·m⁻²·sr⁻¹) × 2^`params.exposure`, with no tone curve and no OETF;
/// pixels where no triangle is seen are `params.background` as given (linear, not exposed).
/// `params.tone` is ignored. Same errors as [`render`]. For [`encode_exr`].
pub fn render_linear(
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
    vertex_radiance: &[[f32; 3]],
    camera: &Camera,
    params: &RenderParams,
) -> Result<Rgb32FImage, RenderError> {
    render_linear_with(positions, triangles, vertex_radiance, camera, params, None)
}

/// [`render_linear`] with per-pixel shading, as [`render_with`].
pub fn render_linear_with(
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
    vertex_radiance: &[[f32; 3]],
    camera: &Camera,
    params: &RenderParams,
    surface: Option<&Surface<'_>>,
) -> Result<Rgb32FImage, RenderError> {
    let scale = exposure_scale(params.exposure);
    let pixels = rasterize(
        positions,
        triangles,
        vertex_radiance,
        camera,
        params,
        surface,
        |c| match c {
            Some(c) => c.map(|v| v * scale),
            None => params.background,
        },
    )?;
    Rgb32FImage::from_raw(params.width, params.height, pixels)
        .ok_or_else(|| RenderError::Encode("the pixel buffer does not match the size".into()))
}

/// Steps 1–6 of the module documentation, then `pixel` turns each pixel's interpolated
/// linear radiance (`None` where no triangle is seen) into its 3 channels; row-major.
fn rasterize<T: Copy + Default + Send>(
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
    vertex_radiance: &[[f32; 3]],
    camera: &Camera,
    params: &RenderParams,
    surface: Option<&Surface<'_>>,
    pixel: impl Fn(Option<[f32; 3]>) -> [T; 3] + Sync,
) -> Result<Vec<T>, RenderError> {
    params.validate()?;
    let (width, height) = (params.width, params.height);
    let view = frame(camera, width as f32 / height as f32)?;
    check_mesh(positions, triangles, vertex_radiance)?;
    if let Some(s) = surface
        && s.normals.len() != positions.len()
    {
        return Err(RenderError::Mesh(format!(
            "normals has {} entries for {} vertices",
            s.normals.len(),
            positions.len()
        )));
    }

    // 1–4: view space, culling, clipping, projection; in parallel, in triangle order.
    const CHUNK: usize = 4096;
    let tris: Vec<ScreenTri> = triangles
        .par_chunks(CHUNK)
        .enumerate()
        .map(|(c, chunk)| {
            let mut out = Vec::with_capacity(chunk.len());
            for (j, t) in chunk.iter().enumerate() {
                let source = (c * CHUNK + j) as u32;
                setup_triangle(
                    source,
                    t,
                    positions,
                    vertex_radiance,
                    &view,
                    params,
                    &mut out,
                );
            }
            out
        })
        .collect::<Vec<_>>()
        .concat();

    // Bin by band: band b holds rows [b·BAND_ROWS, (b+1)·BAND_ROWS).
    let bands = height.div_ceil(BAND_ROWS) as usize;
    let mut bins: Vec<Vec<u32>> = vec![Vec::new(); bands];
    for (k, t) in tris.iter().enumerate() {
        // Rows whose centre y + ½ can lie in [y_min, y_max].
        let Some((r0, r1)) = pixel_span(t.y_min, t.y_max, height) else {
            continue;
        };
        for bin in &mut bins[(r0 / BAND_ROWS) as usize..=(r1 / BAND_ROWS) as usize] {
            bin.push(k as u32);
        }
    }

    // 5–7: each band rasterizes its triangles into its own depth and colour buffers, then
    // writes `pixel`'s values into its rows of the image.
    let row_bytes = width as usize * 3;
    let mut pixels = vec![T::default(); row_bytes * height as usize];
    pixels
        .par_chunks_mut(row_bytes * BAND_ROWS as usize)
        .zip(bins.par_iter())
        .enumerate()
        .for_each(|(b, (out, bin))| {
            let row0 = b as u32 * BAND_ROWS;
            let rows = (out.len() / row_bytes) as u32;
            let n = (width * rows) as usize;
            let mut depth = vec![0.0f32; n];
            let mut colour = vec![[0.0f32; 3]; n];
            // The nearest screen triangle per pixel, for the shading pass.
            let mut nearest = vec![u32::MAX; if surface.is_some() { n } else { 0 }];
            for &k in bin {
                let hit = surface.is_some().then_some((k, &mut nearest[..]));
                raster(
                    &tris[k as usize],
                    width,
                    row0,
                    rows,
                    &mut depth,
                    &mut colour,
                    hit,
                );
            }
            if let Some(s) = surface {
                shade_band(
                    s,
                    &tris,
                    positions,
                    triangles,
                    &view,
                    width,
                    row0,
                    &nearest,
                    &depth,
                    &mut colour,
                );
            }
            for (i, px) in out.chunks_exact_mut(3).enumerate() {
                px.copy_from_slice(&pixel((depth[i] > 0.0).then_some(colour[i])));
            }
        });
    Ok(pixels)
}

/// Indices in range, positions and radiance finite, one radiance per position.
fn check_mesh(
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
    vertex_radiance: &[[f32; 3]],
) -> Result<(), RenderError> {
    if vertex_radiance.len() != positions.len() {
        return Err(RenderError::Mesh(format!(
            "vertex_radiance has {} entries for {} vertices",
            vertex_radiance.len(),
            positions.len()
        )));
    }
    let n = positions.len();
    if let Some((k, t)) = triangles
        .par_iter()
        .enumerate()
        .find_first(|(_, t)| t.iter().any(|&i| i as usize >= n))
    {
        return Err(RenderError::Mesh(format!(
            "triangles[{k}] = {t:?} has an index out of range ({n} vertices)"
        )));
    }
    if let Some(k) = positions
        .par_iter()
        .position_first(|p| !p.iter().all(|x| x.is_finite()))
    {
        return Err(RenderError::Mesh(format!(
            "positions[{k}] = {:?} is not finite",
            positions[k]
        )));
    }
    if let Some(k) = vertex_radiance
        .par_iter()
        .position_first(|c| !c.iter().all(|x| x.is_finite()))
    {
        return Err(RenderError::Mesh(format!(
            "vertex_radiance[{k}] = {:?} is not finite",
            vertex_radiance[k]
        )));
    }
    Ok(())
}

/// Transforms, culls, clips and projects one triangle, appending 0 to 7 screen triangles.
fn setup_triangle(
    source: u32,
    t: &[u32; 3],
    positions: &[[f32; 3]],
    radiance: &[[f32; 3]],
    view: &ViewFrame,
    params: &RenderParams,
    out: &mut Vec<ScreenTri>,
) {
    let to_view = |k: usize| {
        let i = t[k];
        let d = Vec3::from(positions[i as usize]) - view.eye;
        let mut b = [0.0; 3];
        b[k] = 1.0;
        ClipVertex {
            p: Vec3::new(d.dot(view.right), d.dot(view.up), d.dot(view.forward)),
            c: radiance[i as usize],
            b,
        }
    };
    // Facing, in world space (the view frame (r, u, f) is left-handed, which would flip a
    // cross product taken in view coordinates): n · (eye − a) > 0.
    let [a, b, c] = t.map(|i| Vec3::from(positions[i as usize]));
    let facing = (b - a).cross(c - a).dot(view.eye - a);
    let v: [ClipVertex; 3] = std::array::from_fn(to_view);
    // NaN (an overflow in view space) compares false both ways: not drawn.
    let draw = facing > 0.0 || (!params.cull_backfaces && facing < 0.0);
    if !draw {
        return;
    }
    let mut poly = Poly {
        v: [ClipVertex::default(); 9],
        n: 3,
    };
    poly.v[..3].copy_from_slice(&v);
    let (near, gx, gy) = (view.near, GUARD * view.tx, GUARD * view.ty);
    // Trivially inside every plane: no clipping work.
    let inside = v
        .iter()
        .all(|c| c.p.z >= near && c.p.x.abs() <= gx * c.p.z && c.p.y.abs() <= gy * c.p.z);
    if !inside {
        poly = poly.clip(|p| p.z - near);
        poly = poly.clip(|p| gx * p.z - p.x);
        poly = poly.clip(|p| gx * p.z + p.x);
        poly = poly.clip(|p| gy * p.z - p.y);
        poly = poly.clip(|p| gy * p.z + p.y);
        if poly.n < 3 {
            return;
        }
    }
    let (w, h) = (params.width as f64, params.height as f64);
    let project = |c: &ClipVertex| {
        // z ≥ near > 0 after clipping.
        let inv_z = 1.0 / c.p.z;
        ScreenVertex {
            x: (c.p.x as f64 * inv_z as f64 / view.tx as f64 + 1.0) * 0.5 * w,
            y: (1.0 - c.p.y as f64 * inv_z as f64 / view.ty as f64) * 0.5 * h,
            w: inv_z,
            c_w: c.c.map(|x| x * inv_z),
            b_w: c.b.map(|x| x * inv_z),
        }
    };
    let s0 = project(&poly.v[0]);
    for k in 1..poly.n - 1 {
        let (mut s1, mut s2) = (project(&poly.v[k]), project(&poly.v[k + 1]));
        let mut area = edge(&s0, &s1, s2.x, s2.y);
        if area < 0.0 {
            std::mem::swap(&mut s1, &mut s2);
            area = -area;
        }
        let t = ScreenTri {
            v: [s0, s1, s2],
            source,
            inv_area: 1.0 / area,
            x_min: s0.x.min(s1.x).min(s2.x),
            x_max: s0.x.max(s1.x).max(s2.x),
            y_min: s0.y.min(s1.y).min(s2.y),
            y_max: s0.y.max(s1.y).max(s2.y),
        };
        // Edge-on (or collapsed by clipping) triangles cover no pixel centre reliably, and
        // coordinates that overflowed are not drawn.
        let finite = [t.x_min, t.x_max, t.y_min, t.y_max]
            .iter()
            .all(|v| v.is_finite());
        if area > 1e-12 && area.is_finite() && finite {
            out.push(t);
        }
    }
}

/// Twice the signed area of (a, b, p): positive when p is left of a → b in pixel
/// coordinates (y down), i.e. the edge function.
fn edge(a: &ScreenVertex, b: &ScreenVertex, px: f64, py: f64) -> f64 {
    (b.x - a.x) * (py - a.y) - (b.y - a.y) * (px - a.x)
}

/// The pixels i in 0..n whose centre i + ½ lies in [lo, hi], or `None`.
fn pixel_span(lo: f64, hi: f64, n: u32) -> Option<(u32, u32)> {
    let first = (lo - 0.5).ceil().max(0.0);
    let last = (hi - 0.5).floor().min(n as f64 - 1.0);
    (first <= last).then_some((first as u32, last as u32))
}

/// Rasterizes one triangle into the band of `rows` rows starting at `row0`.
fn raster(
    t: &ScreenTri,
    width: u32,
    row0: u32,
    rows: u32,
    depth: &mut [f32],
    colour: &mut [[f32; 3]],
    mut hit: Option<(u32, &mut [u32])>,
) {
    let Some((x0, x1)) = pixel_span(t.x_min, t.x_max, width) else {
        return;
    };
    let Some((y0, y1)) = pixel_span(t.y_min, t.y_max, row0 + rows) else {
        return;
    };
    let y0 = y0.max(row0);
    if y0 > y1 {
        return;
    }
    let [a, b, c] = &t.v;
    for y in y0..=y1 {
        let py = y as f64 + 0.5;
        let row = ((y - row0) * width) as usize;
        for x in x0..=x1 {
            let px = x as f64 + 0.5;
            // λ_k = e_k / area, e_k the edge function of the edge opposite vertex k.
            let e0 = edge(b, c, px, py);
            let e1 = edge(c, a, px, py);
            let e2 = edge(a, b, px, py);
            if e0 < 0.0 || e1 < 0.0 || e2 < 0.0 {
                continue;
            }
            let l = [
                (e0 * t.inv_area) as f32,
                (e1 * t.inv_area) as f32,
                (e2 * t.inv_area) as f32,
            ];
            // 1/z is affine in screen space.
            let w = l[0] * a.w + l[1] * b.w + l[2] * c.w;
            let i = row + x as usize;
            if w > depth[i] {
                depth[i] = w;
                // c = (Σ λ_k c_k / z_k) / (Σ λ_k / z_k).
                colour[i] = std::array::from_fn(|ch| {
                    (l[0] * a.c_w[ch] + l[1] * b.c_w[ch] + l[2] * c.c_w[ch]) / w
                });
                if let Some((k, nearest)) = hit.as_mut() {
                    nearest[i] = *k;
                }
            }
        }
    }
}

/// Adds the surface's shading to each covered pixel of a band whose nearest triangle it
/// takes. The pixel centre's barycentrics in the screen triangle (λ) give those in the mesh
/// triangle perspective-correctly, B = (Σ λ_k b_k / z_k) / (Σ λ_k / z_k), and from them the
/// world position and the normal.
#[allow(clippy::too_many_arguments)]
fn shade_band(
    surface: &Surface<'_>,
    tris: &[ScreenTri],
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
    view: &ViewFrame,
    width: u32,
    row0: u32,
    nearest: &[u32],
    depth: &[f32],
    colour: &mut [[f32; 3]],
) {
    for (i, &k) in nearest.iter().enumerate() {
        if k == u32::MAX || depth[i] <= 0.0 {
            continue;
        }
        let t = &tris[k as usize];
        if !surface.shade.shades(t.source) {
            continue;
        }
        let (x, y) = (
            (i as u32 % width) as f64 + 0.5,
            (row0 + i as u32 / width) as f64 + 0.5,
        );
        let [a, b, c] = &t.v;
        let l = [
            (edge(b, c, x, y) * t.inv_area) as f32,
            (edge(c, a, x, y) * t.inv_area) as f32,
            (edge(a, b, x, y) * t.inv_area) as f32,
        ];
        let w = depth[i];
        let bary: [f32; 3] =
            std::array::from_fn(|m| (l[0] * a.b_w[m] + l[1] * b.b_w[m] + l[2] * c.b_w[m]) / w);
        let corners = triangles[t.source as usize];
        let mut p = Vec3::ZERO;
        let mut n = Vec3::ZERO;
        for m in 0..3 {
            p += Vec3::from(positions[corners[m] as usize]) * bary[m];
            n += Vec3::from(surface.normals[corners[m] as usize]) * bary[m];
        }
        let to_eye = (view.eye - p).normalize_or_zero();
        let n = n.normalize_or_zero();
        if n == Vec3::ZERO || to_eye == Vec3::ZERO {
            continue;
        }
        let pixel = row0 * width + i as u32;
        let add = surface.shade.shade(t.source, p, n, to_eye, pixel);
        for ch in 0..3 {
            colour[i][ch] += add[ch];
        }
    }
}

/// The luminance percentile [`auto_exposure`] exposes for.
pub const AUTO_EXPOSURE_PERCENTILE: f64 = 0.95;

/// The display value [`auto_exposure`] puts that percentile at.
pub const AUTO_EXPOSURE_TARGET: f64 = 0.8;

/// The exposure in EV stops that puts the 95th percentile of vertex luminance
/// (0.2126 R + 0.7152 G + 0.0722 B, Rec. 709) near 0.8, rounded to 0.1 EV: what the viewer
/// picks when it opens a scene. **This mirrors `autoExposure` in web/js/app.js**; change both
/// together, so that a render, an export and the viewer agree on a scene's brightness.
///
/// Exactly as there: the percentile is the value at index ⌊0.95 n⌋ of the luminances sorted
/// ascending, the sums are in f64 (JavaScript numbers), and the rounding is JavaScript's
/// `Math.round` (halves toward +∞, so −2.45 → −2.4, where Rust's `round` gives −2.5). Where
/// that luminance is not positive (no vertices, or under 5% of them lit) the viewer keeps
/// its exposure of 0, and so does this. The answer is clamped to ±[`MAX_EXPOSURE`], the range
/// renders and exports accept, which matters only for luminances under 2⁻⁶⁴.
pub fn auto_exposure(vertex_radiance: &[[f32; 3]]) -> f32 {
    exposure_of_luminance(vertex_radiance.iter().map(|&c| luminance(c)).collect())
}

/// The luminance [`auto_exposure`] reads of a radiance (Rec. 709 weights).
pub fn luminance(c: [f32; 3]) -> f64 {
    0.2126 * f64::from(c[0]) + 0.7152 * f64::from(c[1]) + 0.0722 * f64::from(c[2])
}

/// [`auto_exposure`] from the vertices' luminances ([`luminance`]; a backend that makes the
/// colours where B is sends these back instead of a second set of colours).
pub fn exposure_of_luminance(mut lum: Vec<f64>) -> f32 {
    if lum.is_empty() {
        return 0.0;
    }
    // ⌊0.95 n⌋ < n for every n ≥ 1; only the one order statistic is needed, not a full sort.
    let k = ((lum.len() as f64 * AUTO_EXPOSURE_PERCENTILE).floor() as usize).min(lum.len() - 1);
    let (_, &mut p, _) = lum.select_nth_unstable_by(k, f64::total_cmp);
    if !(p > 0.0 && p.is_finite()) {
        return 0.0;
    }
    let tenths = (AUTO_EXPOSURE_TARGET / p).log2() * 10.0;
    let rounded = js_round(tenths) / 10.0;
    (rounded as f32).clamp(-MAX_EXPOSURE, MAX_EXPOSURE)
}

/// JavaScript's `Math.round`: the nearest integer, halves toward +∞.
fn js_round(x: f64) -> f64 {
    let down = x.floor();
    if x - down >= 0.5 { down + 1.0 } else { down }
}

/// 2^ev: the factor an exposure of `ev` stops applies to radiance.
pub fn exposure_scale(ev: f32) -> f32 {
    ev.exp2()
}

/// The ACES filmic curve as fitted by K. Narkowicz, "ACES Filmic Tone Mapping Curve" (blog
/// post, 2016-01-06; CC0/MIT): f(x) = x(2.51x + 0.03) / (x(2.43x + 0.59) + 0.14), saturated
/// to [0, 1]. It fits ACES's RRT + Rec.709 ODT with the display gamma removed (maximum error
/// 0.0138) on pre-exposed input, so 1 maps to about 0.8 (the full ACES curve is f(0.6 x));
/// the output is linear and still needs the display OETF. A luminance-style fit applied per
/// channel: bright saturated colours shift toward their primaries.
pub fn aces_filmic(x: f32) -> f32 {
    // Past x = 1e4 the curve is 1 after saturation; the bound keeps x² finite.
    let x = x.clamp(0.0, 1e4);
    let y = (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14);
    y.clamp(0.0, 1.0)
}

/// The tone curve, per channel, from exposed linear radiance to linear display values in
/// [0, 1]. NaN and negative inputs give 0.
pub fn tone_map(x: f32, tone: ToneMap) -> f32 {
    let x = if x > 0.0 { x } else { 0.0 };
    match tone {
        ToneMap::Srgb => x.min(1.0),
        ToneMap::Filmic => aces_filmic(x),
    }
}

/// The sRGB opto-electronic transfer function (IEC 61966-2-1): 12.92 v for v ≤ 0.0031308,
/// else 1.055 v^(1/2.4) − 0.055. Input clamped to [0, 1].
pub fn srgb_oetf(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0);
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// The inverse of [`srgb_oetf`]: (V + 0.055)/1.055)^2.4 above 0.04045, V / 12.92 below.
pub fn srgb_eotf(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0);
    if v <= 0.040_45 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// round(255 v) for v clamped to [0, 1].
pub fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// Linear radiance to an 8-bit sRGB pixel: × `scale` (= 2^EV), tone curve, OETF, 8 bits.
pub fn display_rgb8(radiance: [f32; 3], scale: f32, tone: ToneMap) -> [u8; 3] {
    radiance.map(|c| to_u8(srgb_oetf(tone_map(c * scale, tone))))
}

/// The image as PNG bytes (8-bit RGB, fast zlib level: renders are mostly flat shading).
pub fn encode_png(img: &RgbImage) -> Result<Vec<u8>, RenderError> {
    use image::ImageEncoder;
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    let mut bytes = Vec::new();
    PngEncoder::new_with_quality(&mut bytes, CompressionType::Fast, FilterType::Adaptive)
        .write_image(
            img.as_raw(),
            img.width(),
            img.height(),
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| RenderError::Encode(e.to_string()))?;
    Ok(bytes)
}

/// The largest finite half float; brighter linear values are stored as it, not as infinity.
pub const EXR_HALF_MAX: f32 = 65504.0;

/// The linear image as OpenEXR bytes, as compositing tools expect a render pass: one RGB
/// layer, **half-float** channels, increasing scan lines, ZIP-compressed (16 lines a block),
/// linear values as given (no transfer function). A value above [`EXR_HALF_MAX`] is stored
/// as that, so no pixel is infinite.
///
/// Written with the `exr` crate directly: the `image` crate's OpenEXR encoder stores only
/// 32-bit floats in tiles.
pub fn encode_exr(img: &Rgb32FImage) -> Result<Vec<u8>, RenderError> {
    use exr::prelude::{
        Blocks, Compression, Encoding, Image, LineOrder, SpecificChannels, Vec2, WritableImage, f16,
    };
    let half = |v: f32| f16::from_f32(v.clamp(-EXR_HALF_MAX, EXR_HALF_MAX));
    let channels = SpecificChannels::rgb(|p: Vec2<usize>| {
        let [r, g, b] = img.get_pixel(p.x() as u32, p.y() as u32).0;
        (half(r), half(g), half(b))
    });
    let mut image = Image::from_channels((img.width() as usize, img.height() as usize), channels);
    image.layer_data.encoding = Encoding {
        compression: Compression::ZIP16,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    };
    let mut bytes = std::io::Cursor::new(Vec::new());
    image
        .write()
        .to_buffered(&mut bytes)
        .map_err(|e| RenderError::Encode(e.to_string()))?;
    Ok(bytes.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Looking down −Z from the origin, 90° vertical field of view.
    fn cam() -> Camera {
        Camera {
            position: [0.0; 3],
            target: [0.0, 0.0, -1.0],
            up: [0.0, 1.0, 0.0],
            fov_deg: 90.0,
        }
    }

    fn params(w: u32, h: u32) -> RenderParams {
        RenderParams {
            width: w,
            height: h,
            background: [0.2, 0.4, 0.6],
            ..Default::default()
        }
    }

    fn px(img: &RgbImage, x: u32, y: u32) -> [u8; 3] {
        img.get_pixel(x, y).0
    }

    fn bg() -> [u8; 3] {
        [0.2f32, 0.4, 0.6].map(|v| to_u8(srgb_oetf(v)))
    }

    /// A triangle at depth z facing the camera (counter-clockwise seen from +Z).
    fn facing_triangle(z: f32, half: f32) -> Vec<[f32; 3]> {
        vec![[-half, -half, z], [half, -half, z], [0.0, half, z]]
    }

    #[test]
    fn transfer_functions() {
        // 0.5 linear: 1.055 · 0.5^(1/2.4) − 0.055 = 0.7354 → 187.5 → 188.
        assert_eq!(to_u8(srgb_oetf(0.5)), 188);
        assert_eq!(to_u8(srgb_oetf(0.0)), 0);
        assert_eq!(to_u8(srgb_oetf(1.0)), 255);
        for k in 0..=100 {
            let v = k as f32 / 100.0;
            assert!((srgb_eotf(srgb_oetf(v)) - v).abs() < 1e-5, "{v}");
        }
        // Narkowicz's fit: f(1) = 2.54 / 3.16 = 0.8038, f(0) = 0, saturates at 1.
        assert!((aces_filmic(1.0) - 2.54 / 3.16).abs() < 1e-6);
        assert_eq!(aces_filmic(0.0), 0.0);
        assert_eq!(aces_filmic(1e6), 1.0);
        assert_eq!(aces_filmic(f32::INFINITY), 1.0);
        assert_eq!(tone_map(f32::NAN, ToneMap::Filmic), 0.0);
        assert_eq!(tone_map(-1.0, ToneMap::Srgb), 0.0);
        assert_eq!(tone_map(3.0, ToneMap::Srgb), 1.0);
        // Monotonic.
        let mut last = 0.0;
        for k in 1..2000 {
            let y = aces_filmic(k as f32 * 0.01);
            assert!(y >= last);
            last = y;
        }
        assert_eq!(exposure_scale(1.0), 2.0);
        assert_eq!(
            display_rgb8([0.25, 0.5, 1.0], 2.0, ToneMap::Srgb),
            [188, 255, 255]
        );
    }

    #[test]
    fn auto_exposure_follows_the_viewers_rule() {
        // 100 vertices of luminance k/100 (grey): index ⌊0.95 · 100⌋ = 95 holds 0.95, and
        // log2(0.8 / 0.95) = −0.2479 → −0.2.
        let grey: Vec<[f32; 3]> = (0..100).rev().map(|k| [k as f32 / 100.0; 3]).collect();
        assert_eq!(auto_exposure(&grey), -0.2);
        // Luminance weights: pure green 0.1 has luminance 0.07152; log2(0.8 / 0.07152) =
        // 3.4834 → 3.5.
        assert_eq!(auto_exposure(&[[0.0, 0.1, 0.0]; 7]), 3.5);
        // A bright top 4% (past index 95 of 100) does not count; a top 5% does.
        let mut v = vec![[0.1f32; 3]; 96];
        v.extend([[1000.0; 3]; 4]);
        assert_eq!(auto_exposure(&v), 3.0);
        v[95] = [1000.0; 3];
        assert_eq!(auto_exposure(&v), -10.3);
        v[95] = [0.1; 3];
        v.reverse(); // order does not matter
        assert_eq!(auto_exposure(&v), 3.0);
        // Halves round toward +∞, as JavaScript's Math.round does.
        assert_eq!(js_round(-24.5), -24.0);
        assert_eq!(js_round(24.5), 25.0);
        assert_eq!(js_round(-24.6), -25.0);
        // Nothing lit at the percentile, or nothing at all: 0, as the viewer keeps it.
        assert_eq!(auto_exposure(&[]), 0.0);
        let mut dark = vec![[0.0f32; 3]; 96];
        dark.extend([[1.0; 3]; 4]);
        assert_eq!(auto_exposure(&dark), 0.0);
        // Clamped to what a render accepts.
        assert_eq!(auto_exposure(&[[1e-30; 3]]), MAX_EXPOSURE);
        assert_eq!(auto_exposure(&[[f32::MAX; 3]]), -MAX_EXPOSURE);
        // The answer exposes the percentile to about 0.8 (within the 0.1 EV rounding).
        let v: Vec<[f32; 3]> = (1..=1000)
            .map(|k| [k as f32 * 0.37, k as f32, 0.1])
            .collect();
        let ev = auto_exposure(&v);
        let p = 0.2126 * 951.0 * 0.37 + 0.7152 * 951.0 + 0.0722 * 0.1;
        let shown = p * 2f64.powf(f64::from(ev));
        assert!((shown / 0.8).log2().abs() <= 0.05 + 1e-6, "{ev} {shown}");
    }

    #[test]
    fn a_facing_triangle_covers_the_centre_with_the_expected_value() {
        let pos = facing_triangle(-2.0, 1.0);
        let img = render(&pos, &[[0, 1, 2]], &[[0.5; 3]; 3], &cam(), &params(64, 48)).unwrap();
        assert_eq!((img.width(), img.height()), (64, 48));
        let c = px(&img, 32, 24);
        for ch in c {
            assert!(ch.abs_diff(188) <= 1, "{c:?}");
        }
        for (x, y) in [(0, 0), (63, 0), (0, 47), (63, 47)] {
            assert_eq!(px(&img, x, y), bg(), "corner ({x}, {y})");
        }
        // Coverage: the triangle spans ndc y in [−0.5, 0.5] (half = 1 at depth 2, ty = 1),
        // i.e. rows 12..36; the rows just outside are background.
        assert_eq!(px(&img, 32, 10), bg());
        assert_eq!(px(&img, 32, 37), bg());
        assert_ne!(px(&img, 32, 34), bg());
        // Filmic and exposure change the value: 0.5 · 2 = 1 → 0.8038 → sRGB 232.
        let p = RenderParams {
            tone: ToneMap::Filmic,
            exposure: 1.0,
            ..params(64, 48)
        };
        let img = render(&pos, &[[0, 1, 2]], &[[0.5; 3]; 3], &cam(), &p).unwrap();
        let want = to_u8(srgb_oetf(2.54 / 3.16));
        assert_eq!(want, 232);
        assert!(px(&img, 32, 24)[0].abs_diff(want) <= 1);
    }

    #[test]
    fn back_faces_are_culled_unless_asked_not_to() {
        // Clockwise seen from the camera: its front faces −Z, away from the eye.
        let pos = facing_triangle(-2.0, 1.0);
        let tri = [[0, 2, 1]];
        let img = render(&pos, &tri, &[[0.5; 3]; 3], &cam(), &params(32, 32)).unwrap();
        assert_eq!(px(&img, 16, 16), bg());
        let p = RenderParams {
            cull_backfaces: false,
            ..params(32, 32)
        };
        let img = render(&pos, &tri, &[[0.5; 3]; 3], &cam(), &p).unwrap();
        assert!(px(&img, 16, 16)[1].abs_diff(188) <= 1);
    }

    #[test]
    fn the_nearer_triangle_wins_whatever_the_order() {
        let mut pos = facing_triangle(-2.0, 1.0); // near, red
        pos.extend(facing_triangle(-3.0, 2.0)); // far, green
        let mut rad = vec![[1.0, 0.0, 0.0]; 3];
        rad.extend([[0.0, 1.0, 0.0]; 3]);
        for tris in [[[0, 1, 2], [3, 4, 5]], [[3, 4, 5], [0, 1, 2]]] {
            let img = render(&pos, &tris, &rad, &cam(), &params(40, 40)).unwrap();
            assert_eq!(px(&img, 20, 20), [255, 0, 0], "{tris:?}");
            // Below the near one's base (ndc y −0.5), above the far one's (−0.667): green.
            assert_eq!(px(&img, 20, 32), [0, 255, 0], "{tris:?}");
        }
    }

    #[test]
    fn a_triangle_through_the_near_plane_is_clipped_not_dropped() {
        // A floor at y = −1 from behind the eye (z = +5) to far ahead (z = −50), facing up.
        let pos = vec![[-20.0, -1.0, 5.0], [20.0, -1.0, 5.0], [0.0, -1.0, -50.0]];
        let img = render(&pos, &[[0, 1, 2]], &[[0.5; 3]; 3], &cam(), &params(64, 64)).unwrap();
        // Below the horizon: covered down to the bottom row; above it: background.
        for y in [36, 48, 63] {
            assert_ne!(px(&img, 32, y), bg(), "row {y}");
            assert!(px(&img, 32, y)[0].abs_diff(188) <= 1);
        }
        for y in [0, 16, 31] {
            assert_eq!(px(&img, 32, y), bg(), "row {y}");
        }
        // Grazing: a triangle entirely behind the eye draws nothing.
        let behind = vec![[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, 2.0]];
        let p = RenderParams {
            cull_backfaces: false,
            ..params(16, 16)
        };
        let img = render(&behind, &[[0, 1, 2]], &[[0.5; 3]; 3], &cam(), &p).unwrap();
        assert!(img.pixels().all(|p| p.0 == bg()));
    }

    #[test]
    fn interpolation_is_perspective_correct() {
        // A quad tilted in depth: the near edge at z = −1, y = −0.2 (ndc y = −0.2), the far
        // edge at z = −3, y = 0.6 (ndc y = +0.2), radiance 0 near and 1 far. The image
        // centre (ndc y = 0) is halfway on screen, where 1/z = ½(1 + ⅓) = ⅔ and
        // c = ½(0/1 + 1/3) / ⅔ = ¼; affine interpolation would give ½.
        let pos = vec![
            [-2.0, -0.2, -1.0],
            [2.0, -0.2, -1.0],
            [2.0, 0.6, -3.0],
            [-2.0, 0.6, -3.0],
        ];
        let rad = vec![[0.0; 3], [0.0; 3], [1.0; 3], [1.0; 3]];
        let p = RenderParams {
            cull_backfaces: false,
            ..params(101, 101)
        };
        let img = render(&pos, &[[0, 1, 2], [0, 2, 3]], &rad, &cam(), &p).unwrap();
        let got = px(&img, 50, 50)[0];
        let perspective = to_u8(srgb_oetf(0.25)); // 137
        let affine = to_u8(srgb_oetf(0.5)); // 188
        assert_eq!(perspective, 137);
        assert!(got.abs_diff(perspective) <= 1, "{got}");
        assert!(got.abs_diff(affine) > 20, "{got}");
    }

    #[test]
    fn png_round_trips() {
        let pos = facing_triangle(-2.0, 1.0);
        let rad = vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let img = render(&pos, &[[0, 1, 2]], &rad, &cam(), &params(37, 23)).unwrap();
        let bytes = encode_png(&img).unwrap();
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
        let back = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
            .unwrap()
            .to_rgb8();
        assert_eq!(back.dimensions(), (37, 23));
        assert_eq!(back.as_raw(), img.as_raw());
    }

    #[test]
    fn linear_render_matches_the_png_and_round_trips_as_exr() {
        let pos = facing_triangle(-2.0, 1.0);
        let rad = vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let p = RenderParams {
            exposure: 1.5,
            tone: ToneMap::Filmic,
            background: [0.25, 0.5, 0.75],
            ..params(37, 23)
        };
        let lin = render_linear(&pos, &[[0, 1, 2]], &rad, &cam(), &p).unwrap();
        let png = render(&pos, &[[0, 1, 2]], &rad, &cam(), &p).unwrap();
        let scale = exposure_scale(p.exposure);
        let mut covered = 0;
        for (l, d) in lin.pixels().zip(png.pixels()) {
            if l.0 == p.background {
                assert_eq!(d.0, p.background.map(|v| to_u8(srgb_oetf(v))));
            } else {
                covered += 1;
                // The PNG pixel is the linear one (already × 2^EV) through tone and OETF.
                assert_eq!(d.0, display_rgb8(l.0.map(|v| v / scale), scale, p.tone));
            }
        }
        assert!(covered > 0);
        // The centre is the exposed radiance, no tone curve: its channels sum to 2^1.5.
        let c = lin.get_pixel(18, 11).0;
        assert!((c.iter().sum::<f32>() - scale).abs() < 1e-4, "{c:?}");

        let bytes = encode_exr(&lin).unwrap();
        assert_eq!(&bytes[..4], &[0x76, 0x2f, 0x31, 0x01], "EXR magic");
        // The header, read by the `exr` crate: half floats in scan lines.
        let meta = exr::meta::MetaData::read_from_buffered(&bytes[..], true).unwrap();
        let header = &meta.headers[0];
        assert_eq!(header.layer_size, exr::math::Vec2(37, 23));
        assert!(matches!(
            header.blocks,
            exr::meta::BlockDescription::ScanLines
        ));
        let names: Vec<String> = header
            .channels
            .list
            .iter()
            .map(|c| c.name.to_string())
            .collect();
        assert_eq!(names, ["B", "G", "R"]);
        for c in &header.channels.list {
            assert_eq!(c.sample_type, exr::meta::attribute::SampleType::F16);
        }
        // The pixels, read by another decoder (`image`'s), within half precision.
        let back = image::load_from_memory_with_format(&bytes, image::ImageFormat::OpenExr)
            .unwrap()
            .to_rgb32f();
        assert_eq!(back.dimensions(), (37, 23));
        for (b, l) in back.as_raw().iter().zip(lin.as_raw()) {
            assert!((b - l).abs() <= l.abs() / 1024.0 + 1e-7, "{b} vs {l}");
        }
    }

    #[test]
    fn exr_clamps_what_half_floats_cannot_hold() {
        let mut img = Rgb32FImage::new(2, 1);
        img.put_pixel(0, 0, image::Rgb([1e6, 0.5, 70000.0]));
        img.put_pixel(1, 0, image::Rgb([0.0, 65504.0, 1e-3]));
        let back = image::load_from_memory_with_format(
            &encode_exr(&img).unwrap(),
            image::ImageFormat::OpenExr,
        )
        .unwrap()
        .to_rgb32f();
        assert_eq!(back.get_pixel(0, 0).0, [EXR_HALF_MAX, 0.5, EXR_HALF_MAX]);
        assert_eq!(back.get_pixel(1, 0).0[1], EXR_HALF_MAX);
        assert!((back.get_pixel(1, 0).0[2] - 1e-3).abs() < 1e-6);
    }

    #[test]
    fn bad_parameters_and_meshes_are_errors_naming_the_field() {
        let pos = facing_triangle(-2.0, 1.0);
        let tri = [[0, 1, 2]];
        let rad = [[0.5; 3]; 3];
        let go = |p: RenderParams| {
            render(&pos, &tri, &rad, &cam(), &p)
                .unwrap_err()
                .to_string()
        };
        assert!(go(params(0, 10)).starts_with("width must be"));
        assert!(go(params(10, 8193)).starts_with("height must be"));
        assert!(
            go(RenderParams {
                exposure: f32::NAN,
                ..params(4, 4)
            })
            .starts_with("exposure must be finite")
        );
        assert!(
            go(RenderParams {
                background: [0.0, 2.0, 0.0],
                ..params(4, 4)
            })
            .starts_with("background[1]")
        );
        let p = params(4, 4);
        let mut c = cam();
        c.fov_deg = 0.0;
        let e = render(&pos, &tri, &rad, &c, &p).unwrap_err().to_string();
        assert!(e.starts_with("camera.fov_deg"), "{e}");
        let mut c = cam();
        c.up = [0.0, 0.0, 2.0];
        let e = render(&pos, &tri, &rad, &c, &p).unwrap_err().to_string();
        assert!(e.starts_with("camera.up must not be parallel"), "{e}");
        assert!(check_camera(&cam()).is_ok());
        let e = render(&pos, &[[0, 1, 3]], &rad, &cam(), &p).unwrap_err();
        assert!(e.to_string().contains("triangles[0]"), "{e}");
        let e = render(&pos, &tri, &rad[..2], &cam(), &p).unwrap_err();
        assert!(e.to_string().contains("vertex_radiance has 2"), "{e}");
        let mut bad = pos.clone();
        bad[1][2] = f32::INFINITY;
        let e = render(&bad, &tri, &rad, &cam(), &p).unwrap_err();
        assert!(e.to_string().contains("positions[1]"), "{e}");
        let e = render(&pos, &tri, &[[0.5; 3], [f32::NAN; 3], [0.5; 3]], &cam(), &p).unwrap_err();
        assert!(e.to_string().contains("vertex_radiance[1]"), "{e}");
        // An empty mesh is a background image, not an error.
        let img = render(&[], &[], &[], &cam(), &p).unwrap();
        assert!(img.pixels().all(|q| q.0 == bg()));
    }

    #[test]
    fn a_large_image_over_many_bands_covers_the_analytic_area() {
        // 1000 × 700: the triangle's centre pixel and corners, across band boundaries.
        let pos = facing_triangle(-2.0, 1.0);
        let img = render(
            &pos,
            &[[0, 1, 2]],
            &[[0.5; 3]; 3],
            &cam(),
            &params(1000, 700),
        )
        .unwrap();
        assert!(px(&img, 500, 350)[0].abs_diff(188) <= 1);
        assert_eq!(px(&img, 0, 699), bg());
        let covered = img.pixels().filter(|p| p.0 != bg()).count() as f64;
        // The analytic screen area: x = (x/(z·tx) + 1)/2 · W, y = (1 − y/(z·ty))/2 · H with
        // z = 2, tx = aspect = 1000/700, ty = 1.
        let (w, h, tx) = (1000.0, 700.0, 1000.0 / 700.0);
        let sx = |x: f64| (x / (2.0 * tx) + 1.0) * 0.5 * w;
        let sy = |y: f64| (1.0 - y / 2.0) * 0.5 * h;
        let area = 0.5 * (sx(1.0) - sx(-1.0)) * (sy(-1.0) - sy(1.0));
        assert!((covered - area).abs() < 0.01 * area, "{covered} vs {area}");
    }
}
