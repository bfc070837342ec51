//! The OpenAPI 3.1 document of the API, served at `GET /api/v1/openapi.json`.
//!
//! Generated, not written: each handler's `#[utoipa::path]` (in [`crate::routes`],
//! [`crate::ws`] and [`crate::team`]) gives its method, path, parameters, request body and
//! answers; the bodies' schemas come from `ToSchema` derives on the types the handlers
//! read and write ([`translux_proto::api`] through its `openapi` feature, and the server's
//! own answers, [`crate::jobs::JobRecord`], [`crate::schema`]). A `Modify` step (`Access`) then adds what the access layer does to every route, from the
//! same rule the layer applies ([`crate::auth::required_role`]): the security schemes, the
//! role (`x-translux-role`), and the 401, 403 and 429 answers.
//!
//! The tests below check that the document is valid OpenAPI 3.1 (an independent reader,
//! `oas3`, and every `$ref` resolved) and that it lists exactly the routes the routers
//! serve: [`crate::routes::routes`] and [`crate::team::routes`], the records of the route
//! tables that build the routers.
//!
//! Why utoipa: it describes the handlers where they are, with attributes, and leaves the
//! axum `Router` and the handlers' signatures as they were (the custom extractors,
//! [`crate::extract::JsonBody`] and the `Result<_, AppError>` rejections, stay); its
//! derives follow the serde attributes the bodies already carry (`rename_all`, internally
//! tagged enums, `default`, `skip_serializing_if`). aide, the other maintained choice,
//! builds the document from the handlers' types instead, which would need its `ApiRouter`
//! in place of axum's router, `OperationInput`/`OperationOutput` impls for each custom
//! extractor and answer, and `schemars` derives on every body.

use std::sync::OnceLock;

use axum::body::Bytes;
use axum::http::Method;
use utoipa::openapi::path::Operation;
use utoipa::openapi::response::ResponseBuilder;
use utoipa::openapi::security::{
    ApiKey, ApiKeyValue, Http, HttpAuthScheme, SecurityRequirement, SecurityScheme,
};
use utoipa::openapi::{ContentBuilder, HeaderBuilder, Ref, RefOr};
use utoipa::{Modify, OpenApi};

use crate::auth::Role;

#[derive(OpenApi)]
#[openapi(
    info(
        title = "translux-server",
        description = "Relights precomputed translucent-radiosity bundles: lights in, \
                       per-vertex linear radiance B/π out (docs/api.md). Every error answer \
                       is `{\"error\":{\"code\",\"message\"}}` (the `ErrorBody` schema). The \
                       WebSocket stream's protocol is in docs/stream.md; uploads, jobs and \
                       tokens in docs/team.md.\n\n\
                       Access: without `--tokens` every route is open and the server listens \
                       on loopback only. With `--tokens` every route under `/api/` needs a \
                       bearer token whose role is at least the operation's `x-translux-role` \
                       (viewer < editor < admin); `/`, `/web/…`, `/healthz` and `/metrics` \
                       stay open (`x-translux-role: none`). A path no route serves is 404 \
                       `not_found` (under `/api/` with tokens on, 401 comes first); a known \
                       path with another method is 405 `method_not_allowed`."
    ),
    paths(
        crate::routes::index,
        crate::routes::web_file,
        crate::routes::healthz,
        crate::routes::metrics,
        crate::openapi_document,
        crate::routes::presets,
        crate::routes::list_scenes,
        crate::routes::scene_detail,
        crate::routes::scene_mesh,
        crate::routes::relight,
        crate::routes::render,
        crate::ws::stream,
        crate::team::upload,
        crate::team::delete_scene,
        crate::team::resimulate,
        crate::team::list_jobs,
        crate::team::get_job,
        crate::team::cancel_job,
        crate::team::job_events,
        crate::team::whoami,
    ),
    modifiers(&Access),
    tags(
        (name = "scenes", description = "Scenes, relights, renders and the stream."),
        (name = "team", description = "Uploads, precompute jobs, deletion, the caller's token."),
        (name = "viewer", description = "The browser viewer's page and files."),
        (name = "operations", description = "Health, metrics and this document."),
    )
)]
struct ApiDoc;

