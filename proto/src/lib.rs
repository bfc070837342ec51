//! # translux-proto
//!
//! Plain data shared by every translux crate; it depends on serde, bytemuck and memmap2 and
//! never on a web framework or a GPU API.
//!
//! - [`scene`]: the JSON scene file (objects, meshes, materials, profiles), with
//!   [`scene::SceneFile::validate`] naming the field and rule of any bad value.
//! - [`animation`]: animated scenes (frames, per-frame meshes, keyframes) and the
//!   `sequence.json` of their precomputed frames.
//! - [`light`]: lights and cameras, shared by scene files and relight requests.
//! - [`csr`]: the compressed-sparse-row layout of F, with a checked borrowed view.
//! - [`bundle`]: the on-disk bundle — manifest, array files, and the verifying loader.
//! - [`transform`]: an object's placement (scale, rotate, translate), re-exported by
//!   [`scene`].
//! - [`validate`]: in: a parsed value; out: errors that name the field path and the rule,
//!   e.g. `lights[0].intensity[1] must be finite and in [0, 1000000000000]`.
//! - [`api`]: the HTTP API's JSON bodies (strict requests, plain-data responses), shared
//!   by the server, scripts and tests.
//! - `tagged` (private): internally tagged enums (`{"type": ...}`) whose decoding errors
//!   keep the field path.
//! - [`parse_json`]: JSON parsing whose errors carry the field path, line and column.
//!
//! ```
//! let scene: translux_proto::scene::SceneFile = translux_proto::parse_json(
//!     r#"{"objects":[{"name":"floor","mesh":{"shape":"quad","size":[1,1]},
//!        "material":{"type":"diffuse","albedo":[0.5,0.5,0.5]}}]}"#,
//! ).unwrap();
//! scene.validate().unwrap();
//! assert_eq!(scene.unit_mm, 1000.0);
//! ```

pub mod animation;
pub mod api;
pub mod bundle;
pub mod csr;
pub mod light;
pub mod scene;
mod tagged;
pub mod transform;
pub mod validate;

pub use validate::FieldError;

/// A JSON document that could not be read into the expected type.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct JsonError {
    /// Path of the field where decoding failed (`objects[1].material.albedo`), or empty at
    /// the top level.
    pub path: String,
    pub line: usize,
    pub column: usize,
    /// serde's description of the problem.
    pub message: String,
}

impl std::fmt::Display for JsonError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.path.is_empty() || self.path == "." {
            write!(
                f,
                "{} (line {}, column {})",
                self.message, self.line, self.column
            )
        } else {
            write!(
                f,
                "{}: {} (line {}, column {})",
                self.path, self.message, self.line, self.column
            )
        }
    }
}

impl std::error::Error for JsonError {}

/// Parses JSON into `T`, reporting the path of the field that failed. An object that gives
/// a key twice is refused wherever it is ([`check_unique_keys`]): serde would keep the last
/// value of a map's key without a word.
pub fn parse_json<T: serde::de::DeserializeOwned>(text: &str) -> Result<T, JsonError> {
    check_unique_keys(text)?;
    let de = &mut serde_json::Deserializer::from_str(text);
    let parsed = serde_path_to_error::deserialize(&mut *de);
    // `end` refuses anything but whitespace after the value: `{} xyz` is not a JSON body.
    if parsed.is_ok()
        && let Err(e) = de.end()
    {
        return Err(JsonError {
            path: String::new(),
            line: e.line(),
            column: e.column(),
            message: "trailing characters after the JSON value".to_owned(),
        });
    }
    match parsed {
        Ok(v) => Ok(v),
        Err(e) => {
            let mut path = e.path().to_string();
            let inner = e.into_inner();
            // serde_json appends " at line L column C" to its message; keep only the cause.
            let full = inner.to_string();
            let mut message = match full.rfind(" at line ") {
                Some(k) => full[..k].to_string(),
                None => full,
            };
            // Paths from inside tagged enums arrive at the front of the message.
            while let Some(rest) = message.strip_prefix(tagged::PATH_MARK) {
                let Some((sub, msg)) = rest.split_once(tagged::PATH_MARK) else {
                    break;
                };
                path = tagged::join_path(&path, sub);
                message = msg.to_string();
            }
            if path == "." {
                path.clear();
            }
            Err(JsonError {
                path,
                line: inner.line(),
                column: inner.column(),
                message,
            })
        }
    }
}

