//! Internally tagged enums (`{"type": "diffuse", ...}`) whose decoding errors keep the path.
//!
//! serde's `#[serde(tag = "type")]` buffers the object before choosing a variant, and the
//! error then loses the path inside it (`objects[0].material` instead of
//! `objects[0].material.albedo[1]`). [`tagged_enum!`] declares the public enum (serialised
//! with the tag, as the file format wants) plus a private externally tagged mirror used only
//! for decoding: the tag is moved to the outside (`{"diffuse": {...}}`) and the mirror is
//! decoded with `serde_path_to_error`, whose inner path is carried out in the message and
//! stitched back together by [`crate::parse_json`].

use serde::de::{DeserializeOwned, Error};
use serde::{Deserialize, Deserializer};
use serde_json::{Map, Value};

/// Brackets an inner path at the start of an error message (never in user text).
pub(crate) const PATH_MARK: char = '\u{1f}';

/// Decodes a tagged object through the externally tagged mirror `T`.
pub(crate) fn deserialize_tagged<'de, D, T>(d: D, tag: &'static str) -> Result<T, D::Error>
where
    D: Deserializer<'de>,
    T: DeserializeOwned,
{
    let mut map = Map::deserialize(d)?;
    let ty = match map.remove(tag) {
        Some(Value::String(s)) => s,
        Some(other) => {
            return Err(D::Error::custom(format!(
                "`{tag}` must be a string, got {other}"
            )));
        }
        None => return Err(D::Error::missing_field(tag)),
    };
    let wrapped = Value::Object(Map::from_iter([(ty, Value::Object(map))]));
    serde_path_to_error::deserialize::<_, T>(wrapped).map_err(|e| {
        // The mirror's path starts with the variant name; the user's file has no such level.
        let path = e.path().to_string();
        let inner = match path.find(['.', '[']) {
            Some(k) => path[k..].trim_start_matches('.').to_string(),
            None => String::new(),
        };
        let message = e.into_inner().to_string();
        if inner.is_empty() {
            D::Error::custom(message)
        } else {
            D::Error::custom(format!("{PATH_MARK}{inner}{PATH_MARK}{message}"))
        }
    })
}

/// Joins a path and a sub-path: `a` + `b.c` → `a.b.c`, `a` + `[0]` → `a[0]`.
pub(crate) fn join_path(outer: &str, inner: &str) -> String {
    if outer.is_empty() || outer == "." {
        inner.to_string()
    } else if inner.starts_with('[') {
        format!("{outer}{inner}")
    } else {
        format!("{outer}.{inner}")
    }
}

/// Declares an internally tagged enum with struct variants, and its decoding mirror.
macro_rules! tagged_enum {
    (
        tag = $tag:literal, mirror = $mirror:ident;
        $(#[$meta:meta])*
        pub enum $name:ident {
            $(
                $(#[$vmeta:meta])*
                $var:ident { $( $(#[$fmeta:meta])* $field:ident : $ty:ty ),* $(,)? }
            ),* $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(serde::Serialize)]
        #[serde(tag = $tag, rename_all = "snake_case")]
        pub enum $name {
            $( $(#[$vmeta])* $var { $( $(#[$fmeta])* $field: $ty ),* } ),*
        }

        #[derive(serde::Deserialize)]
        #[serde(rename_all = "snake_case", deny_unknown_fields)]
        enum $mirror {
            $( $var { $( $(#[$fmeta])* $field: $ty ),* } ),*
        }

        impl From<$mirror> for $name {
            fn from(m: $mirror) -> Self {
                match m { $( $mirror::$var { $($field),* } => $name::$var { $($field),* } ),* }
            }
        }

        impl<'de> serde::Deserialize<'de> for $name {
            fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                $crate::tagged::deserialize_tagged::<D, $mirror>(d, $tag).map(Into::into)
            }
        }
    };
}
pub(crate) use tagged_enum;
