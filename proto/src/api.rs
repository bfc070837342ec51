//! The HTTP API's JSON bodies, shared by the server, scripts and tests.
//!
//! Requests are strict (`deny_unknown_fields`: a misspelt field is an error, never silently
//! ignored); responses are plain data that clients may read with extra fields ignored.
//!
//! ```
//! use translux_proto::api::{Components, RelightRequest, Solver};
//! let req: RelightRequest = translux_proto::parse_json(
//!     r#"{"lights":[{"type":"point","position":[0,1,0],"intensity":[5,5,5]}],"components":"direct"}"#,
//! ).unwrap();
//! assert_eq!(req.components, Components::Direct);
//! assert_eq!(req.solver, Solver::Auto);
//! assert!(req.materials.is_empty());
//! // An empty body means "the bundle's default lights, full transport".
//! assert_eq!(translux_proto::parse_json::<RelightRequest>("{}").unwrap(), RelightRequest::default());
//! ```

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::bundle::{FormFactorInfo, StageTime};
use crate::light::{Camera, Light};
use crate::scene::Material;

/// Which light paths a relight includes (the paper's Figures 5 and 12: components and
/// heuristics). P = diag ρ̄ is each patch's opaque albedo (a translucent patch's profile's
/// total diffuse reflectance); docs/transport.md defines each.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum Components {
    /// Everything: B = Bₑ + S(E + F B).
    #[default]
    Full,
    /// Direct lighting, one local diffuse bounce: B = Bₑ + P E.
    Direct,
    /// Subsurface scattering of direct light, no inter-reflection: B = Bₑ + S E.
    SubsurfaceOnly,
    /// Diffuse inter-reflection with translucent objects opaque: B = Bₑ + P(E + F B).
    InterreflectionOnly,
    /// The paper's (I − F)⁻¹ S L: one subsurface bounce of direct light, then diffuse
    /// inter-reflection: B = (I − P F)⁻¹(Bₑ + S E).
    HeuristicA,
    /// The paper's S L + (I − F)⁻¹ L: subsurface scattering of direct light plus diffuse
    /// inter-reflection: B = Bₑ + S E + (I − P F)⁻¹ P F (Bₑ + P E).
    HeuristicB,
}

impl Components {
    /// The name used in JSON.
    pub fn as_str(self) -> &'static str {
        match self {
            Components::Full => "full",
            Components::Direct => "direct",
            Components::SubsurfaceOnly => "subsurface_only",
            Components::InterreflectionOnly => "interreflection_only",
            Components::HeuristicA => "heuristic_a",
            Components::HeuristicB => "heuristic_b",
        }
    }
}

/// How the transport equation is solved.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum Solver {
    /// The server picks (the transfer matrix T where the bundle has one, else iterative).
    #[default]
    Auto,
    /// Multiply by the precomputed T = (I − S F)⁻¹ S.
    Inverse,
    /// Iterate B ← S(E + F B) to the tolerance.
    Iterative,
}

impl Solver {
    /// The name used in JSON.
    pub fn as_str(self) -> &'static str {
        match self {
            Solver::Auto => "auto",
            Solver::Inverse => "inverse",
            Solver::Iterative => "iterative",
        }
    }
}

/// `POST /api/v1/scenes/{id}/relight`. Every field is optional; `{}` relights with the
/// bundle's default lights and full transport.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(deny_unknown_fields)]
pub struct RelightRequest {
    /// The lights; absent (or `null`) means the bundle's default lights, `[]` means none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lights: Option<Vec<Light>>,
    /// Material overrides by object name.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub materials: BTreeMap<String, Material>,
    #[serde(default)]
    pub components: Components,
    #[serde(default)]
    pub solver: Solver,
    /// Where the direct light of diffuse objects is evaluated (default `vertex`). With
    /// `pixel`, the answer leaves out the direct term ρE/π of the point, spot and directional
    /// lights at the vertices of diffuse objects, for a client that adds it per pixel with
    /// its own shadows (the viewer does); the rest of the transport is unchanged.
    #[serde(default, skip_serializing_if = "DirectAt::is_vertex")]
    pub direct_at: DirectAt,
    /// The frame of an animated scene (0-based; absent: frame 0). A frame out of range is
    /// a 400 that names it; a still scene has frame 0 only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<u32>,
    /// Walk the lamps' own beams into the simulated objects, this many walks per lamp
    /// (1..=10,000,000, shared out over the lit patches by the power they receive), instead
    /// of modelling their first scattering from the stored walks (docs/transport.md, *A
    /// lamp's own beams*). Seconds to minutes for a new set of lights, kept for the next
    /// relights with the same lights (an absorption change re-weights them). Absent: the
    /// model alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lamp_walks: Option<u32>,
}

/// Where the direct light of diffuse objects is evaluated (docs/transport.md).
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum DirectAt {
    /// At each vertex, interpolated across triangles with the rest of the transport.
    #[default]
    Vertex,
    /// Per pixel, by whoever draws the picture: a relight answer then holds the rest.
    Pixel,
}

impl DirectAt {
    pub fn is_vertex(&self) -> bool {
        *self == DirectAt::Vertex
    }
}

fn pixel() -> DirectAt {
    DirectAt::Pixel
}

/// The tone curve that maps exposed linear radiance to display values (before the sRGB
/// encoding) in renders and exports.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum ToneMap {
    /// Clamp to [0, 1]: what a plain sRGB display shows.
    #[default]
    Srgb,
    /// The ACES filmic curve (Narkowicz's 2016 fit): a soft shoulder instead of clipping.
    Filmic,
}

impl ToneMap {
    /// The name used in JSON and on the command line.
    pub fn as_str(self) -> &'static str {
        match self {
            ToneMap::Srgb => "srgb",
            ToneMap::Filmic => "filmic",
        }
    }
}

impl std::str::FromStr for ToneMap {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "srgb" => Ok(ToneMap::Srgb),
            "filmic" => Ok(ToneMap::Filmic),
            other => Err(format!(
                "unknown tone map {other:?}; expected \"srgb\" or \"filmic\""
            )),
        }
    }
}