/// Refuses a JSON text in which any object, at any depth, gives the same key twice; the
/// error names the key's path. Other syntax errors are left to the parse that follows.
pub fn check_unique_keys(text: &str) -> Result<(), JsonError> {
    use serde::de::DeserializeSeed;
    let de = &mut serde_json::Deserializer::from_str(text);
    let mut duplicate = None;
    let result = UniqueKeys {
        path: String::new(),
        duplicate: &mut duplicate,
    }
    .deserialize(&mut *de);
    match (result, duplicate) {
        (Err(e), Some(path)) => Err(JsonError {
            path,
            line: e.line(),
            column: e.column(),
            message: "this key is given twice in its object; give each key once".to_owned(),
        }),
        _ => Ok(()),
    }
}

/// Walks any JSON value, checking each object's keys ([`check_unique_keys`]); the path of
/// the first repeated key goes to `duplicate`.
struct UniqueKeys<'a> {
    path: String,
    duplicate: &'a mut Option<String>,
}

impl UniqueKeys<'_> {
    fn at(&mut self, step: String) -> UniqueKeys<'_> {
        UniqueKeys {
            path: step,
            duplicate: self.duplicate,
        }
    }
}

impl<'de> serde::de::DeserializeSeed<'de> for UniqueKeys<'_> {
    type Value = ();
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_any(self)
    }
}

