//! The observer page (`web/`), compiled into the binary: the server needs no npm, no internet
//! and no files beside itself, and can serve nothing but these assets.

use axum::extract::Path;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};

struct Asset {
    path: &'static str,
    content_type: &'static str,
    bytes: &'static [u8],
}

macro_rules! asset {
    ($path:literal, $content_type:expr) => {
        Asset {
            path: $path,
            content_type: $content_type,
            bytes: include_bytes!(concat!("../../web/", $path)),
        }
    };
}

const JS: &str = "text/javascript; charset=utf-8";

static ASSETS: &[Asset] = &[
    asset!("index.html", "text/html; charset=utf-8"),
    asset!("app/main.js", JS),
    asset!("app/protocol.js", JS),
    asset!("app/colormap.js", JS),
    asset!("app/placement.js", JS),
    asset!("app/style.css", "text/css; charset=utf-8"),
    asset!("vendor/three/three.module.js", JS),
    asset!("vendor/three/three.core.js", JS),
    asset!("vendor/three/OrbitControls.js", JS),
    asset!("vendor/three/LICENSE", "text/plain; charset=utf-8"),
];

fn respond(path: &str) -> Response {
    match ASSETS.iter().find(|a| a.path == path) {
        Some(asset) => (
            [
                (header::CONTENT_TYPE, asset.content_type),
                // A new server version may bring new assets: always revalidate.
                (header::CACHE_CONTROL, "no-cache"),
            ],
            asset.bytes,
        )
            .into_response(),
        None => (StatusCode::NOT_FOUND, "not found\n").into_response(),
    }
}

pub(super) async fn index() -> Response {
    respond("index.html")
}

pub(super) async fn app(Path(path): Path<String>) -> Response {
    respond(&format!("app/{path}"))
}

pub(super) async fn vendor(Path(path): Path<String>) -> Response {
    respond(&format!("vendor/{path}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn files_under(dir: &std::path::Path, out: &mut Vec<PathBuf>) {
        for entry in std::fs::read_dir(dir).expect("readable web dir") {
            let path = entry.expect("dir entry").path();
            if path.is_dir() {
                files_under(&path, out);
            } else {
                out.push(path);
            }
        }
    }

    /// A file added to `web/app` or `web/vendor` but not to `ASSETS` would be a 404 in the field.
    #[test]
    fn every_page_file_is_embedded() {
        let web = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("web");
        let mut files = Vec::new();
        files_under(&web.join("app"), &mut files);
        files_under(&web.join("vendor"), &mut files);
        for file in files {
            let rel = file
                .strip_prefix(&web)
                .expect("under web/")
                .to_string_lossy()
                .replace('\\', "/");
            if rel == "vendor/three/package.json" {
                continue; // provenance of the vendored copy, not served
            }
            let asset = ASSETS.iter().find(|a| a.path == rel);
            let asset = asset.unwrap_or_else(|| panic!("web/{rel} is not in ASSETS"));
            assert_eq!(
                asset.bytes,
                std::fs::read(&file).expect("readable").as_slice(),
                "{rel}"
            );
        }
    }

    #[test]
    fn only_embedded_assets_are_served() {
        assert_eq!(respond("app/main.js").status(), StatusCode::OK);
        for path in [
            "app/../Cargo.toml",
            "app/missing.js",
            "vendor/three/package.json",
            "../src/main.rs",
            "",
        ] {
            assert_eq!(respond(path).status(), StatusCode::NOT_FOUND, "{path}");
        }
    }
}
