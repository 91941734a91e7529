//! The gateway's HTTP routes: the page and its assets, the API that forwards protocol
//! requests to the daemon, session results (targets table, plots, downloads), the current
//! calibration, and the page's WebSocket.

use super::link::Daemon;
use super::{assets, auth, bridge, export, plots};
use axum::extract::{Path as UrlPath, State, WebSocketUpgrade};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde_json::{json, Value};
use std::path::PathBuf;

/// What the handlers share.
#[derive(Clone)]
pub struct App {
    pub daemon: Daemon,
    /// For the page's links to its script and style.
    pub token: auth::Token,
}

/// The request kinds the page may send through `/api/request`: everything a rigctl user
/// may ask, but the subscriptions (the page's WebSocket holds those).
pub const PAGE_KINDS: &[&str] = &[
    "hello",
    "status",
    "list",
    "result",
    "submit",
    "cancel",
    "pause",
    "resume",
    "resume_session",
    "position",
    "move",
    "stop",
    "unlock",
    "home",
    "reconnect",
];

/// Every route, behind the token check.
pub fn router(app: App, token: auth::Token) -> Router {
    Router::new()
        .route("/", get(assets::index))
        .route("/app.js", get(assets::script))
        .route("/style.css", get(assets::style))
        .route("/ws", get(websocket))
        .route("/api/request", post(request))
        .route("/api/sessions/{name}/targets", get(targets))
        .route("/api/sessions/{name}/charts", get(plots::list))
        .route("/api/calibration", get(calibration))
        .route("/plots/{name}/{chart}", get(plots::chart))
        .route("/files/{name}/results.csv", get(results_csv))
        .route("/files/{name}/export.ome.tif", get(export::ome_tiff))
        .with_state(app)
        .layer(axum::middleware::from_fn_with_state(token, auth::check))
        .layer(tower_http::set_header::SetResponseHeaderLayer::overriding(
            header::REFERRER_POLICY,
            header::HeaderValue::from_static("no-referrer"),
        ))
        .layer(tower_http::set_header::SetResponseHeaderLayer::overriding(
            header::CACHE_CONTROL,
            header::HeaderValue::from_static("no-store"),
        ))
        .layer(tower_http::set_header::SetResponseHeaderLayer::overriding(
            header::X_FRAME_OPTIONS,
            header::HeaderValue::from_static("DENY"),
        ))
}

async fn websocket(State(app): State<App>, ws: WebSocketUpgrade) -> Response {
    ws.on_upgrade(move |socket| bridge::serve(socket, app.daemon))
}

/// An error the page shows: its status and a protocol-shaped error object.
pub fn error(status: StatusCode, code: &str, message: impl Into<String>) -> Response {
    let body = json!({"ok": false, "error": {"code": code, "message": message.into()}});
    (status, Json(body)).into_response()
}

/// `POST /api/request`: one protocol request (an object with `kind`) to the daemon; its
/// reply as the daemon wrote it (`ok`, `result` or `error`).
async fn request(State(app): State<App>, Json(req): Json<Value>) -> Response {
    let kind = req.get("kind").and_then(Value::as_str).unwrap_or("");
    if !PAGE_KINDS.contains(&kind) {
        return error(
            StatusCode::BAD_REQUEST,
            "bad_request",
            format!("`kind`: {kind:?} is not a request the page sends ({PAGE_KINDS:?})"),
        );
    }
    match app.daemon.ask(&req).await {
        Ok(reply) => Json(reply).into_response(),
        Err(e) => error(
            StatusCode::BAD_GATEWAY,
            "unavailable",
            crate::text::error_chain(e.chain()),
        ),
    }
}

/// A session's folder under the daemon's data root; `name` must be a plain folder name.
pub async fn session_dir(app: &App, name: &str) -> Result<PathBuf, Response> {
    let plain = !name.is_empty()
        && !name.starts_with('.')
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c));
    if !plain {
        return Err(error(
            StatusCode::BAD_REQUEST,
            "bad_request",
            format!("session {name:?}: not a session name (letters, digits, - _ .)"),
        ));
    }
    let root = app.daemon.data_root().await.map_err(|e| {
        error(
            StatusCode::BAD_GATEWAY,
            "unavailable",
            crate::text::error_chain(e.chain()),
        )
    })?;
    Ok(root.join(name))
}

/// `GET /files/NAME/results.csv`: the session's table, as a download.
async fn results_csv(State(app): State<App>, UrlPath(name): UrlPath<String>) -> Response {
    let dir = match session_dir(&app, &name).await {
        Ok(d) => d,
        Err(r) => return r,
    };
    match crate::nofollow::read_in(&dir, crate::results_csv::FILE) {
        Ok(bytes) => (
            [
                (header::CONTENT_TYPE, "text/csv; charset=utf-8".to_string()),
                (
                    header::CONTENT_DISPOSITION,
                    format!("attachment; filename=\"{name}-results.csv\""),
                ),
            ],
            bytes,
        )
            .into_response(),
        Err(e) => error(
            StatusCode::NOT_FOUND,
            "not_found",
            format!("session {name}: no {} ({e})", crate::results_csv::FILE),
        ),
    }
}

/// `GET /api/sessions/NAME/targets`: the session's results.csv rows as JSON.
async fn targets(State(app): State<App>, UrlPath(name): UrlPath<String>) -> Response {
    let dir = match session_dir(&app, &name).await {
        Ok(d) => d,
        Err(r) => return r,
    };
    match crate::results_csv::read(&dir.join(crate::results_csv::FILE)) {
        Ok(rows) => Json(json!({"session": name, "rows": rows})).into_response(),
        Err(e) => error(StatusCode::NOT_FOUND, "not_found", e),
    }
}

/// `GET /api/calibration`: the current calibration record's summary (none: `null`).
async fn calibration(State(app): State<App>) -> Response {
    let root = match app.daemon.data_root().await {
        Ok(r) => r,
        Err(e) => {
            return error(
                StatusCode::BAD_GATEWAY,
                "unavailable",
                crate::text::error_chain(e.chain()),
            )
        }
    };
    match crate::calibration_store::current(&root) {
        Ok(None) => Json(json!({"current": null})).into_response(),
        Ok(Some(a)) => {
            let c = &a.calibration;
            Json(json!({"current": {
                "id": c.id,
                "date": c.date,
                "age_days": age_days(&c.date),
                "method": c.method,
                "source": a.source,
                "frames": c.scan.frames,
                "step_um": c.scan.step_um,
                "travel_um": c.scan.travel_um,
                "residual_rms_um": c.field.residual_rms_um,
                "residual_max_um": c.field.residual_max_um,
                "rejected": c.rejected.len(),
            }}))
            .into_response()
        }
        Err(e) => Json(json!({"current": null, "error": crate::text::error_chain(e.chain())}))
            .into_response(),
    }
}

/// Days since an RFC 3339 date (None when it is not one).
fn age_days(date: &str) -> Option<f64> {
    let t =
        time::OffsetDateTime::parse(date, &time::format_description::well_known::Rfc3339).ok()?;
    Some((time::OffsetDateTime::now_utc() - t).as_seconds_f64() / 86_400.0)
}
