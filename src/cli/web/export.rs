//! `GET /files/NAME/export.ome.tif`: a session's frames as OME-TIFF (`rigctl export`'s
//! writer), made for the request in a private temporary folder and streamed from the open
//! file, so a session of any size costs the gateway a buffer, not the file.

use super::routes::{error, session_dir, App};
use crate::export::{export, Format};
use axum::body::Body;
use axum::extract::{Path as UrlPath, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};

/// The download's file name for session `name`.
pub fn file_name(name: &str) -> String {
    format!("{name}.{}", Format::OmeTiff.extension())
}

/// A new folder for one export, private to this user (mode 0700).
fn private_dir() -> std::io::Result<PathBuf> {
    use std::os::unix::fs::DirBuilderExt;
    static N: AtomicU64 = AtomicU64::new(0);
    let n = N.fetch_add(1, Ordering::Relaxed);
    let dir = std::env::temp_dir().join(format!("rigd-web-{}-{n}", std::process::id()));
    std::fs::DirBuilder::new().mode(0o700).create(&dir)?;
    Ok(dir)
}

pub async fn ome_tiff(State(app): State<App>, UrlPath(name): UrlPath<String>) -> Response {
    let dir = match session_dir(&app, &name).await {
        Ok(d) => d,
        Err(r) => return r,
    };
    let tmp = match private_dir() {
        Ok(t) => t,
        Err(e) => {
            let why = format!("a temporary folder for the export: {e}");
            return error(StatusCode::INTERNAL_SERVER_ERROR, "internal", why);
        }
    };
    let out = tmp.join(file_name(&name));
    let made = tokio::task::spawn_blocking({
        let out = out.clone();
        move || export(&dir, Format::OmeTiff, &out)
    })
    .await;
    // Opened before the folder goes: the open file stays readable until it is sent.
    let file = match made {
        Ok(Ok(_)) => tokio::fs::File::open(&out).await.map_err(|e| e.to_string()),
        Ok(Err(e)) => Err(e.to_string()),
        Err(e) => Err(format!("the export stopped: {e}")),
    };
    let _ = std::fs::remove_dir_all(&tmp);
    match file {
        Ok(f) => (
            [
                (header::CONTENT_TYPE, "image/tiff".to_string()),
                (
                    header::CONTENT_DISPOSITION,
                    format!("attachment; filename=\"{}\"", file_name(&name)),
                ),
            ],
            Body::from_stream(tokio_util::io::ReaderStream::new(f)),
        )
            .into_response(),
        Err(why) => error(StatusCode::NOT_FOUND, "not_found", why),
    }
}