/// How bright a render or export is: a number of EV stops (radiance × 2^EV before the tone
/// curve), or `"auto"`: the exposure the viewer picks, computed from the relit radiance
/// (`translux_engine::render::auto_exposure`: the 95th percentile of vertex luminance
/// near 0.8, rounded to 0.1 EV). In JSON a number or the string `"auto"`; on the command
/// line `auto` or a number.
///
/// ```
/// use translux_proto::api::Exposure;
/// assert_eq!(translux_proto::parse_json::<Exposure>("-1.5").unwrap(), Exposure::Ev(-1.5));
/// assert_eq!(translux_proto::parse_json::<Exposure>(r#""auto""#).unwrap(), Exposure::Auto);
/// assert_eq!("auto".parse::<Exposure>(), Ok(Exposure::Auto));
/// assert_eq!("-2".parse::<Exposure>(), Ok(Exposure::Ev(-2.0)));
/// assert_eq!(serde_json::to_string(&Exposure::Auto).unwrap(), r#""auto""#);
/// ```
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub enum Exposure {
    /// The viewer's automatic exposure for the relit scene (the default).
    #[default]
    Auto,
    /// EV stops, as given (checked where used: finite and within ±64).
    Ev(f32),
}

impl Exposure {
    /// `Some(ev)` for a number, `None` for `auto`.
    pub fn ev(self) -> Option<f32> {
        match self {
            Exposure::Auto => None,
            Exposure::Ev(ev) => Some(ev),
        }
    }
}

impl From<f32> for Exposure {
    fn from(ev: f32) -> Self {
        Exposure::Ev(ev)
    }
}

impl std::fmt::Display for Exposure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Exposure::Auto => f.write_str("auto"),
            Exposure::Ev(ev) => write!(f, "{ev}"),
        }
    }
}

impl std::str::FromStr for Exposure {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim();
        if s == "auto" {
            return Ok(Exposure::Auto);
        }
        s.parse::<f32>()
            .map(Exposure::Ev)
            .map_err(|_| format!("exposure {s:?} is neither \"auto\" nor a number of EV stops"))
    }
}

impl Serialize for Exposure {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Exposure::Auto => s.serialize_str("auto"),
            Exposure::Ev(ev) => s.serialize_f32(*ev),
        }
    }
}

/// A number or `"auto"` (serialised by hand, so described by hand).
#[cfg(feature = "openapi")]
impl utoipa::PartialSchema for Exposure {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        use utoipa::openapi::schema::{
            ObjectBuilder, OneOfBuilder, SchemaFormat, SchemaType, Type,
        };
        OneOfBuilder::new()
            .item(
                ObjectBuilder::new()
                    .schema_type(SchemaType::Type(Type::Number))
                    .format(Some(SchemaFormat::KnownFormat(
                        utoipa::openapi::KnownFormat::Float,
                    )))
                    .description(Some("EV stops: radiance × 2^EV before the tone curve.")),
            )
            .item(
                ObjectBuilder::new()
                    .schema_type(SchemaType::Type(Type::String))
                    .enum_values(Some(["auto"]))
                    .description(Some("The viewer's automatic exposure for the relit scene.")),
            )
            .description(Some(
                "How bright a render is: a number of EV stops, or \"auto\" (the default).",
            ))
            .into()
    }
}

#[cfg(feature = "openapi")]
impl utoipa::ToSchema for Exposure {}

/// Hand-written rather than `#[serde(untagged)]`: untagged enums answer any mismatch with
/// "data did not match any variant", which names neither choice.
impl<'de> Deserialize<'de> for Exposure {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = Exposure;

            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("a number of EV stops or \"auto\"")
            }

            // Numbers become f32 as serde's own f32 does (`as`): out-of-range values turn
            // infinite and are refused by the range check where the exposure is used.
            fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<Exposure, E> {
                Ok(Exposure::Ev(v as f32))
            }

            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<Exposure, E> {
                Ok(Exposure::Ev(v as f32))
            }

            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<Exposure, E> {
                Ok(Exposure::Ev(v as f32))
            }

            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<Exposure, E> {
                if v == "auto" {
                    Ok(Exposure::Auto)
                } else {
                    Err(E::invalid_value(serde::de::Unexpected::Str(v), &self))
                }
            }
        }
        d.deserialize_any(Visitor)
    }
}

/// Default `width` of a render, in pixels.
pub const DEFAULT_RENDER_WIDTH: u32 = 800;
/// Default `height` of a render, in pixels.
pub const DEFAULT_RENDER_HEIGHT: u32 = 600;

