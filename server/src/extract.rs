//! Request plumbing: the strict JSON body extractor and `Accept` negotiation.

use axum::body::Bytes;
use std::net::SocketAddr;

use axum::extract::{ConnectInfo, FromRequest, FromRequestParts, Path, Request};
use axum::http::header::{ACCEPT, CONTENT_TYPE};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue};
use serde::de::DeserializeOwned;

use crate::error::AppError;
use translux_engine::picture::PictureFormat;

/// Largest request body accepted, in bytes (1 MiB).
pub const BODY_LIMIT: usize = 1 << 20;

/// A JSON body read with [`translux_proto::parse_json`], so that a bad body's message names
/// the field path, line and column. An empty body reads as `{}`.
///
/// Rejections: 415 when `Content-Type` is present and not JSON (or absent with a non-empty
/// body), 413 over [`BODY_LIMIT`], 400 `bad_request` for anything serde refuses.
#[derive(Debug, Clone)]
pub struct JsonBody<T>(pub T);

impl<S, T> FromRequest<S> for JsonBody<T>
where
    S: Send + Sync,
    T: DeserializeOwned,
{
    type Rejection = AppError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let content_type = req.headers().get(CONTENT_TYPE).cloned();
        if let Some(ct) = &content_type
            && !is_json_media_type(ct)
        {
            return Err(AppError::unsupported_media_type(format!(
                "Content-Type {} is not JSON; send the body as application/json",
                show_header(ct)
            )));
        }
        let bytes = Bytes::from_request(req, state).await.map_err(|rejection| {
            if rejection.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
                AppError::payload_too_large(format!(
                    "the request body is larger than the limit of {} bytes (1 MiB)",
                    BODY_LIMIT
                ))
            } else {
                AppError::bad_request(format!(
                    "cannot read the request body: {}",
                    rejection.body_text()
                ))
            }
        })?;
        let text = std::str::from_utf8(&bytes)
            .map_err(|e| AppError::bad_request(format!("the request body is not UTF-8: {e}")))?;
        let text = if text.trim().is_empty() {
            "{}"
        } else if content_type.is_none() {
            return Err(AppError::unsupported_media_type(
                "the request has a body but no Content-Type; send it as application/json",
            ));
        } else {
            text
        };
        translux_proto::parse_json(text)
            .map(JsonBody)
            .map_err(|e| AppError::bad_request(format!("invalid JSON body: {e}")))
    }
}

/// The `{id}` of a scene route; an id that is not valid UTF-8 once percent-decoded is a 400
/// `bad_request` in the JSON error format (axum's own rejection is plain text).
#[derive(Debug, Clone)]
pub struct SceneId(pub String);

impl<S> FromRequestParts<S> for SceneId
where
    S: Send + Sync,
{
    type Rejection = AppError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        match Path::<String>::from_request_parts(parts, state).await {
            Ok(Path(id)) => Ok(SceneId(id)),
            Err(e) => Err(AppError::bad_request(format!(
                "bad scene id: {}",
                e.body_text()
            ))),
        }
    }
}

/// `?frame=K` of a scene route (an animated scene's frame; absent: frame 0); a value that is
/// not a whole number is a 400 in the JSON error format.
#[derive(Debug, Clone, Copy)]
pub struct FrameQuery(pub Option<u32>);

impl<S> FromRequestParts<S> for FrameQuery
where
    S: Send + Sync,
{
    type Rejection = AppError;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<Self, Self::Rejection> {
        let query = parts.uri.query().unwrap_or("");
        for pair in query.split('&') {
            let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
            if k == "frame" {
                return v.parse::<u32>().map(|f| FrameQuery(Some(f))).map_err(|_| {
                    AppError::bad_request(format!(
                        "bad frame {v:?}: a frame is a whole number from 0 (`?frame=12`)"
                    ))
                });
            }
        }
        Ok(FrameQuery(None))
    }
}

/// Who a request is from, for the worker pool's fair order: the `X-Client-Id` header
/// (trimmed, at most [`MAX_CLIENT_ID`] bytes kept) when a client sends one, so one user's
/// scripts count as one client across connections; otherwise the connection (peer address
/// and port); `anonymous` when neither is known (a router driven without a socket).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ClientKey(pub String);

