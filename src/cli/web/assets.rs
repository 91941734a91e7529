//! The page, compiled into the binary (assets/web/): plain HTML, JavaScript and CSS, no
//! build step outside cargo, nothing fetched from elsewhere.

use super::routes::App;
use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;

const INDEX: &str = include_str!("../../../assets/web/index.html");
const SCRIPT: &str = include_str!("../../../assets/web/app.js");
const STYLE: &str = include_str!("../../../assets/web/style.css");

/// Everything the page loads comes from this gateway; no inline script.
const CSP: &str = "default-src 'self'; img-src 'self' data: blob:; connect-src 'self'; \
                   style-src 'self'; script-src 'self'; frame-ancestors 'none'";

/// The page, its links to the script and style carrying the token (every request does).
pub async fn index(State(app): State<App>) -> impl IntoResponse {
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CONTENT_SECURITY_POLICY, CSP),
        ],
        INDEX.replace("__TOKEN__", app.token.as_str()),
    )
}

pub async fn script() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
        SCRIPT,
    )
}

pub async fn style() -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "text/css; charset=utf-8")], STYLE)
}