/// `POST /api/v1/scenes/{id}/render`: a relight request plus how to picture it; the answer
/// is a PNG. Every field is optional; `{}` renders the bundle's default lights from its
/// camera at 800 × 600, auto-exposed as the viewer would.
///
/// The relight fields (`lights`, `materials`, `components`, `solver`) sit at the top level,
/// next to the picture's, and mean what they mean in [`RelightRequest`];
/// [`RenderRequest::relight`] splits them off. They are repeated here rather than
/// `#[serde(flatten)]`ed from a `RelightRequest`: serde cannot combine `flatten` with
/// `deny_unknown_fields` (a misspelt field would be ignored), and a flattened field loses its
/// path in error messages. A test checks that every relight request is also a render request.
///
/// ```
/// use translux_proto::api::{Exposure, RenderRequest, ToneMap};
/// let req: RenderRequest = translux_proto::parse_json(
///     r#"{"components":"direct","width":320,"height":240,"tone":"filmic","exposure":1,
///         "camera":{"position":[0,0.3,1.3],"target":[0,0.3,0]}}"#,
/// ).unwrap();
/// assert_eq!((req.width, req.height, req.tone), (320, 240, ToneMap::Filmic));
/// assert_eq!(req.exposure, Exposure::Ev(1.0));
/// assert_eq!(req.relight().components.as_str(), "direct");
/// assert!(translux_proto::parse_json::<RenderRequest>(r#"{"widht":3}"#).is_err());
/// ```
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[cfg_attr(
    feature = "openapi",
    schema(
        description = "`POST /api/v1/scenes/{id}/render`: the relight request's fields \
                          plus how to picture it. Every field is optional; `{}` renders the \
                          bundle's default lights from its camera at 800 × 600, \
                          auto-exposed as the viewer would."
    )
)]
#[serde(deny_unknown_fields)]
pub struct RenderRequest {
    /// As in [`RelightRequest::lights`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lights: Option<Vec<Light>>,
    /// As in [`RelightRequest::materials`].
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub materials: BTreeMap<String, Material>,
    #[serde(default)]
    pub components: Components,
    #[serde(default)]
    pub solver: Solver,
    /// The viewpoint; absent means the bundle's camera.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<Camera>,
    /// Pixels, 1..=8192.
    #[serde(default = "default_width")]
    pub width: u32,
    /// Pixels, 1..=8192.
    #[serde(default = "default_height")]
    pub height: u32,
    /// EV stops (radiance × 2^exposure before the tone curve), or `"auto"` (the default):
    /// the viewer's automatic exposure for this relight. The answer's `X-Exposure` header
    /// says which number was used.
    #[serde(default)]
    pub exposure: Exposure,
    #[serde(default)]
    pub tone: ToneMap,
    /// Where nothing is seen: linear display RGB in [0, 1] (sRGB-encoded, not exposed or
    /// tone mapped).
    #[serde(default)]
    pub background: [f32; 3],
    /// Skip triangles facing away from the camera, so a closed room is seen from outside
    /// through its near wall.
    #[serde(default = "yes")]
    pub cull_backfaces: bool,
    /// Add the specular pass (glossy highlights of the lights on materials with a
    /// `specular` coat) where the components show direct light leaving the surface.
    #[serde(default = "yes")]
    pub specular: bool,
    /// Where the direct light of diffuse objects is evaluated: `pixel` (the default: per
    /// pixel, with a shadow ray, so shadow edges are sharp) or `vertex` (interpolated from
    /// the vertices, the relight answer's picture).
    #[serde(default = "pixel")]
    pub direct_at: DirectAt,
    /// As in [`RelightRequest::frame`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<u32>,
    /// As in [`RelightRequest::lamp_walks`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lamp_walks: Option<u32>,
}

fn default_width() -> u32 {
    DEFAULT_RENDER_WIDTH
}
fn default_height() -> u32 {
    DEFAULT_RENDER_HEIGHT
}
fn yes() -> bool {
    true
}

impl Default for RenderRequest {
    fn default() -> Self {
        RenderRequest {
            lights: None,
            materials: BTreeMap::new(),
            components: Components::default(),
            solver: Solver::default(),
            camera: None,
            width: DEFAULT_RENDER_WIDTH,
            height: DEFAULT_RENDER_HEIGHT,
            exposure: Exposure::Auto,
            tone: ToneMap::default(),
            background: [0.0; 3],
            cull_backfaces: true,
            specular: true,
            direct_at: DirectAt::Pixel,
            frame: None,
            lamp_walks: None,
        }
    }
}

impl RenderRequest {
    /// The relight part of the request.
    pub fn relight(&self) -> RelightRequest {
        RelightRequest {
            lights: self.lights.clone(),
            materials: self.materials.clone(),
            components: self.components,
            solver: self.solver,
            direct_at: self.direct_at,
            frame: self.frame,
            lamp_walks: self.lamp_walks,
        }
    }

    /// A render request with `relight`'s fields and the picture's defaults.
    pub fn from_relight(relight: RelightRequest) -> RenderRequest {
        RenderRequest {
            lights: relight.lights,
            materials: relight.materials,
            components: relight.components,
            solver: relight.solver,
            direct_at: relight.direct_at,
            frame: relight.frame,
            lamp_walks: relight.lamp_walks,
            ..Default::default()
        }
    }
}

/// What a relight did.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct RelightStats {
    /// What computed the transport: `inverse` (one product with the stored T), an
    /// iterative method (`bicgstab`, `jacobi`, `gauss_seidel`), or `none` when nothing was
    /// solved (`direct`, `subsurface_only`).
    pub solver: String,
    pub components: Components,
    pub iterations: u32,
    /// Relative residual ‖b − (I − K F)B‖ / ‖b‖ of the answer (0 without a solve; with T,
    /// 0 here and the stored T's error is in the bundle's manifest).
    pub residual: f32,
    pub converged: bool,
    /// Wall-clock milliseconds for the whole relight (direct + solve + vertex colours).
    pub ms: f64,
    /// Milliseconds computing direct irradiance (with shadow rays).
    pub direct_ms: f64,
    /// Milliseconds in the solver.
    pub solve_ms: f64,
    /// Milliseconds rebuilding S for material overrides (0 when none, or when the same
    /// overrides were applied just before and S came from the cache).
    #[serde(default)]
    pub materials_ms: f64,
    /// Where S for the material overrides was made: `cpu` (on both backends). Absent without
    /// overrides.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub materials_on: Option<String>,
    pub lights: usize,
    /// Passes over F and S (or over T) the transport made.
    #[serde(default)]
    pub products: u32,
    /// Whether the iterative solve started from a previous solution of this scene with the
    /// same materials and components.
    #[serde(default)]
    pub warm: bool,
    /// How many relights shared this transport (one pass over the matrices for all).
    #[serde(default = "one")]
    pub batch: usize,
    /// Why the server took the path it did when `solver` was `auto` and T was not used
    /// (e.g. a translucency change makes T stale).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
    /// With `"direct_at": "pixel"`: the viewer's automatic exposure (EV, the rule of a
    /// render's `"exposure": "auto"`) of the whole answer, its direct light at the vertices
    /// included, which the answer leaves out. A client that adds the direct light per pixel
    /// exposes with this. Absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub auto_exposure: Option<f32>,
    /// Present when the GPU did the whole relight (direct light, solve and vertex colours
    /// in one submission): what it took on the device. Absent on the CPU stages.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device: Option<DeviceStats>,
}