/// Longest `X-Client-Id` kept.
pub const MAX_CLIENT_ID: usize = 64;

impl<S> FromRequestParts<S> for ClientKey
where
    S: Send + Sync,
{
    type Rejection = std::convert::Infallible;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<Self, Self::Rejection> {
        // With access control on, the token is the client: its queue share cannot be
        // multiplied by sending many X-Client-Id values.
        if let Some(who) = parts.extensions.get::<crate::auth::Identity>()
            && who.role.is_some()
            && &*who.name != crate::auth::LOCAL_NAME
        {
            return Ok(ClientKey(format!("token:{}", who.name)));
        }
        if let Some(id) = parts
            .headers
            .get("x-client-id")
            .and_then(|v| v.to_str().ok())
            .map(str::trim)
            .filter(|s| !s.is_empty())
        {
            let mut end = id.len().min(MAX_CLIENT_ID);
            while !id.is_char_boundary(end) {
                end -= 1;
            }
            return Ok(ClientKey(format!("id:{}", &id[..end])));
        }
        if let Some(ConnectInfo(addr)) = parts.extensions.get::<ConnectInfo<SocketAddr>>() {
            return Ok(ClientKey(format!("conn:{addr}")));
        }
        Ok(ClientKey("anonymous".to_string()))
    }
}

/// `application/json` or any `application/*+json`, parameters ignored.
fn is_json_media_type(v: &HeaderValue) -> bool {
    let Ok(s) = v.to_str() else { return false };
    let essence = s
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    essence == "application/json"
        || (essence.starts_with("application/") && essence.ends_with("+json"))
}

/// A header value for a message, quoted; non-ASCII shown lossily.
fn show_header(v: &HeaderValue) -> String {
    format!("{:?}", String::from_utf8_lossy(v.as_bytes()))
}

/// The answer formats of an endpoint that offers JSON and raw bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Json,
    Binary,
}

/// Picks the format from `Accept`: `application/json` → JSON; `application/octet-stream`,
/// `application/*`, `*/*` or no `Accept` → binary. The highest `q` wins; on a tie an exact
/// type beats a wildcard, then the earlier entry. Nothing acceptable → 406.
pub fn negotiate(headers: &HeaderMap) -> Result<Format, AppError> {
    choose(
        headers,
        &[
            ("application/json", 2, Format::Json),
            ("application/octet-stream", 2, Format::Binary),
            ("application/*", 1, Format::Binary),
            ("*/*", 1, Format::Binary),
        ],
        Format::Binary,
        "application/json or application/octet-stream",
    )
}

/// The render endpoint's format from `Accept`: `image/x-exr` → OpenEXR; `image/png`,
/// `image/*`, `*/*`, an absent or empty `Accept` → PNG. The highest `q` (> 0) wins; on a tie
/// an exact type beats a wildcard, then the earlier entry. Nothing acceptable → 406 naming
/// both types.
pub fn accept_picture(headers: &HeaderMap) -> Result<PictureFormat, AppError> {
    choose(
        headers,
        &[
            ("image/png", 2, PictureFormat::Png),
            ("image/x-exr", 2, PictureFormat::Exr),
            ("image/*", 1, PictureFormat::Png),
            ("*/*", 1, PictureFormat::Png),
        ],
        PictureFormat::Png,
        "image/png or image/x-exr",
    )
}