impl<'de> serde::de::Visitor<'de> for UniqueKeys<'_> {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("any JSON value")
    }
    fn visit_bool<E>(self, _: bool) -> Result<(), E> {
        Ok(())
    }
    fn visit_i64<E>(self, _: i64) -> Result<(), E> {
        Ok(())
    }
    fn visit_u64<E>(self, _: u64) -> Result<(), E> {
        Ok(())
    }
    fn visit_f64<E>(self, _: f64) -> Result<(), E> {
        Ok(())
    }
    fn visit_str<E>(self, _: &str) -> Result<(), E> {
        Ok(())
    }
    fn visit_unit<E>(self) -> Result<(), E> {
        Ok(())
    }
    fn visit_seq<A: serde::de::SeqAccess<'de>>(mut self, mut seq: A) -> Result<(), A::Error> {
        let mut k = 0usize;
        loop {
            let path = format!("{}[{k}]", self.path);
            if seq.next_element_seed(self.at(path))?.is_none() {
                return Ok(());
            }
            k += 1;
        }
    }
    fn visit_map<A: serde::de::MapAccess<'de>>(mut self, mut map: A) -> Result<(), A::Error> {
        let mut seen = std::collections::HashSet::new();
        while let Some(key) = map.next_key::<String>()? {
            let path = if self.path.is_empty() {
                key.clone()
            } else {
                format!("{}.{key}", self.path)
            };
            if !seen.insert(key) {
                *self.duplicate = Some(path);
                return Err(serde::de::Error::custom("duplicate key"));
            }
            map.next_value_seed(self.at(path))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Material, MeshRef, SceneFile, Shape};

    #[test]
    fn a_key_given_twice_is_refused_in_every_object() {
        let e = parse_json::<crate::api::RelightRequest>(
            r#"{"materials": {"block": {"type": "diffuse", "albedo": [1, 0, 0]},
                              "block": {"type": "diffuse", "albedo": [0, 1, 0]}}}"#,
        )
        .unwrap_err();
        assert_eq!(e.path, "materials.block", "{e}");
        assert!(e.message.contains("twice"), "{e}");
        assert_eq!(e.line, 2, "{e}");
        let e =
            parse_json::<serde_json::Value>(r#"[{"a": 1}, {"b": {"c": 1, "c": 2}}]"#).unwrap_err();
        assert_eq!(e.path, "[1].b.c", "{e}");
        // The same key in different objects is fine, and so are other errors' messages.
        assert!(parse_json::<serde_json::Value>(r#"{"a": {"x": 1}, "b": {"x": 1}}"#).is_ok());
        let e = parse_json::<serde_json::Value>(r#"{"a": 1,}"#).unwrap_err();
        assert!(!e.message.contains("twice"), "{e}");
    }

    #[test]
    fn trailing_garbage_after_a_json_value_is_refused() {
        let e = parse_json::<SceneFile>(r#"{"objects": []} xyz"#).unwrap_err();
        assert!(e.message.contains("trailing characters"), "{e}");
        assert_eq!((e.line, e.column), (1, 17), "{e}");
        // Whitespace after the value is fine.
        assert!(parse_json::<serde_json::Value>("{\"a\": 1}\n  \n").is_ok());
        assert!(parse_json::<serde_json::Value>("{} {}").is_err());
    }

    #[test]
    fn unknown_field_and_wrong_type_name_the_path() {
        let e = parse_json::<SceneFile>(
            r#"{"objects":[{"name":"a","mesh":"a.obj","material":{"type":"diffuse","albedo":[1,1,1],"colour":1}}]}"#,
        )
        .unwrap_err();
        assert!(e.path.starts_with("objects[0].material"), "{e}");
        assert!(e.message.contains("colour"), "{e}");

        let e = parse_json::<SceneFile>(
            r#"{"objects":[{"name":"a","mesh":"a.obj","material":{"type":"diffuse","albedo":[1,"x",1]}}]}"#,
        )
        .unwrap_err();
        assert_eq!(e.path, "objects[0].material.albedo[1]", "{e}");

        let e = parse_json::<SceneFile>(
            r#"{"objects":[{"name":"a","mesh":{"shape":"box","size":[1,1]},"material":{"type":"diffuse","albedo":[1,1,1]}}]}"#,
        )
        .unwrap_err();
        assert!(e.path.starts_with("objects[0].mesh"), "{e}");

        let e = parse_json::<SceneFile>(
            r#"{"objects":[{"name":"a","mesh":"a.obj","material":{"type":"glass"}}]}"#,
        )
        .unwrap_err();
        assert!(e.message.contains("glass"), "{e}");

        // Tagged enums inside tagged enums keep the whole path.
        let e = parse_json::<SceneFile>(
            r#"{"objects":[{"name":"a","mesh":"a.obj","material":{"type":"translucent",
                "profile":{"type":"exponentials","terms":[{"a":[1,1,1],"b":[1,true,1]}]}}}]}"#,
        )
        .unwrap_err();
        assert_eq!(e.path, "objects[0].material.profile.terms[0].b[1]", "{e}");
        assert!(e.message.starts_with("invalid type: boolean"), "{e}");
        let e = parse_json::<SceneFile>(
            r#"{"objects":[],"lights":[{"type":"spot","position":[0,0,0],"intensity":[1,1,1],
                "direction":[0,-1,0],"inner_deg":"ten","outer_deg":20}]}"#,
        )
        .unwrap_err();
        assert_eq!(e.path, "lights[0].inner_deg", "{e}");
    }

    #[test]
    fn mesh_ref_accepts_path_and_shape() {
        let s: SceneFile = parse_json(
            r#"{"objects":[
              {"name":"a","mesh":"m.obj","material":{"type":"emitter","radiance":[1,1,1]}},
              {"name":"b","mesh":{"shape":"box","size":[1,2,3]},"material":{"type":"diffuse","albedo":[0.5,0.5,0.5]}}]}"#,
        )
        .unwrap();
        assert_eq!(s.objects[0].mesh, MeshRef::Path("m.obj".into()));
        assert_eq!(
            s.objects[1].mesh,
            MeshRef::Shape(Shape::Box {
                size: [1.0, 2.0, 3.0],
                inward: false
            })
        );
        assert!(matches!(s.objects[0].material, Material::Emitter { .. }));
        s.validate().unwrap();
    }

    #[test]
    fn validation_names_field_and_rule() {
        let mut s: SceneFile = parse_json(
            r#"{"objects":[{"name":"a","mesh":"m.obj","material":{"type":"diffuse","albedo":[0.5,-0.1,0.5]}}],
               "lights":[{"type":"point","position":[0,1,0],"intensity":[1,1,1]}]}"#,
        )
        .unwrap();
        assert_eq!(
            s.validate().unwrap_err().to_string(),
            "objects[0].material.albedo[1] must be finite and in [0, 1]"
        );
        s.objects[0].material = Material::Diffuse {
            albedo: [0.5; 3],
            specular: None,
        };
        s.lights[0] = crate::light::Light::Point {
            position: [0.0; 3],
            intensity: [1.0, f32::NAN, 1.0],
        };
        assert_eq!(
            s.validate().unwrap_err().to_string(),
            "lights[0].intensity[1] must be finite and in [0, 1000000000000]"
        );
        // NaN is not JSON at all.
        assert!(parse_json::<SceneFile>(r#"{"objects":[],"unit_mm":NaN}"#).is_err());
        let bad_preset: SceneFile = parse_json(
            r#"{"objects":[{"name":"a","mesh":"m.obj","material":{"type":"translucent","profile":{"type":"dipole","preset":"jade"}}}]}"#,
        )
        .unwrap();
        let msg = bad_preset.validate().unwrap_err().to_string();
        assert!(
            msg.starts_with("objects[0].material.profile.preset \"jade\" is not a known medium"),
            "{msg}"
        );
    }
}