/// What a relight took on the GPU ([`RelightStats::device`]): done whole there, or solved
/// there with S of its materials written there.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct DeviceStats {
    /// Command submissions (1 for a whole relight when the iterations recorded up front
    /// sufficed; a translucency change written on the device adds 2).
    pub submissions: u32,
    /// Bytes the host wrote to the device (the lights, the solve's parameters; E and Bₑ, and
    /// a translucency change's tables and factors, where S of the materials is written).
    pub bytes_up: u64,
    /// Bytes read back (the vertex colours or B, the solve's counter and residual history,
    /// a translucency change's column and node sums).
    pub bytes_down: u64,
}

fn one() -> usize {
    1
}

/// The JSON form of a relight answer.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct RelightResponse {
    pub vertex_count: usize,
    /// Linear outgoing radiance B/π, `[r, g, b]` per vertex of the mesh endpoint, flat.
    pub radiance: Vec<f32>,
    pub stats: RelightStats,
}

/// One entry of `GET /api/v1/scenes`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct SceneSummary {
    /// The bundle's folder name.
    pub id: String,
    /// The scene's name from the manifest.
    pub name: String,
    pub patches: u64,
    pub vertices: u64,
    pub objects: usize,
    /// Frames of an animated scene (1 for a still one); `patches` and `vertices` are frame
    /// 0's.
    #[serde(default = "one_frame")]
    pub frames: u32,
    /// Playback rate of an animated scene.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fps: Option<f32>,
}

fn one_frame() -> u32 {
    1
}

/// `GET /api/v1/presets`: the named media a material may give (`"preset": NAME` in a
/// `dipole` profile or a `simulated` material), and the indices used where none is given.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Presets {
    /// Jensen et al. 2001's measured media, in the order [`crate::scene::DIPOLE_PRESETS`]
    /// lists them.
    pub dipole: Vec<DipolePreset>,
    /// The relative index η of a dipole given by its coefficients without `eta`.
    pub default_eta: f32,
    /// η of a specular coat whose material states none and has no dipole to take it from.
    pub default_coat_eta: f32,
}

/// One measured medium of [`Presets`].
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct DipolePreset {
    pub name: String,
    /// Reduced scattering coefficient σs′ per channel (R, G, B), mm⁻¹.
    pub sigma_s_prime: [f32; 3],
    /// Absorption coefficient σa per channel, mm⁻¹.
    pub sigma_a: [f32; 3],
    /// Relative index of refraction η.
    pub eta: f32,
}

/// `GET /api/v1/scenes`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct SceneList {
    pub scenes: Vec<SceneSummary>,
}

/// One object in `GET /api/v1/scenes/{id}`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct SceneObject {
    pub name: String,
    pub material: Material,
    /// ρ the diffuse solver uses for its patches.
    pub albedo: [f32; 3],
    pub first_patch: u64,
    pub patch_count: u64,
    /// For a simulated object: the absorption its walks were weighted for and the lowest one
    /// an override is served with (no new walks); absent for other materials.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub absorption: Option<Absorption>,
}

/// The absorption range of a simulated object's stored walks (mm⁻¹ per channel).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Absorption {
    /// σa of the scene file (the preset's where the file gives none).
    pub sigma_a: [f32; 3],
    /// The lowest σa an override may ask for (σa / 16 at precompute).
    pub sigma_a_min: [f32; 3],
}

/// Where a scene stands in making what its first translucency change needs: S's entries
/// reduced to radial terms on the CPU, on both backends
/// (`GET /api/v1/scenes/{id}`'s `translucency`). Without it made, the first change makes
/// it and waits (seconds to minutes on large objects); the server makes it in the
/// background instead (`docs/api.md#translucency-preparation`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct TranslucencyPrep {
    pub state: PrepState,
    /// Where translucency changes make S (`cpu`), once known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub on: Option<String>,
    /// Seconds the preparation took.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f64>,
    /// Host bytes it holds (the CPU's radial terms).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bytes: Option<u64>,
    /// Why it failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
}

/// [`TranslucencyPrep`]'s state.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq, Default)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum PrepState {
    /// No translucent object or thin sheet: nothing to prepare (a heterogeneous object's S
    /// is rebuilt without it).
    None,
    /// Not started: made by the first translucency change, or in the background soon.
    #[default]
    Pending,
    /// Being made now (a translucency change asked meanwhile waits for it).
    Preparing,
    Ready,
    Failed,
}

/// `GET /api/v1/scenes/{id}`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct SceneDetail {
    pub id: String,
    pub name: String,
    /// What the bundle was built from: `builtin:cornell`, `upload:JOB/FILE`, or a scene
    /// file's name (never a path on the server).
    pub source: String,
    pub created_by: String,
    /// Millimetres per scene unit.
    pub unit_mm: f64,
    pub patches: u64,
    pub vertices: u64,
    /// Triangles of the viewer mesh (one per patch).
    pub triangles: u64,
    /// Source triangles used for shadow rays.
    pub occluders: u64,
    pub objects: Vec<SceneObject>,
    /// The lights a relight without `lights` uses.
    pub lights: Vec<Light>,
    pub camera: Camera,
    pub form_factors: FormFactorInfo,
    pub stages: Vec<StageTime>,
    /// Bytes of the bundle on disk (every frame's for an animated scene).
    pub bundle_bytes: u64,
    /// Frames of an animated scene (1 for a still one); the rest describes the frame asked
    /// for (`?frame=K`, default 0).
    #[serde(default = "one_frame")]
    pub frames: u32,
    /// Playback rate of an animated scene.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fps: Option<f32>,
    /// The frame described.
    #[serde(default)]
    pub frame: u32,
    /// Whether the first translucency change will find what it needs made.
    #[serde(default)]
    pub translucency: TranslucencyPrep,
}