/// Content negotiation over `Accept` for an endpoint answering the formats of `offers`
/// (media type, specificity: 2 exact, 1 wildcard, format). The highest `q` (> 0) wins; on
/// a tie the more specific type, then the earlier entry. No `Accept` → `default`; nothing
/// acceptable → 406 listing what was asked and what the endpoint `answers`.
fn choose<F: Copy>(
    headers: &HeaderMap,
    offers: &[(&str, u8, F)],
    default: F,
    answers: &str,
) -> Result<F, AppError> {
    let mut best: Option<(f32, u8, F)> = None;
    let mut seen = Vec::new();
    for value in headers.get_all(ACCEPT) {
        let Ok(value) = value.to_str() else {
            return Err(AppError::not_acceptable("the Accept header is not ASCII"));
        };
        for entry in value.split(',') {
            let mut parts = entry.split(';');
            let media = parts.next().unwrap_or("").trim().to_ascii_lowercase();
            if media.is_empty() {
                continue;
            }
            let mut q = 1.0f32;
            for p in parts {
                if let Some((k, v)) = p.split_once('=')
                    && k.trim().eq_ignore_ascii_case("q")
                {
                    q = v.trim().parse().unwrap_or(0.0);
                }
            }
            let candidate = offers
                .iter()
                .find(|(m, _, _)| *m == media)
                .map(|&(_, specificity, format)| (specificity, format));
            seen.push(media);
            if let Some((specificity, format)) = candidate
                && q > 0.0
                && best.is_none_or(|(bq, bs, _)| q > bq || (q == bq && specificity > bs))
            {
                best = Some((q, specificity, format));
            }
        }
    }
    match best {
        Some((_, _, f)) => Ok(f),
        None if seen.is_empty() => Ok(default),
        None => Err(AppError::not_acceptable(format!(
            "Accept: {} is not available; this endpoint answers {answers}",
            seen.join(", ")
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn accept(v: &str) -> Result<Format, AppError> {
        let mut h = HeaderMap::new();
        h.insert(ACCEPT, HeaderValue::from_str(v).unwrap());
        negotiate(&h)
    }

    #[test]
    fn accept_negotiation() {
        assert_eq!(negotiate(&HeaderMap::new()), Ok(Format::Binary));
        assert_eq!(accept("application/json"), Ok(Format::Json));
        assert_eq!(accept("application/json; charset=utf-8"), Ok(Format::Json));
        assert_eq!(accept("*/*"), Ok(Format::Binary));
        assert_eq!(accept("application/octet-stream"), Ok(Format::Binary));
        assert_eq!(
            accept("text/html, application/json;q=0.9, */*;q=0.8"),
            Ok(Format::Json)
        );
        assert_eq!(accept("*/*, application/json"), Ok(Format::Json));
        assert_eq!(
            accept("application/json;q=0.5, application/octet-stream"),
            Ok(Format::Binary)
        );
        assert_eq!(accept("application/json;q=0, */*"), Ok(Format::Binary));
        assert_eq!(accept(""), Ok(Format::Binary));
        let e = accept("image/png").unwrap_err();
        assert_eq!(e.status.as_u16(), 406);
        assert!(e.message.contains("image/png"), "{e}");
        assert!(accept("application/json;q=0").is_err());
    }

    #[test]
    fn picture_acceptance() {
        let pick = |v: &str| {
            let mut h = HeaderMap::new();
            h.insert(ACCEPT, HeaderValue::from_str(v).unwrap());
            accept_picture(&h)
        };
        assert_eq!(accept_picture(&HeaderMap::new()), Ok(PictureFormat::Png));
        for ok in [
            "image/png",
            "image/*",
            "*/*",
            "text/html, image/png;q=0.5",
            "",
            "image/x-exr;q=0.5, image/png",
            "*/*, image/x-exr;q=0",
        ] {
            assert_eq!(pick(ok), Ok(PictureFormat::Png), "{ok}");
        }
        for exr in [
            "image/x-exr",
            "Image/X-EXR",
            "image/png;q=0.5, image/x-exr",
            "*/*, image/x-exr",
            "image/*;q=1, image/x-exr",
        ] {
            assert_eq!(pick(exr), Ok(PictureFormat::Exr), "{exr}");
        }
        for bad in [
            "application/json",
            "image/png;q=0",
            "image/jpeg",
            "image/x-exr;q=0",
        ] {
            let e = pick(bad).unwrap_err();
            assert_eq!(e.status.as_u16(), 406, "{bad}");
            assert!(e.message.contains("image/png"), "{e}");
            assert!(e.message.contains("image/x-exr"), "{e}");
        }
    }

    #[test]
    fn json_media_types() {
        for ok in [
            "application/json",
            "Application/JSON; charset=utf-8",
            "application/vnd.x+json",
        ] {
            assert!(is_json_media_type(&HeaderValue::from_static(ok)), "{ok}");
        }
        for bad in ["text/plain", "application/x-www-form-urlencoded", "json"] {
            assert!(!is_json_media_type(&HeaderValue::from_static(bad)), "{bad}");
        }
    }
}
