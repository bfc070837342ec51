//! Schemas that the route descriptions ([`crate::openapi`]) name and no body type of the
//! server carries: a binary answer, the upload's multipart form, the routes' path and
//! query parameters.
//!
//! In: nothing. Out: [`Binary`], [`UploadForm`] and the parameters, for `#[utoipa::path]`
//! annotations.

use utoipa::ToSchema;
use utoipa::openapi::RefOr;

/// A binary body: a PNG, an OpenEXR, little-endian floats.
#[derive(Debug)]
pub struct Binary;

impl utoipa::PartialSchema for Binary {
    fn schema() -> RefOr<utoipa::openapi::schema::Schema> {
        use utoipa::openapi::schema::{KnownFormat, ObjectBuilder, SchemaFormat, Type};
        ObjectBuilder::new()
            .schema_type(Type::String)
            .format(Some(SchemaFormat::KnownFormat(KnownFormat::Binary)))
            .description(Some("Binary data."))
            .into()
    }
}

impl ToSchema for Binary {}

/// The form of `POST /api/v1/scenes` (`multipart/form-data`; docs/team.md).
#[derive(Debug, ToSchema)]
#[allow(dead_code)]
pub struct UploadForm {
    /// The scene file (JSON, as for translux-precompute; a file name ending `.json`). Its
    /// mesh paths must be plain names of uploaded files.
    #[schema(value_type = String, format = Binary)]
    scene: (),
    /// Meshes (`.obj`, `.ply`, `.gltf` with the `.bin` buffers it names, `.glb`) and MTL
    /// files, any number.
    #[schema(value_type = Option<Vec<String>>, format = Binary)]
    mesh: (),
    /// The scene id to serve it under (default: the scene file's name without `.json`):
    /// a letter or digit, then up to 63 letters, digits, `_` or `-`.
    #[schema(pattern = "^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")]
    id: Option<String>,
    /// Patch target, overriding the file's (not with `max_edge`).
    #[schema(minimum = 1)]
    patches: Option<u64>,
    /// Largest patch edge in scene units, overriding the file's (not with `patches`).
    max_edge: Option<f32>,
}

/// `{id}` of a scene route.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
pub(crate) struct SceneIdParam {
    /// The scene id: its bundle's folder name.
    id: String,
}

/// `?frame=K` of a scene route.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)]
pub(crate) struct FrameParam {
    /// The frame of an animated scene (0-based; absent: 0). Not a whole number: 400
    /// `bad_request`; out of range: 400 `invalid`.
    frame: Option<u32>,
}

/// `X-Client-Id` of a relight or render.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Header)]
#[allow(dead_code)]
pub(crate) struct ClientIdParam {
    /// Groups requests into one client for the queue's fair (round-robin) order (at most
    /// 64 bytes kept); default: the connection. With tokens the client is the token's name.
    #[param(rename = "X-Client-Id")]
    client_id: Option<String>,
}