/// One object's triangle range in `GET /api/v1/scenes/{id}/mesh`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct MeshObject {
    pub name: String,
    pub first_triangle: u64,
    pub triangle_count: u64,
}

/// `GET /api/v1/scenes/{id}/mesh`: flat arrays, 3 floats per vertex, 3 indices per triangle.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Mesh {
    pub positions: Vec<f32>,
    pub normals: Vec<f32>,
    pub indices: Vec<u32>,
    pub objects: Vec<MeshObject>,
}

/// The GPU part of `GET /healthz`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct GpuHealth {
    pub available: bool,
    /// Why there is no GPU (absent when there is one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// The adapter relights run on (absent without a GPU).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adapter: Option<GpuAdapter>,
    /// GPU bytes held by all scenes.
    #[serde(default)]
    pub bytes: u64,
    /// Each scene the GPU backend has seen: on the device, or served from the CPU and why.
    #[serde(default)]
    pub scenes: Vec<GpuScene>,
}

/// The adapter in [`GpuHealth`].
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct GpuAdapter {
    pub name: String,
    /// wgpu's backend: `vulkan`, …
    pub backend: String,
    /// `discrete`, `integrated`, `virtual`, `cpu` or `other`.
    pub device_type: String,
    /// A software adapter (lavapipe, llvmpipe): it runs on the CPU.
    pub software: bool,
    /// The largest storage binding; bigger matrices are split into row blocks.
    pub max_binding_bytes: u64,
}

/// One scene in [`GpuHealth`].
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct GpuScene {
    pub id: String,
    /// `gpu`, or `cpu` for a scene that does not fit (see `reason`).
    pub on: String,
    pub bytes: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// `GET /healthz`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Health {
    /// Always `ok` (a stopping server answers 503 `shutting_down` instead of this report).
    pub status: String,
    /// `cpu` or `gpu`.
    pub backend: String,
    pub gpu: GpuHealth,
    /// Ids of the scenes served.
    pub scenes: Vec<String>,
}

/// The inside of every error answer.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Eq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ErrorDetail {
    /// Machine-readable and stable: `bad_request` (400: the body, form, query or id is not
    /// readable or not the request's shape), `invalid` (400: a value breaks a rule; the
    /// message names the field), `unsupported` (400: valid, but this bundle or build cannot
    /// do it), `unauthorized` (401), `forbidden` (403), `not_found` (404: unknown scene, job
    /// or route), `method_not_allowed` (405), `not_acceptable` (406), `conflict` (409),
    /// `payload_too_large` (413), `unsupported_media_type` (415), `work_limit` (422: the
    /// request's work ran past its role's limit), `upgrade_required` (426: a plain GET on
    /// the WebSocket route), `queue_full` and `rate_limited` (429, with `Retry-After`),
    /// `internal` (500: a bug or a server-side I/O failure, never bad input), `loading`,
    /// `deadline_exceeded`, `shutting_down` and `cancelled` (503).
    pub code: String,
    /// What was wrong and where (`lights[0].intensity[1] must be finite and in [0, 1000000000000]`).
    pub message: String,
}

/// Every 4xx/5xx answer: `{"error":{"code":"...","message":"..."}}`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Eq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

/// OpenAPI schemas of the body types that live outside this module ([`Light`], [`Camera`],
/// [`Material`] and what it holds, the manifest's [`FormFactorInfo`] and [`StageTime`]).
///
/// Those files are decoded through hand-written mirrors ([`crate::tagged`]), which a
/// `ToSchema` derive cannot see, so each is described here by a twin with the same serde
/// shape that derives its schema; the real type's schema is its twin's. The test below
/// keeps the twins honest: a value of every variant, with every optional field set, must
/// survive real → JSON → twin → JSON unchanged (the twins deny unknown fields), and the
/// real type must read it back.
#[cfg(feature = "openapi")]
mod twins {
    #![allow(dead_code)]

    use serde::{Deserialize, Serialize};
    use utoipa::ToSchema;

    /// A light; the units are the scene's (W/sr, W/m², W·m⁻²·sr⁻¹).
    #[derive(Debug, Serialize, Deserialize, ToSchema)]
    #[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
    pub enum Light {
        /// Intensity W/sr in every direction.
        Point {
            position: [f32; 3],
            intensity: [f32; 3],
        },
        /// A point light in a cone: full intensity inside `inner_deg` of `direction`, none
        /// outside `outer_deg` (half-angles, 0..=180).
        Spot {
            position: [f32; 3],
            intensity: [f32; 3],
            direction: [f32; 3],
            inner_deg: f32,
            outer_deg: f32,
        },
        /// Parallel light along `direction` with irradiance W/m² (a sun).
        Directional {
            direction: [f32; 3],
            irradiance: [f32; 3],
        },
        /// Light from every direction: `builtin:sky`, `builtin:white`, or a Radiance `.hdr`
        /// file as a relative path inside the bundles folder (docs/environment.md); `scale`
        /// multiplies its radiance, `rotation_deg` turns it about +Y.
        Environment {
            map: String,
            #[serde(default = "one")]
            scale: f32,
            #[serde(default)]
            rotation_deg: f32,
        },
    }

    fn one() -> f32 {
        1.0
    }

    /// A pinhole camera.
    #[derive(Debug, Serialize, Deserialize, ToSchema)]
    #[serde(deny_unknown_fields)]
    pub struct Camera {
        pub position: [f32; 3],
        pub target: [f32; 3],
        /// Default `[0, 1, 0]`.
        #[serde(default)]
        pub up: [f32; 3],
        /// Vertical field of view in degrees (default 40).
        #[serde(default)]
        pub fov_deg: f32,
    }

