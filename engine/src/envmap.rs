//! Environment maps: equirectangular Radiance `.hdr` images and built-in skies, and their
//! mean radiance over the direction bins that [`crate::envvis`] stores visibility for.
//!
//! In: a map name (`builtin:sky`, `builtin:white`, or a `.hdr` file) and a rotation. Out:
//! an [`EnvMap`] (radiance per direction, W·m⁻²·sr⁻¹, linear RGB) and, per [`Bins`] bin k,
//! the map's mean radiance L̄_k over that bin after rotation ([`bin_radiance`]). With the
//! bundle's per-patch visibility V_ik (`∫_bin k visible(ω) max(n·ω, 0) dω`), the
//! environment's irradiance at patch i is E_i = scale · Σ_k V_ik L̄_k.
//!
//! ## Conventions (also in `docs/environment.md`)
//!
//! World +Y is up. A map is read as latitude-longitude: pixel column u ∈ [0, 1) (left to
//! right) and row v ∈ [0, 1] (top to bottom) are the direction
//!
//! ```text
//!     θ = π v  (from +Y),  φ = 2π u,   ω = (sin θ sin φ, cos θ, −sin θ cos φ)
//! ```
//!
//! so the top row is the zenith, the middle row the horizon, u = 0 looks along −Z,
//! u = 0.25 along +X, u = 0.5 along +Z and u = 0.75 along −X (Mitsuba 3's `envmap`
//! convention, so one file lights both the same way). `rotation_deg` = α turns the map
//! right-handedly about +Y (counter-clockwise seen from above, like Mitsuba's
//! `rotate([0, 1, 0], α)`): what the file shows at u appears at u − α/360.
//!
//! Bins partition the sphere into `rows × cols` cells of equal solid angle 4π/(rows·cols):
//! rows uniform in y = cos θ (row 0 at the zenith), columns uniform in u. Equal areas keep
//! every bin equally well sampled, and a rotation about +Y is a shift in u.

use std::f32::consts::PI;
use std::path::{Path, PathBuf};

use glam::Vec3;
use thiserror::Error;

/// Names of the built-in maps.
pub const BUILTIN_SKY: &str = "builtin:sky";
pub const BUILTIN_WHITE: &str = "builtin:white";

/// Largest map accepted (pixels): 16384 × 8192.
pub const MAX_PIXELS: u64 = 16384 * 8192;

/// Why a map could not be had.
#[derive(Debug, Error)]
pub enum EnvMapError {
    #[error("{name:?} is not a built-in map (the built-ins are {BUILTIN_SKY} and {BUILTIN_WHITE})")]
    UnknownBuiltin { name: String },
    #[error("{}: cannot read the file: {error}", path.display())]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{}: not a valid Radiance .hdr image: {reason}", path.display())]
    Malformed { path: PathBuf, reason: String },
    #[error(
        "{}: {width}×{height} pixels is larger than the {MAX_PIXELS} allowed",
        path.display()
    )]
    TooLarge {
        path: PathBuf,
        width: u32,
        height: u32,
    },
    #[error("a map needs at least one pixel, got {width}×{height}")]
    Empty { width: u32, height: u32 },
    #[error("pixel {index} has radiance {value}, expected finite and >= 0")]
    BadTexel { index: usize, value: f32 },
}

/// An equirectangular radiance map (W·m⁻²·sr⁻¹, linear RGB), row-major from the top row.
#[derive(Debug, Clone, PartialEq)]
pub struct EnvMap {
    width: u32,
    height: u32,
    texels: Vec<[f32; 3]>,
}

impl EnvMap {
    /// A map from texels (row-major, top row first); every value must be finite and ≥ 0.
    pub fn from_texels(
        width: u32,
        height: u32,
        texels: Vec<[f32; 3]>,
    ) -> Result<EnvMap, EnvMapError> {
        if width == 0 || height == 0 || texels.len() != width as usize * height as usize {
            return Err(EnvMapError::Empty { width, height });
        }
        if let Some((index, value)) = texels
            .iter()
            .flatten()
            .enumerate()
            .find(|(_, v)| !(v.is_finite() && **v >= 0.0))
        {
            return Err(EnvMapError::BadTexel {
                index: index / 3,
                value: *value,
            });
        }
        Ok(EnvMap {
            width,
            height,
            texels,
        })
    }