/// The document.
pub fn document() -> utoipa::openapi::OpenApi {
    ApiDoc::openapi()
}

/// The document as JSON, made once.
pub fn json() -> Bytes {
    static JSON: OnceLock<Bytes> = OnceLock::new();
    JSON.get_or_init(|| {
        // Serialising plain data (strings, maps, numbers) cannot fail.
        Bytes::from(document().to_pretty_json().unwrap_or_default())
    })
    .clone()
}

/// The access layer's part of every operation ([`crate::auth::middleware`]): security, the
/// role, and the answers it gives before any handler runs.
#[derive(Debug)]
struct Access;

const BEARER: &str = "bearerAuth";
const QUERY_TOKEN: &str = "accessTokenQuery";

impl Modify for Access {
    fn modify(&self, doc: &mut utoipa::openapi::OpenApi) {
        let components = doc.components.get_or_insert_with(Default::default);
        components.security_schemes.insert(
            BEARER.into(),
            SecurityScheme::Http(
                Http::builder()
                    .scheme(HttpAuthScheme::Bearer)
                    .bearer_format("tlx_ followed by 64 hex digits (translux-server token add)")
                    .description(Some(
                        "`Authorization: Bearer TOKEN`, needed only when the server runs \
                         with --tokens FILE (SHA-256 hashes of the tokens, each with a name \
                         and a role: viewer < editor < admin). A malformed Authorization \
                         header counts as an unknown token (401).",
                    ))
                    .build(),
            ),
        );
        components.security_schemes.insert(
            QUERY_TOKEN.into(),
            SecurityScheme::ApiKey(ApiKey::Query(ApiKeyValue::with_description(
                "access_token",
                "The same token as the query parameter `access_token` (RFC 6750 section \
                 2.3), for browsers' WebSockets, which cannot set headers: GET only, and \
                 only when no Authorization header is sent.",
            ))),
        );
        let error = |description: &str, header: (&str, &str)| {
            ResponseBuilder::new()
                .description(description)
                .content(
                    "application/json",
                    ContentBuilder::new()
                        .schema(Some(Ref::from_schema_name("ErrorBody")))
                        .build(),
                )
                .header(
                    header.0,
                    HeaderBuilder::new()
                        .description(Some(header.1))
                        .schema(<String as utoipa::PartialSchema>::schema())
                        .build(),
                )
                .build()
        };
        let challenge = (
            "WWW-Authenticate",
            "`Bearer realm=\"translux\"`, with `error=\"invalid_token\"` for an unknown token \
             and `error=\"insufficient_scope\"` for a role too low.",
        );
        let retry = ("Retry-After", "Seconds to wait before retrying.");
        for (name, response) in [
            (
                "Unauthorized",
                error(
                    "`unauthorized`: no token, or one this server does not know (with --tokens).",
                    challenge,
                ),
            ),
            (
                "Forbidden",
                error(
                    "`forbidden`: the token's role is below the route's (with --tokens).",
                    challenge,
                ),
            ),
            (
                "RateLimited",
                error(
                    "`rate_limited`: the token is over its request rate (with --tokens).",
                    retry,
                ),
            ),
        ] {
            components.responses.insert(name.into(), response.into());
        }

        for (path, item) in doc.paths.paths.iter_mut() {
            for (method, op) in [
                (Method::GET, &mut item.get),
                (Method::POST, &mut item.post),
                (Method::DELETE, &mut item.delete),
                (Method::PUT, &mut item.put),
                (Method::PATCH, &mut item.patch),
            ] {
                if let Some(op) = op {
                    secure(op, &method, path);
                }
            }
        }
    }
}