    /// What a surface does with light (docs/scenes.md).
    #[derive(Debug, Serialize, Deserialize, ToSchema)]
    #[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
    pub enum Material {
        /// Opaque Lambertian: S_ii = albedo.
        Diffuse {
            albedo: [f32; 3],
            #[serde(default, skip_serializing_if = "Option::is_none")]
            specular: Option<Specular>,
        },
        /// Subsurface scattering through the object, described by a 1-D profile.
        Translucent {
            profile: Profile,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            specular: Option<Specular>,
        },
        /// A thin two-sided sheet (a petal, a leaf, paper) of constant thickness.
        ThinSheet {
            reflectance: Profile,
            transmittance: Profile,
            thickness_mm: f32,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            specular: Option<Specular>,
        },
        /// A Lambertian emitter of constant radiance (W·m⁻²·sr⁻¹); it reflects nothing.
        Emitter { radiance: [f32; 3] },
        /// A translucent object made of 2 to 4 homogeneous media laid out by `pattern`.
        Heterogeneous {
            materials: Vec<Profile>,
            pattern: Pattern,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            specular: Option<Specular>,
        },
        /// A translucent object whose S is simulated by random walks inside its mesh: a
        /// Jensen `preset` or coefficients in mm⁻¹.
        Simulated {
            #[serde(default, skip_serializing_if = "Option::is_none")]
            preset: Option<String>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            sigma_a: Option<[f32; 3]>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            sigma_s_prime: Option<[f32; 3]>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            sigma_s: Option<[f32; 3]>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            g: Option<f32>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            eta: Option<f32>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            noise: Option<f32>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            max_walks: Option<u32>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            seed: Option<u64>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            specular: Option<Specular>,
        },
    }

    /// A glossy GGX coat evaluated per pixel; it does not change the radiosity answer.
    #[derive(Debug, Serialize, Deserialize, ToSchema)]
    #[serde(deny_unknown_fields)]
    pub struct Specular {
        /// Perceptual roughness in [0.01, 1].
        pub roughness: f32,
        /// Relative index of refraction in [1, 3].
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub eta: Option<f32>,
    }

    /// A 1-D diffuse reflectance profile R(r) per RGB channel.
    #[derive(Debug, Serialize, Deserialize, ToSchema)]
    #[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
    pub enum Profile {
        /// The dipole of Jensen et al. 2001: a `preset`, or `sigma_a` and `sigma_s_prime`
        /// (mm⁻¹) with `eta`; `scale` multiplies the mean free path.
        Dipole {
            #[serde(default, skip_serializing_if = "Option::is_none")]
            preset: Option<String>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            sigma_a: Option<[f32; 3]>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            sigma_s_prime: Option<[f32; 3]>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            eta: Option<f32>,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            scale: Option<f32>,
        },
        /// A measured table: R at `radius_mm[k]` is `values[k]` (mm⁻², RGB).
        Table {
            radius_mm: Vec<f32>,
            values: Vec<[f32; 3]>,
        },
        /// R(r) = Σ a_k e^(−b_k r).
        Exponentials { terms: Vec<ExpTerm> },
    }

    /// One term a·e^(−b r) of an exponential-sum profile.
    #[derive(Debug, Serialize, Deserialize, ToSchema)]
    #[serde(deny_unknown_fields)]
    pub struct ExpTerm {
        pub a: [f32; 3],
        pub b: [f32; 3],
    }

    /// Which medium of a heterogeneous object is where.
    #[derive(Debug, Serialize, Deserialize, ToSchema)]
    #[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
    pub enum Pattern {
        /// A 3-D checkerboard of cubic cells of edge `cell` (scene units).
        Checkerboard {
            cell: f32,
            #[serde(default)]
            origin: [f32; 3],
        },
        /// Media by the OBJ's `usemtl` groups.
        ByObjMaterial { names: Vec<String> },
    }

    /// How F was computed, and what was dropped.
    #[derive(Debug, Serialize, Deserialize, ToSchema)]
    #[serde(deny_unknown_fields)]
    pub struct FormFactorInfo {
        pub nnz: u64,
        /// Entries below this were dropped (0: none).
        pub threshold: f32,
        /// Fraction of all power leaving patches that the dropped entries carried.
        pub dropped_energy: f64,
        /// Row sums Σ_j F_ij: mean, min, max.
        pub row_sum_mean: f64,
        pub row_sum_min: f64,
        pub row_sum_max: f64,
        /// Occlusion rays cast.
        pub rays: u64,
        /// Patch pairs considered after orientation culling.
        pub pairs: u64,
    }

    /// Wall-clock time of one precompute stage.
    #[derive(Debug, Serialize, Deserialize, ToSchema)]
    #[serde(deny_unknown_fields)]
    pub struct StageTime {
        pub stage: String,
        pub seconds: f64,
    }
}

/// `ToSchema` of `$real` from its twin in [`twins`].
#[cfg(feature = "openapi")]
macro_rules! schema_from_twin {
    ($($real:ty => $twin:ty),* $(,)?) => {$(
        impl utoipa::PartialSchema for $real {
            fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
                <$twin as utoipa::PartialSchema>::schema()
            }
        }

        impl utoipa::ToSchema for $real {
            fn name() -> std::borrow::Cow<'static, str> {
                <$twin as utoipa::ToSchema>::name()
            }

            fn schemas(
                schemas: &mut Vec<(
                    String,
                    utoipa::openapi::RefOr<utoipa::openapi::schema::Schema>,
                )>,
            ) {
                <$twin as utoipa::ToSchema>::schemas(schemas)
            }
        }
    )*};
}