    /// A uniform map of radiance `l`.
    pub fn uniform(l: [f32; 3]) -> EnvMap {
        EnvMap {
            width: 1,
            height: 1,
            texels: vec![l],
        }
    }

    /// `builtin:white` (uniform radiance 1) or `builtin:sky` ([`sky`]).
    pub fn builtin(name: &str) -> Result<EnvMap, EnvMapError> {
        match name {
            BUILTIN_WHITE => Ok(EnvMap::uniform([1.0; 3])),
            BUILTIN_SKY => Ok(sky(&SkyParams::default())),
            _ => Err(EnvMapError::UnknownBuiltin { name: name.into() }),
        }
    }

    /// Reads an equirectangular Radiance `.hdr` file (RGBE, `-Y H +X W` orientation).
    pub fn load_hdr(path: &Path) -> Result<EnvMap, EnvMapError> {
        use image::ImageDecoder;
        let file = std::fs::File::open(path).map_err(|error| EnvMapError::Io {
            path: path.to_path_buf(),
            error,
        })?;
        let malformed = |e: image::ImageError| EnvMapError::Malformed {
            path: path.to_path_buf(),
            reason: e.to_string(),
        };
        let decoder = image::codecs::hdr::HdrDecoder::new(std::io::BufReader::new(file))
            .map_err(malformed)?;
        let (width, height) = decoder.dimensions();
        if u64::from(width) * u64::from(height) > MAX_PIXELS {
            return Err(EnvMapError::TooLarge {
                path: path.to_path_buf(),
                width,
                height,
            });
        }
        if width == 0 || height == 0 {
            return Err(EnvMapError::Malformed {
                path: path.to_path_buf(),
                reason: format!("the image is {width}×{height} pixels"),
            });
        }
        let mut bytes = vec![0u8; decoder.total_bytes() as usize];
        decoder.read_image(&mut bytes).map_err(malformed)?;
        let floats: &[f32] =
            bytemuck::try_cast_slice(&bytes).map_err(|e| EnvMapError::Malformed {
                path: path.to_path_buf(),
                reason: format!("decoded pixels are not f32 RGB: {e}"),
            })?;
        let texels = floats.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        EnvMap::from_texels(width, height, texels).map_err(|e| EnvMapError::Malformed {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    /// Bytes held (for cache accounting).
    pub fn bytes(&self) -> usize {
        self.texels.len() * 12
    }

    /// The texel at column `x`, row `y`.
    pub fn texel(&self, x: u32, y: u32) -> [f32; 3] {
        self.texels[(y.min(self.height - 1) * self.width + x.min(self.width - 1)) as usize]
    }

    /// Radiance along direction `d` (unit, map frame: no rotation), nearest texel.
    pub fn radiance(&self, d: Vec3) -> [f32; 3] {
        let (u, v) = direction_to_uv(d);
        let x = ((u * self.width as f32) as u32).min(self.width - 1);
        let y = ((v * self.height as f32) as u32).min(self.height - 1);
        self.texel(x, y)
    }

    /// Radiance arriving from world direction `d` when the map is turned by `rotation_deg`.
    pub fn radiance_rotated(&self, d: Vec3, rotation_deg: f32) -> [f32; 3] {
        self.radiance(rotate_y(d, -rotation_deg))
    }
}

/// (u, v) of unit direction `d` (see the module's conventions); u in [0, 1), v in [0, 1].
pub fn direction_to_uv(d: Vec3) -> (f32, f32) {
    let u = d.x.atan2(-d.z) / (2.0 * PI);
    let u = u - u.floor();
    let v = d.y.clamp(-1.0, 1.0).acos() / PI;
    (if u >= 1.0 { 0.0 } else { u }, v)
}

/// The unit direction of map coordinates (u, v).
pub fn uv_to_direction(u: f32, v: f32) -> Vec3 {
    let (st, ct) = (PI * v).sin_cos();
    let (sp, cp) = (2.0 * PI * u).sin_cos();
    Vec3::new(st * sp, ct, -st * cp)
}

/// `d` turned right-handedly about +Y by `deg` degrees.
pub fn rotate_y(d: Vec3, deg: f32) -> Vec3 {
    let (s, c) = deg.to_radians().sin_cos();
    Vec3::new(d.x * c + d.z * s, d.y, -d.x * s + d.z * c)
}

/// An equal-area partition of the sphere: `rows` bands uniform in y = cos θ (row 0 at the
/// zenith), each cut into `cols` equal ranges of u. Bin k = row·cols + col.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Bins {
    pub rows: u32,
    pub cols: u32,
}

impl Bins {
    /// Number of bins.
    pub fn count(&self) -> usize {
        self.rows as usize * self.cols as usize
    }

    /// Solid angle of every bin, 4π / count (sr).
    pub fn solid_angle(&self) -> f32 {
        4.0 * PI / self.count() as f32
    }

    /// The bin holding world direction `d` (unit).
    pub fn bin_of(&self, d: Vec3) -> usize {
        let (u, _) = direction_to_uv(d);
        self.bin_of_yu(d.y, u)
    }

    /// The bin of y = cos θ and map column u ∈ [0, 1).
    pub fn bin_of_yu(&self, y: f32, u: f32) -> usize {
        let r = (((1.0 - y) * 0.5 * self.rows as f32) as u32).min(self.rows - 1);
        let c = ((u * self.cols as f32) as u32).min(self.cols - 1);
        (r * self.cols + c) as usize
    }

    /// The direction at fractions (s, t) ∈ [0, 1]² across bin k (s along u, t down in y);
    /// uniform (s, t) gives directions uniform in solid angle over the bin.
    pub fn direction(&self, k: usize, s: f32, t: f32) -> Vec3 {
        let (r, c) = (
            (k / self.cols as usize) as f32,
            (k % self.cols as usize) as f32,
        );
        let y = 1.0 - 2.0 * (r + t) / self.rows as f32;
        let u = (c + s) / self.cols as f32;
        let sin = (1.0 - y * y).max(0.0).sqrt();
        let (sp, cp) = (2.0 * PI * u).sin_cos();
        Vec3::new(sin * sp, y, -sin * cp)
    }
}

/// Mean radiance of `map`, turned by `rotation_deg`, over every bin of `bins` (W·m⁻²·sr⁻¹).
///
/// Exact for the map as piecewise-constant texels: each texel's radiance is counted in each
/// bin with the exact solid angle they share (dω = dy dφ, so a texel row and a bin row
/// share a y-interval and a texel column and a bin column a u-interval; a rotation about +Y
/// only shifts u). Nothing is sampled, so a small bright feature (a sun) keeps its power:
/// Σ_k L̄_k Ω_k equals the map's ∫ L dω.
pub fn bin_radiance(map: &EnvMap, rotation_deg: f32, bins: Bins) -> Vec<[f32; 3]> {
    let (w, h) = (map.width as usize, map.height as usize);
    let (rows, cols) = (bins.rows as usize, bins.cols as usize);
    // Texel row ty spans y ∈ [cos(π(ty+1)/h), cos(π ty/h)]; bin row r spans
    // y ∈ [1 − 2(r+1)/rows, 1 − 2r/rows]. Their shared y-lengths:
    let row_overlap: Vec<Vec<(usize, f64)>> = (0..h)
        .map(|ty| {
            let pi = std::f64::consts::PI;
            let y_hi = (pi * ty as f64 / h as f64).cos();
            let y_lo = (pi * (ty + 1) as f64 / h as f64).cos();
            (0..rows)
                .filter_map(|r| {
                    let b_hi = 1.0 - 2.0 * r as f64 / rows as f64;
                    let b_lo = 1.0 - 2.0 * (r + 1) as f64 / rows as f64;
                    let o = y_hi.min(b_hi) - y_lo.max(b_lo);
                    (o > 0.0).then_some((r, o))
                })
                .collect()
        })
        .collect();
    // Texel column tx spans u ∈ [tx/w, (tx+1)/w) in the file, shifted by −α/360 in the
    // world (mod 1); bin column c spans [c/cols, (c+1)/cols). Their shared u-lengths:
    let shift = f64::from(-rotation_deg) / 360.0;
    let col_overlap: Vec<Vec<(usize, f64)>> = (0..w)
        .map(|tx| {
            let mut out = Vec::new();
            let a = tx as f64 / w as f64 + shift;
            let a = a - a.floor();
            let (mut lo, mut left) = (a, 1.0 / w as f64);
            // Walk bin columns from the one holding `lo`, wrapping at u = 1.
            while left > 1e-15 {
                let c = ((lo * cols as f64) as usize).min(cols - 1);
                let end = (c + 1) as f64 / cols as f64;
                let take = (end - lo).min(left);
                if take > 0.0 {
                    out.push((c, take));
                }
                left -= take.max(0.0);
                lo = if c + 1 == cols { 0.0 } else { end };
            }
            out
        })
        .collect();
    let mut sum = vec![[0.0f64; 3]; bins.count()];
    for (ty, ro) in row_overlap.iter().enumerate() {
        for (tx, co) in col_overlap.iter().enumerate() {
            let l = map.texels[ty * w + tx];
            for &(r, oy) in ro {
                for &(c, ou) in co {
                    let s = &mut sum[r * cols + c];
                    for k in 0..3 {
                        s[k] += f64::from(l[k]) * oy * ou;
                    }
                }
            }
        }
    }
    // Every bin has Δy = 2/rows and Δu = 1/cols.
    let area = 2.0 / rows as f64 / cols as f64;
    sum.iter().map(|s| s.map(|v| (v / area) as f32)).collect()
}

/// Settings of the built-in sky.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SkyParams {
    /// Sun elevation above the horizon (degrees).
    pub sun_elevation_deg: f32,
    /// Sun direction's map column u (0.25: toward +X before rotation).
    pub sun_u: f32,
    /// Zenith radiance (W·m⁻²·sr⁻¹, per channel before tint).
    pub zenith: f32,
    /// Colour at the zenith and at the horizon (multiplied by the luminance pattern).
    pub zenith_tint: [f32; 3],
    pub horizon_tint: [f32; 3],
    /// Albedo of the ground below the horizon (lit by the sky alone).
    pub ground_albedo: f32,
    /// Map size (width = 2 × height).
    pub height: u32,
}

impl Default for SkyParams {
    fn default() -> Self {
        SkyParams {
            sun_elevation_deg: 40.0,
            sun_u: 0.25,
            zenith: 1.0,
            zenith_tint: [0.55, 0.7, 1.0],
            horizon_tint: [1.0, 1.0, 1.0],
            ground_albedo: 0.2,
            height: 128,
        }
    }
}

/// The CIE clear-sky relative luminance (CIE 1973 / ISO 15469 clear sky) at zenith angle
/// `z` and angle `gamma` from the sun, for a sun at zenith angle `zs`, normalised to 1 at
/// the zenith:
///
/// ```text
///   L/Lz = (0.91 + 10 e^(−3γ) + 0.45 cos²γ)(1 − e^(−0.32 / cos z))
///          / ((0.91 + 10 e^(−3 zs) + 0.45 cos² zs)(1 − e^(−0.32)))
/// ```
pub fn cie_clear_sky(z: f32, gamma: f32, zs: f32) -> f32 {
    let indicatrix = |g: f32| 0.91 + 10.0 * (-3.0 * g).exp() + 0.45 * g.cos().powi(2);
    let gradation = |z: f32| 1.0 - (-0.32 / z.cos().max(1e-4)).exp();
    indicatrix(gamma) * gradation(z) / (indicatrix(zs) * gradation(0.0))
}

/// `builtin:sky`: the CIE clear-sky luminance pattern (no sun disc: add the sun as a
/// directional light), tinted from white at the horizon to blue at the zenith, over a grey
/// ground of uniform radiance ρ_g E_sky/π (E_sky: the sky's irradiance on the ground).
pub fn sky(p: &SkyParams) -> EnvMap {
    let (h, w) = (p.height.max(2), 2 * p.height.max(2));
    let zs = (90.0 - p.sun_elevation_deg).to_radians();
    let sun = uv_to_direction(p.sun_u, zs / PI);
    let mut texels = vec![[0.0f32; 3]; (w * h) as usize];
    let mut e_sky = 0.0f64;
    for y in 0..h {
        let v = (y as f32 + 0.5) / h as f32;
        let z = PI * v;
        if z >= 0.5 * PI {
            continue;
        }
        let t0 = PI * y as f32 / h as f32;
        let t1 = PI * (y + 1) as f32 / h as f32;
        let omega = (t0.cos() - t1.cos()) * 2.0 * PI / w as f32;
        let blend = z.cos();
        for x in 0..w {
            let u = (x as f32 + 0.5) / w as f32;
            let d = uv_to_direction(u, v);
            let gamma = d.dot(sun).clamp(-1.0, 1.0).acos();
            let l = p.zenith * cie_clear_sky(z, gamma, zs);
            let texel = std::array::from_fn(|c| {
                l * (p.horizon_tint[c] + (p.zenith_tint[c] - p.horizon_tint[c]) * blend)
            });
            // Luminance-like weight for the ground's brightness.
            let lum = 0.2126 * texel[0] + 0.7152 * texel[1] + 0.0722 * texel[2];
            e_sky += f64::from(lum * z.cos() * omega);
            texels[(y * w + x) as usize] = texel;
        }
    }
    let ground = p.ground_albedo * e_sky as f32 / PI;
    for y in 0..h {
        let v = (y as f32 + 0.5) / h as f32;
        if PI * v >= 0.5 * PI {
            for x in 0..w {
                texels[(y * w + x) as usize] = [ground; 3];
            }
        }
    }
    EnvMap {
        width: w,
        height: h,
        texels,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uv_round_trip_and_axes() {
        let close = |a: Vec3, b: Vec3| (a - b).length() < 1e-5;
        assert!(close(uv_to_direction(0.0, 0.5), -Vec3::Z));
        assert!(close(uv_to_direction(0.25, 0.5), Vec3::X));
        assert!(close(uv_to_direction(0.5, 0.5), Vec3::Z));
        assert!(close(uv_to_direction(0.75, 0.5), -Vec3::X));
        assert!(close(uv_to_direction(0.3, 0.0), Vec3::Y));
        for (u, v) in [(0.1, 0.2), (0.6, 0.7), (0.9, 0.45)] {
            let (u2, v2) = direction_to_uv(uv_to_direction(u, v));
            assert!(
                (u - u2).abs() < 1e-5 && (v - v2).abs() < 1e-5,
                "{u} {v} -> {u2} {v2}"
            );
        }
    }

    #[test]
    fn rotation_is_right_handed_about_y_and_shifts_u() {
        // +X turned by 90° right-handedly about +Y points to −Z.
        assert!((rotate_y(Vec3::X, 90.0) - (-Vec3::Z)).length() < 1e-6);
        // A map that is bright only near u = 0.25 (+X): after 90° the light comes from −Z.
        let mut texels = vec![[0.0f32; 3]; 8];
        texels[2] = [1.0; 3];
        let map = EnvMap::from_texels(8, 1, texels).unwrap();
        assert_eq!(map.radiance_rotated(Vec3::X, 0.0), [1.0; 3]);
        assert_eq!(map.radiance_rotated(-Vec3::Z, 90.0), [1.0; 3]);
        assert_eq!(map.radiance_rotated(Vec3::X, 90.0), [0.0; 3]);
    }

    #[test]
    fn bins_are_equal_area_and_cover_the_sphere() {
        let bins = Bins { rows: 6, cols: 12 };
        // Directions drawn uniformly in (s, t) land in their own bin.
        for k in 0..bins.count() {
            for (s, t) in [(0.1, 0.1), (0.5, 0.5), (0.9, 0.8)] {
                assert_eq!(bins.bin_of(bins.direction(k, s, t)), k);
            }
        }
        assert!((bins.solid_angle() * bins.count() as f32 - 4.0 * PI).abs() < 1e-4);
    }

    #[test]
    fn bin_means_keep_the_maps_power() {
        // A map with one hot texel: the bins' total power (Σ L̄_k Ω_k) equals the map's.
        let (w, h) = (64, 32);
        let mut texels = vec![[0.1f32; 3]; w * h];
        texels[10 * w + 40] = [500.0, 20.0, 0.0];
        let map = EnvMap::from_texels(w as u32, h as u32, texels.clone()).unwrap();
        let mut power = [0.0f64; 3];
        for y in 0..h {
            let t0 = PI as f64 * y as f64 / h as f64;
            let t1 = PI as f64 * (y + 1) as f64 / h as f64;
            let om = (t0.cos() - t1.cos()) * 2.0 * PI as f64 / w as f64;
            for x in 0..w {
                for c in 0..3 {
                    power[c] += f64::from(texels[y * w + x][c]) * om;
                }
            }
        }
        let bins = Bins { rows: 8, cols: 16 };
        for rot in [0.0, 33.0, 180.0] {
            let means = bin_radiance(&map, rot, bins);
            for c in 0..3 {
                let got: f64 = means
                    .iter()
                    .map(|m| f64::from(m[c]) * f64::from(bins.solid_angle()))
                    .sum();
                assert!(
                    (got - power[c]).abs() < 1e-3 * power[c],
                    "rotation {rot} channel {c}: {got} vs {}",
                    power[c]
                );
            }
        }
        // A uniform map gives its radiance in every bin.
        let means = bin_radiance(&EnvMap::uniform([2.0, 1.0, 0.5]), 17.0, bins);
        assert!(means.iter().all(|m| (m[0] - 2.0).abs() < 1e-5
            && (m[1] - 1.0).abs() < 1e-5
            && (m[2] - 0.5).abs() < 1e-5));
    }

    #[test]
    fn sky_is_brightest_near_the_sun_and_grey_below_the_horizon() {
        let sky = EnvMap::builtin(BUILTIN_SKY).unwrap();
        let p = SkyParams::default();
        let sun = uv_to_direction(p.sun_u, (90.0 - p.sun_elevation_deg) / 180.0);
        let away = rotate_y(sun, 180.0);
        let near = sky.radiance(sun)[0];
        assert!(near > 3.0 * sky.radiance(away)[0], "{near}");
        assert!((sky.radiance(Vec3::Y)[2] - p.zenith * p.zenith_tint[2]).abs() < 0.1);
        let g = sky.radiance(-Vec3::Y);
        assert!(g[0] > 0.0 && g[0] == g[1] && g[1] == g[2]);
        assert!(EnvMap::builtin("builtin:nope").is_err());
    }

    #[test]
    fn cie_clear_sky_is_one_at_the_zenith() {
        for zs in [0.2f32, 0.7, 1.2] {
            assert!((cie_clear_sky(0.0, zs, zs) - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn hdr_files_load_and_bad_ones_are_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("map.hdr");
        let (w, h) = (8usize, 4usize);
        let px: Vec<image::Rgb<f32>> = (0..w * h)
            .map(|i| image::Rgb([i as f32 * 0.25, 1.0, 2.0]))
            .collect();
        let f = std::fs::File::create(&path).unwrap();
        image::codecs::hdr::HdrEncoder::new(std::io::BufWriter::new(f))
            .encode(&px, w, h)
            .unwrap();
        let map = EnvMap::load_hdr(&path).unwrap();
        assert_eq!((map.width(), map.height()), (8, 4));
        // RGBE keeps about 1% precision.
        let t = map.texel(5, 2);
        assert!(
            (t[0] - 21.0 * 0.25).abs() < 0.05 && (t[2] - 2.0).abs() < 0.02,
            "{t:?}"
        );

        let bad = dir.path().join("bad.hdr");
        std::fs::write(&bad, b"this is not an image").unwrap();
        let e = EnvMap::load_hdr(&bad).unwrap_err().to_string();
        assert!(
            e.contains("bad.hdr") && e.contains("not a valid Radiance .hdr"),
            "{e}"
        );
        // A valid header with the pixels cut off.
        let mut bytes = std::fs::read(&path).unwrap();
        bytes.truncate(bytes.len() - 20);
        let cut = dir.path().join("cut.hdr");
        std::fs::write(&cut, &bytes).unwrap();
        let e = EnvMap::load_hdr(&cut).unwrap_err().to_string();
        assert!(e.contains("cut.hdr"), "{e}");
        let e = EnvMap::load_hdr(&dir.path().join("missing.hdr"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("missing.hdr") && e.contains("cannot read"),
            "{e}"
        );
    }
}
