//! The viewer's static files (`web/`), embedded in the server binary and served under
//! `/web/{path}`, so the viewer needs no network and no files beside the binary.
//!
//! In: a request path below `/web/`. Out: the file's bytes with its content type, or a
//! `not_found` JSON error naming the path and the files there are. The list is written by
//! hand (no `include_dir` dependency for a dozen files); a test checks that it names every
//! file the viewer has, so a new module cannot be forgotten.

use axum::extract::Path;
use axum::http::HeaderValue;
use axum::http::header::{CACHE_CONTROL, CONTENT_TYPE};
use axum::response::{IntoResponse, Response};

use crate::error::AppError;

/// `(path below web/, content type, bytes)` of every served file.
pub const FILES: &[(&str, &str, &[u8])] = &[
    ("style.css", CSS, include_bytes!("style.css")),
    ("js/app.js", JS, include_bytes!("js/app.js")),
    ("js/auth.js", JS, include_bytes!("js/auth.js")),
    ("js/camera.js", JS, include_bytes!("js/camera.js")),
    ("js/glb.js", JS, include_bytes!("js/glb.js")),
    ("js/hashstate.js", JS, include_bytes!("js/hashstate.js")),
    ("js/link.js", JS, include_bytes!("js/link.js")),
    ("js/math.js", JS, include_bytes!("js/math.js")),
    ("js/renderer.js", JS, include_bytes!("js/renderer.js")),
    ("js/ui.js", JS, include_bytes!("js/ui.js")),
];

const JS: &str = "text/javascript; charset=utf-8";
const CSS: &str = "text/css; charset=utf-8";

/// `GET /web/{*path}`.
pub async fn serve(Path(path): Path<String>) -> Result<Response, AppError> {
    let Some((_, mime, bytes)) = FILES.iter().find(|(p, _, _)| *p == path) else {
        let names: Vec<&str> = FILES.iter().map(|f| f.0).collect();
        return Err(AppError::not_found(format!(
            "no viewer file {path:?}; the files are: {}",
            names.join(", ")
        )));
    };
    Ok((
        [
            (CONTENT_TYPE, HeaderValue::from_static(mime)),
            // Revalidated on every load: a rebuilt server serves its new viewer at once.
            (CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        ],
        *bytes,
    )
        .into_response())
}

#[cfg(test)]
mod tests {
    use super::FILES;

    /// Every file under `web/` except the page itself, this file and the browser tests.
    fn viewer_files(dir: &std::path::Path, prefix: &str, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let rel = format!("{prefix}{name}");
            if e.file_type().unwrap().is_dir() {
                if name != "tests" && name != "node_modules" {
                    viewer_files(&e.path(), &format!("{rel}/"), out);
                }
            } else if rel != "index.html" && rel != "assets.rs" {
                out.push(rel);
            }
        }
    }

    #[test]
    fn every_viewer_file_is_embedded() {
        let web = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../web");
        let mut on_disk = Vec::new();
        viewer_files(&web, "", &mut on_disk);
        on_disk.sort();
        let mut listed: Vec<String> = FILES.iter().map(|f| f.0.to_string()).collect();
        listed.sort();
        assert_eq!(
            listed, on_disk,
            "web/assets.rs FILES must list every viewer file"
        );
        for (path, _, bytes) in FILES {
            let text = std::str::from_utf8(bytes).unwrap();
            // Served files must not reach the network.
            assert!(
                !text.contains("http://") && !text.contains("https://"),
                "{path} names an external resource"
            );
        }
    }
}