#[cfg(feature = "openapi")]
schema_from_twin! {
    Light => twins::Light,
    Camera => twins::Camera,
    Material => twins::Material,
    FormFactorInfo => twins::FormFactorInfo,
    StageTime => twins::StageTime,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::parse_json;

    #[test]
    fn every_relight_request_is_a_render_request() {
        // Every field of RelightRequest set to a non-default value: if RelightRequest gains
        // a field that RenderRequest lacks, this stops parsing (deny_unknown_fields).
        let relight: RelightRequest = parse_json(
            r#"{"lights":[{"type":"point","position":[0,1,0],"intensity":[1,2,3]}],
                "materials":{"block":{"type":"diffuse","albedo":[1,0,0]}},
                "components":"direct","solver":"iterative","direct_at":"pixel"}"#,
        )
        .unwrap();
        let text = serde_json::to_string(&relight).unwrap();
        let render: RenderRequest = parse_json(&text).unwrap();
        assert_eq!(render.relight(), relight);
        assert_eq!(render, RenderRequest::from_relight(relight));
        assert_eq!((render.width, render.height), (800, 600));
        assert!(render.cull_backfaces && render.camera.is_none());
        assert_eq!(
            parse_json::<RenderRequest>("{}").unwrap(),
            RenderRequest::default()
        );

        let e = parse_json::<RenderRequest>(r#"{"width":-1}"#).unwrap_err();
        assert_eq!(e.path, "width", "{e}");
        let e = parse_json::<RenderRequest>(r#"{"tone":"aces"}"#).unwrap_err();
        assert_eq!(e.path, "tone", "{e}");
        let e = parse_json::<RenderRequest>(r#"{"camera":{"position":[0,0,1]}}"#).unwrap_err();
        assert!(e.message.contains("target"), "{e}");
        let e = parse_json::<RenderRequest>(
            r#"{"camera":{"position":[0,0,1],"target":[0,0,0],"fov":3}}"#,
        )
        .unwrap_err();
        assert!(
            e.path.starts_with("camera") && e.message.contains("fov"),
            "{e}"
        );
        let e = parse_json::<RenderRequest>(
            r#"{"lights":[{"type":"point","position":[0,1,0],"intensity":[1,"x",1]}]}"#,
        )
        .unwrap_err();
        assert_eq!(e.path, "lights[0].intensity[1]", "{e}");
        assert_eq!("filmic".parse::<ToneMap>(), Ok(ToneMap::Filmic));
        assert!("aces".parse::<ToneMap>().unwrap_err().contains("aces"));
        let full = RenderRequest {
            camera: Some(Camera {
                position: [0.0, 0.0, 1.0],
                target: [0.0; 3],
                up: [0.0, 1.0, 0.0],
                fov_deg: 30.0,
            }),
            tone: ToneMap::Filmic,
            ..Default::default()
        };
        let back: RenderRequest = parse_json(&serde_json::to_string(&full).unwrap()).unwrap();
        assert_eq!(back, full);
    }

    #[test]
    fn render_exposure_is_a_number_or_auto_and_auto_by_default() {
        assert_eq!(
            parse_json::<RenderRequest>("{}").unwrap().exposure,
            Exposure::Auto
        );
        assert_eq!(RenderRequest::default().exposure, Exposure::Auto);
        for (text, want) in [
            (r#"{"exposure":"auto"}"#, Exposure::Auto),
            (r#"{"exposure":-2.4}"#, Exposure::Ev(-2.4)),
            (r#"{"exposure":3}"#, Exposure::Ev(3.0)),
            (r#"{"exposure":0}"#, Exposure::Ev(0.0)),
        ] {
            let req = parse_json::<RenderRequest>(text).unwrap();
            assert_eq!(req.exposure, want, "{text}");
            // Round trip: auto as "auto", a number as a number.
            let back: RenderRequest = parse_json(&serde_json::to_string(&req).unwrap()).unwrap();
            assert_eq!(back, req);
        }
        let text = serde_json::to_string(&RenderRequest {
            exposure: Exposure::Ev(-1.5),
            ..Default::default()
        })
        .unwrap();
        assert!(text.contains(r#""exposure":-1.5"#), "{text}");
        // Anything else is refused at the field, naming both choices.
        for bad in [
            r#"{"exposure":"bright"}"#,
            r#"{"exposure":null}"#,
            r#"{"exposure":[1]}"#,
        ] {
            let e = parse_json::<RenderRequest>(bad).unwrap_err();
            assert_eq!(e.path, "exposure", "{bad}: {e}");
            assert!(
                e.message.contains(r#"a number of EV stops or "auto""#),
                "{e}"
            );
        }
        // The command line's form.
        assert_eq!("auto".parse::<Exposure>(), Ok(Exposure::Auto));
        assert_eq!("-0.5".parse::<Exposure>(), Ok(Exposure::Ev(-0.5)));
        assert!("bright".parse::<Exposure>().unwrap_err().contains("bright"));
        assert_eq!(Exposure::Ev(-2.4).to_string(), "-2.4");
        assert_eq!(Exposure::Auto.ev(), None);
        assert_eq!(Exposure::from(1.0).ev(), Some(1.0));
    }

    #[test]
    fn relight_request_is_strict_and_names_fields() {
        let e = parse_json::<RelightRequest>(r#"{"light":[]}"#).unwrap_err();
        assert!(e.message.contains("unknown field `light`"), "{e}");
        let e = parse_json::<RelightRequest>(r#"{"components":"everything"}"#).unwrap_err();
        assert_eq!(e.path, "components", "{e}");
        let e = parse_json::<RelightRequest>(
            r#"{"lights":[{"type":"point","position":[0,1,0],"intensity":[1,"x",1]}]}"#,
        )
        .unwrap_err();
        assert_eq!(e.path, "lights[0].intensity[1]", "{e}");
        let r: RelightRequest = parse_json(
            r#"{"lights":null,"materials":{"block":{"type":"diffuse","albedo":[1,0,0]}},"components":"heuristic_b","solver":"inverse"}"#,
        )
        .unwrap();
        assert_eq!(r.lights, None);
        assert_eq!(r.components.as_str(), "heuristic_b");
        assert_eq!(r.solver.as_str(), "inverse");
        assert_eq!(r.materials.len(), 1);
        // Round trip.
        let back: RelightRequest = parse_json(&serde_json::to_string(&r).unwrap()).unwrap();
        assert_eq!(back, r);
    }

    /// Each twin of `twins` has its type's JSON shape: a value of every variant with every
    /// field set goes real → JSON → twin → JSON unchanged, and the JSON is the input. The
    /// `match`es fail to compile when the real enums gain a variant.
    #[cfg(feature = "openapi")]
    #[test]
    fn the_schema_twins_have_the_shape_of_the_real_types() {
        use crate::scene::{Pattern, Profile};
        use serde::de::DeserializeOwned;

        fn same<R: Serialize + DeserializeOwned, T: Serialize + DeserializeOwned>(text: &str) -> R {
            let real: R = parse_json(text).unwrap_or_else(|e| panic!("{text}: {e}"));
            let json = serde_json::to_value(&real).unwrap();
            // Numbers as f64 on both sides (`1` in the text is `1.0` once an f32).
            fn floats(v: &serde_json::Value) -> serde_json::Value {
                use serde_json::Value;
                match v {
                    Value::Number(n) => n.as_f64().map_or(Value::Null, Value::from),
                    Value::Array(a) => Value::Array(a.iter().map(floats).collect()),
                    Value::Object(o) => {
                        Value::Object(o.iter().map(|(k, v)| (k.clone(), floats(v))).collect())
                    }
                    other => other.clone(),
                }
            }
            let input: serde_json::Value = serde_json::from_str(text).unwrap();
            assert_eq!(
                floats(&json),
                floats(&input),
                "a sample must set every field"
            );
            let twin: T = serde_json::from_value(json.clone())
                .unwrap_or_else(|e| panic!("the twin does not read {json}: {e}"));
            assert_eq!(serde_json::to_value(&twin).unwrap(), json);
            real
        }
        let spec = r#""specular":{"roughness":0.5,"eta":1.5}"#;
        let dipole = r#"{"type":"dipole","preset":"marble","sigma_a":[0.5,0.5,0.5],"sigma_s_prime":[2,2,2],"eta":1.25,"scale":2}"#;
        let table = r#"{"type":"table","radius_mm":[0,1],"values":[[1,1,1],[0.5,0.5,0.5]]}"#;
        let exps = r#"{"type":"exponentials","terms":[{"a":[1,1,1],"b":[2,2,2]}]}"#;
        let mut kinds = std::collections::BTreeSet::new();
        for text in [
            r#"{"type":"point","position":[0,1,0],"intensity":[1,2,3]}"#.to_string(),
            r#"{"type":"spot","position":[0,1,0],"intensity":[1,2,3],"direction":[0,-1,0],"inner_deg":10,"outer_deg":20}"#.into(),
            r#"{"type":"directional","direction":[0,-1,0],"irradiance":[1,2,3]}"#.into(),
            r#"{"type":"environment","map":"builtin:sky","scale":2,"rotation_deg":90}"#.into(),
        ] {
            let light: Light = same::<Light, twins::Light>(&text);
            kinds.insert(match light {
                Light::Point { .. } => "point",
                Light::Spot { .. } => "spot",
                Light::Directional { .. } => "directional",
                Light::Environment { .. } => "environment",
            });
        }
        assert_eq!(kinds.len(), 4);
        let mut materials = std::collections::BTreeSet::new();
        let mut profiles = std::collections::BTreeSet::new();
        let mut patterns = std::collections::BTreeSet::new();
        for text in [
            format!(r#"{{"type":"diffuse","albedo":[0.5,0.5,0.5],{spec}}}"#),
            format!(r#"{{"type":"translucent","profile":{dipole},{spec}}}"#),
            format!(
                r#"{{"type":"thin_sheet","reflectance":{table},"transmittance":{exps},"thickness_mm":0.25,{spec}}}"#
            ),
            r#"{"type":"emitter","radiance":[1,2,3]}"#.into(),
            format!(
                r#"{{"type":"heterogeneous","materials":[{dipole},{table}],"pattern":{{"type":"checkerboard","cell":0.5,"origin":[0,1,0]}},{spec}}}"#
            ),
            format!(
                r#"{{"type":"heterogeneous","materials":[{exps},{table}],"pattern":{{"type":"by_obj_material","names":["a","b"]}}}}"#
            ),
            format!(
                r#"{{"type":"simulated","preset":"skin1","sigma_a":[0.5,0.5,0.5],"sigma_s_prime":[1,1,1],"sigma_s":[2,2,2],"g":0.5,"eta":1.25,"noise":0.125,"max_walks":64,"seed":7,{spec}}}"#
            ),
        ] {
            let m: Material = same::<Material, twins::Material>(&text);
            let mut profile = |p: &Profile| {
                profiles.insert(match p {
                    Profile::Dipole { .. } => "dipole",
                    Profile::Table { .. } => "table",
                    Profile::Exponentials { .. } => "exponentials",
                });
            };
            materials.insert(match &m {
                Material::Diffuse { .. } => "diffuse",
                Material::Translucent { profile: p, .. } => {
                    profile(p);
                    "translucent"
                }
                Material::ThinSheet {
                    reflectance,
                    transmittance,
                    ..
                } => {
                    profile(reflectance);
                    profile(transmittance);
                    "thin_sheet"
                }
                Material::Emitter { .. } => "emitter",
                Material::Heterogeneous {
                    materials: ps,
                    pattern,
                    ..
                } => {
                    ps.iter().for_each(&mut profile);
                    patterns.insert(match pattern {
                        Pattern::Checkerboard { .. } => "checkerboard",
                        Pattern::ByObjMaterial { .. } => "by_obj_material",
                    });
                    "heterogeneous"
                }
                Material::Simulated { .. } => "simulated",
            });
        }
        assert_eq!((materials.len(), profiles.len(), patterns.len()), (6, 3, 2));
        same::<Camera, twins::Camera>(
            r#"{"position":[0,1,2],"target":[0,0,0],"up":[0,1,0],"fov_deg":35}"#,
        );
        same::<FormFactorInfo, twins::FormFactorInfo>(
            r#"{"nnz":10,"threshold":0.5,"dropped_energy":0.25,"row_sum_mean":0.5,"row_sum_min":0.25,"row_sum_max":1,"rays":100,"pairs":50}"#,
        );
        same::<StageTime, twins::StageTime>(r#"{"stage":"bvh","seconds":1.5}"#);
    }
}