/// Security, `x-translux-role` and the access layer's answers of the operation `method path`.
fn secure(op: &mut Operation, method: &Method, path: &str) {
    let role = crate::auth::required_role(method, path);
    let name = role.map_or("none", Role::as_str);
    let ext = op.extensions.get_or_insert_with(Default::default);
    ext.insert("x-translux-role".into(), name.into());
    let Some(role) = role else {
        // Open even with tokens: an empty requirement list.
        op.security = Some(Vec::new());
        return;
    };
    let mut schemes = vec![SecurityRequirement::new(BEARER, Vec::<String>::new())];
    if *method == Method::GET {
        schemes.push(SecurityRequirement::new(QUERY_TOKEN, Vec::<String>::new()));
    }
    op.security = Some(schemes);
    let note = format!("Role: {name} (with --tokens).");
    op.description = Some(match op.description.take() {
        Some(d) if !d.is_empty() => format!("{d}\n\n{note}"),
        _ => note,
    });
    let responses = &mut op.responses.responses;
    let mut add = |status: &str, component: &str| {
        responses
            .entry(status.into())
            .or_insert_with(|| RefOr::Ref(Ref::from_response_name(component)));
    };
    add("401", "Unauthorized");
    add("429", "RateLimited");
    if role > Role::Viewer {
        add("403", "Forbidden");
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    use serde_json::Value;

    use super::*;

    /// The document as JSON.
    fn doc() -> Value {
        serde_json::from_slice(&json()).expect("the document is JSON")
    }

    /// `(method, path)` of every route the routers serve, as OpenAPI writes paths
    /// (`{*path}` → `{path}`).
    fn served() -> BTreeSet<(String, String)> {
        crate::routes::routes()
            .into_iter()
            .chain(crate::team::routes())
            .map(|(m, p)| (m.as_str().to_lowercase(), p.replace("{*", "{")))
            .collect()
    }

    /// `(method, path)` of every operation of `doc`.
    fn documented(doc: &Value) -> BTreeSet<(String, String)> {
        const METHODS: [&str; 8] = [
            "get", "put", "post", "delete", "options", "head", "patch", "trace",
        ];
        let mut out = BTreeSet::new();
        for (path, item) in doc["paths"].as_object().expect("paths") {
            for (key, _) in item.as_object().expect("a path item") {
                if METHODS.contains(&key.as_str()) {
                    out.insert((key.clone(), path.clone()));
                }
            }
        }
        out
    }

    #[test]
    fn the_document_lists_exactly_the_routes_the_routers_serve() {
        let served = served();
        // Both tables are in: the document is not compared with half the API.
        assert!(served.contains(&("get".into(), "/api/v1/scenes/{id}/stream".into())));
        assert!(served.contains(&("delete".into(), "/api/v1/jobs/{id}".into())));
        assert_eq!(
            served,
            documented(&doc()),
            "(method, path) of the routers vs the OpenAPI document"
        );
        // And the typed model says the same as its JSON.
        let typed: BTreeSet<_> = document()
            .paths
            .paths
            .iter()
            .flat_map(|(p, item)| {
                [
                    (Method::GET, item.get.is_some()),
                    (Method::POST, item.post.is_some()),
                    (Method::DELETE, item.delete.is_some()),
                    (Method::PUT, item.put.is_some()),
                    (Method::PATCH, item.patch.is_some()),
                ]
                .into_iter()
                .filter(|(_, on)| *on)
                .map(move |(m, _)| (m.as_str().to_lowercase(), p.clone()))
            })
            .collect();
        assert_eq!(typed, served);
    }

    /// Every `"$ref"` under `v`, with where it was found.
    fn refs(v: &Value, at: &str, out: &mut Vec<(String, String)>) {
        match v {
            Value::Object(o) => {
                for (k, v) in o {
                    if k == "$ref" {
                        out.push((at.to_string(), v.as_str().unwrap_or("").to_string()));
                    } else {
                        refs(v, &format!("{at}/{k}"), out);
                    }
                }
            }
            Value::Array(a) => {
                for (i, v) in a.iter().enumerate() {
                    refs(v, &format!("{at}/{i}"), out);
                }
            }
            _ => {}
        }
    }

    /// The errors of the checks an independent reader does not make: every `$ref`
    /// resolves inside the document, every operation has a summary, a unique operationId,
    /// answers with descriptions, each `{name}` of its path as a required path parameter
    /// and no other path parameter, a role and security, and every error answer the
    /// error body.
    fn problems(doc: &Value) -> Vec<String> {
        let mut out = Vec::new();
        for key in ["openapi", "info", "paths"] {
            if doc.get(key).is_none() {
                out.push(format!("no `{key}`"));
            }
        }
        if !doc["openapi"].as_str().unwrap_or("").starts_with("3.1.") {
            out.push(format!("openapi is {}", doc["openapi"]));
        }
        for key in ["title", "version"] {
            if !doc["info"][key].is_string() {
                out.push(format!("no info.{key}"));
            }
        }
        let mut found = Vec::new();
        refs(doc, "", &mut found);
        for (at, r) in &found {
            // `#/a/b/c` → doc["a"]["b"]["c"] (JSON pointer, `~1` for `/`).
            let resolved = r.strip_prefix('#').and_then(|p| doc.pointer(p)).is_some();
            if !resolved {
                out.push(format!("{at}: $ref {r:?} does not resolve"));
            }
        }
        let mut ids = BTreeSet::new();
        for (path, item) in doc["paths"].as_object().into_iter().flatten() {
            let names: BTreeSet<String> = path
                .split('{')
                .skip(1)
                .filter_map(|s| s.split_once('}').map(|(n, _)| n.to_string()))
                .collect();
            for (method, op) in item.as_object().into_iter().flatten() {
                let here = format!("{method} {path}");
                if op["summary"].as_str().is_none_or(str::is_empty) {
                    out.push(format!("{here}: no summary"));
                }
                match op["operationId"].as_str() {
                    Some(id) if ids.insert(id.to_string()) => {}
                    other => out.push(format!("{here}: operationId {other:?} missing or repeated")),
                }
                let in_path: BTreeSet<String> = op["parameters"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .filter(|p| p["in"] == "path")
                    .filter(|p| {
                        let required = p["required"] == true;
                        if !required {
                            out.push(format!("{here}: path parameter {} not required", p["name"]));
                        }
                        required
                    })
                    .filter_map(|p| p["name"].as_str().map(str::to_string))
                    .collect();
                if in_path != names {
                    out.push(format!(
                        "{here}: path parameters {in_path:?}, path has {names:?}"
                    ));
                }
                let role = op["x-translux-role"].as_str().unwrap_or("");
                let open = role == "none";
                if !["none", "viewer", "editor", "admin"].contains(&role) {
                    out.push(format!("{here}: x-translux-role {role:?}"));
                }
                if op["security"]
                    .as_array()
                    .is_none_or(|s| s.is_empty() != open)
                {
                    out.push(format!(
                        "{here}: security {} for role {role:?}",
                        op["security"]
                    ));
                }
                let responses = op["responses"].as_object();
                if responses.is_none_or(|r| r.is_empty()) {
                    out.push(format!("{here}: no responses"));
                }
                for (status, r) in responses.into_iter().flatten() {
                    let r = match r["$ref"].as_str() {
                        Some(p) => doc.pointer(&p[1..]).unwrap_or(&Value::Null),
                        None => r,
                    };
                    if !r["description"].is_string() {
                        out.push(format!("{here} {status}: no description"));
                    }
                    let error_body = "#/components/schemas/ErrorBody";
                    if status.starts_with(['4', '5'])
                        && r["content"]["application/json"]["schema"]["$ref"] != error_body
                    {
                        out.push(format!("{here} {status}: not the error body"));
                    }
                }
                if !open && !responses.is_some_and(|r| r.contains_key("401")) {
                    out.push(format!("{here}: no 401"));
                }
            }
        }
        out
    }

    #[test]
    fn the_document_is_valid_openapi_3_1() {
        let text = std::str::from_utf8(&json()).unwrap().to_string();
        // An independent reader of OpenAPI 3.1 must accept it, and find every route.
        let spec = oas3::from_json(&text).expect("oas3 reads the document");
        assert!(spec.openapi.starts_with("3.1."), "{}", spec.openapi);
        let ops = spec.operations().count();
        assert_eq!(ops, served().len());
        let doc = doc();
        let problems = problems(&doc);
        assert!(problems.is_empty(), "{problems:#?}");
        // The bodies are the types', not free-form objects.
        let schemas = &doc["components"]["schemas"];
        for name in [
            "ErrorBody",
            "RelightRequest",
            "RenderRequest",
            "RelightResponse",
            "SceneDetail",
            "Mesh",
            "Light",
            "Material",
            "HealthReport",
            "JobRecord",
            "UploadForm",
        ] {
            assert!(schemas[name].is_object(), "no schema {name}");
        }
        let relight = &doc["paths"]["/api/v1/scenes/{id}/relight"]["post"];
        assert_eq!(
            relight["requestBody"]["content"]["application/json"]["schema"]["$ref"],
            "#/components/schemas/RelightRequest"
        );
        let ok = &relight["responses"]["200"]["content"];
        assert!(ok["application/json"].is_object() && ok["application/octet-stream"].is_object());
        let render = &doc["paths"]["/api/v1/scenes/{id}/render"]["post"]["responses"]["200"];
        assert!(render["content"]["image/png"].is_object());
        assert!(render["content"]["image/x-exr"].is_object());
        let events = &doc["paths"]["/api/v1/jobs/{id}/events"]["get"]["responses"]["200"];
        assert!(events["content"]["text/event-stream"].is_object());
        // Roles as the access layer decides them.
        for (method, path, role) in [
            ("get", "/healthz", "none"),
            ("get", "/api/v1/scenes", "viewer"),
            ("post", "/api/v1/scenes", "editor"),
            ("delete", "/api/v1/scenes/{id}", "admin"),
            ("get", "/api/v1/jobs/{id}/events", "editor"),
        ] {
            assert_eq!(
                doc["paths"][path][method]["x-translux-role"], role,
                "{method} {path}"
            );
        }
    }

    /// The checks of [`problems`] find what they look for.
    #[test]
    fn the_validity_checks_catch_a_broken_document() {
        let good = doc();
        let mut broken = good.clone();
        broken["paths"]["/api/v1/scenes/{id}"]["get"]["responses"]["200"]["content"]["application/json"]
            ["schema"]["$ref"] = "#/components/schemas/Nothing".into();
        broken["paths"]["/api/v1/jobs"]["get"]
            .as_object_mut()
            .unwrap()
            .remove("summary");
        broken["paths"]["/api/v1/scenes/{id}/mesh"]["get"]["parameters"] = Value::Array(vec![]);
        broken["paths"]["/api/v1/whoami"]["get"]["security"] = Value::Array(vec![]);
        let found = problems(&broken);
        for needle in [
            "Nothing\" does not resolve",
            "get /api/v1/jobs: no summary",
            "get /api/v1/scenes/{id}/mesh: path parameters",
            "get /api/v1/whoami: security",
        ] {
            assert!(
                found.iter().any(|p| p.contains(needle)),
                "{needle} not found in {found:#?}"
            );
        }
        assert_eq!(found.len(), 4, "{found:#?}");
        // A route the routers do not serve, or one missing, is seen.
        let mut extra = good.clone();
        extra["paths"]["/api/v1/nothing"] = serde_json::json!({"get": {}});
        assert_ne!(documented(&extra), served());
        let mut fewer = good;
        fewer["paths"].as_object_mut().unwrap().remove("/metrics");
        assert_ne!(documented(&fewer), served());
    }
}
