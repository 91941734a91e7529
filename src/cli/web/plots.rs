//! A session's charts as SVG, drawn on request by the project's own plotters charts
//! (`plot::Chart`): the per-step residuals, the paper's Figures 4 and 5 (`figures`), and each
//! target's offsets with their u as error bars. Drawn off the async threads.

use super::routes::{error, session_dir, App};
use axum::extract::{Path as UrlPath, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use std::path::Path;

/// The chart of this name (stem) in the session, if it has one.
fn chart_of(dir: &Path, stem: &str) -> anyhow::Result<Option<crate::plot::Chart>> {
    if stem == super::offsets::STEM {
        return super::offsets::chart(dir).map(Some);
    }
    let charts = crate::cli::report::charts(dir)?;
    Ok(charts.into_iter().find(|(s, _)| s == stem).map(|(_, c)| c))
}

/// The stems of the session's charts, in the order the page shows them.
fn stems(dir: &Path) -> anyhow::Result<Vec<String>> {
    let mut v: Vec<String> = crate::cli::report::charts(dir)?
        .into_iter()
        .map(|(s, _)| s)
        .collect();
    v.insert(1.min(v.len()), super::offsets::STEM.to_string());
    Ok(v)
}

/// `GET /api/sessions/NAME/charts`: the names of the session's charts.
pub async fn list(State(app): State<App>, UrlPath(name): UrlPath<String>) -> Response {
    let dir = match session_dir(&app, &name).await {
        Ok(d) => d,
        Err(r) => return r,
    };
    match tokio::task::spawn_blocking(move || stems(&dir)).await {
        Ok(Ok(v)) => Json(serde_json::json!({"charts": v})).into_response(),
        Ok(Err(e)) => error(
            StatusCode::NOT_FOUND,
            "not_found",
            crate::text::error_chain(e.chain()),
        ),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string()),
    }
}

/// `GET /plots/NAME/STEM.svg`: one chart.
pub async fn chart(
    State(app): State<App>,
    UrlPath((name, file)): UrlPath<(String, String)>,
) -> Response {
    let Some(stem) = file.strip_suffix(".svg").map(str::to_string) else {
        return error(
            StatusCode::NOT_FOUND,
            "not_found",
            format!("{file:?}: charts are served as NAME.svg"),
        );
    };
    let dir = match session_dir(&app, &name).await {
        Ok(d) => d,
        Err(r) => return r,
    };
    let drawn = tokio::task::spawn_blocking(move || -> anyhow::Result<Option<String>> {
        match chart_of(&dir, &stem)? {
            Some(c) => Ok(Some(c.svg().map_err(anyhow::Error::msg)?)),
            None => Ok(None),
        }
    })
    .await;
    match drawn {
        Ok(Ok(Some(svg))) => ([(header::CONTENT_TYPE, "image/svg+xml")], svg).into_response(),
        Ok(Ok(None)) => error(
            StatusCode::NOT_FOUND,
            "not_found",
            format!("session {name} has no chart {file:?}"),
        ),
        Ok(Err(e)) => error(
            StatusCode::NOT_FOUND,
            "not_found",
            crate::text::error_chain(e.chain()),
        ),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string()),
    }
}
