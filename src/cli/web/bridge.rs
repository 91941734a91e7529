//! The page's WebSocket: one daemon connection per open page, subscribed to every job's
//! events and to the preview, its lines passed on verbatim as text messages.
//!
//! The page sends `{"preview": {"max_fps", "scale", "crop"}}` to change its picture (a zoom
//! is a crop) and `{"preview": null}` to pause it; the rig is never paused by this.
//!
//! Frames are flow-controlled: one is in flight until the page says `{"painted": true}`;
//! meanwhile only the newest frame waits (older ones are dropped), so a slow browser gets
//! fewer frames, never older ones. A page that stops reading is dropped: after
//! [`SEND_TIMEOUT`] on a message it does not take, or [`PAINT_TIMEOUT`] without painting the
//! frame it has. Nothing is queued for it here.

use super::link::{Daemon, Link};
use crate::daemon::protocol::Request;
use axum::extract::ws::{Message, WebSocket};
use serde_json::{json, Value};
use std::time::Duration;
use tokio::time::Instant;

/// Longest a message may wait to go to the page before the page is dropped.
pub const SEND_TIMEOUT: Duration = Duration::from_secs(2);

/// Longest a frame may stay unpainted before the page is dropped (a hidden tab that the
/// browser throttles comes back through the page's own reconnection).
pub const PAINT_TIMEOUT: Duration = Duration::from_secs(10);

/// The preview a page gets until it asks for another.
pub const DEFAULT_FPS: f64 = 15.0;
pub const DEFAULT_SCALE: f64 = 0.5;

/// Serve one page until it goes or the daemon does.
pub async fn serve(mut ws: WebSocket, daemon: Daemon) {
    let mut link = match open(&daemon).await {
        Ok(l) => l,
        Err(e) => {
            let msg = json!({"type": "gateway", "daemon": "down", "error": crate::text::error_chain(e.chain())});
            let _ = send(&mut ws, msg.to_string()).await;
            return;
        }
    };
    let hello = json!({"type": "gateway", "daemon": "up"});
    if send(&mut ws, hello.to_string()).await.is_err() {
        return;
    }
    if let Err(e) = pump(&mut ws, &mut link).await {
        let msg = json!({"type": "gateway", "daemon": "lost", "error": crate::text::error_chain(e.chain())});
        let _ = send(&mut ws, msg.to_string()).await;
    }
}

/// A daemon connection subscribed to all events, with the default preview.
async fn open(daemon: &Daemon) -> anyhow::Result<Link> {
    let mut link = Link::connect(&daemon.socket).await?;
    link.send_request(&Request::Subscribe { job_id: None })
        .await?;
    link.send_request(&preview(DEFAULT_FPS, Some(DEFAULT_SCALE), None))
        .await?;
    Ok(link)
}

fn preview(max_fps: f64, scale: Option<f64>, crop: Option<[u32; 4]>) -> Request {
    Request::Preview {
        max_fps,
        scale,
        crop,
    }
}

/// The frames on their way to one page: at most one sent and unpainted, one waiting.
#[derive(Default)]
struct Frames {
    /// When the unpainted frame was sent.
    in_flight: Option<Instant>,
    waiting: Option<String>,
}

/// Resolves when the frame sent at `since` has waited [`PAINT_TIMEOUT`]; never without one.
async fn unpainted(since: Option<Instant>) {
    match since {
        Some(t) => tokio::time::sleep_until(t + PAINT_TIMEOUT).await,
        None => std::future::pending().await,
    }
}

/// Whether a daemon line is a preview event (a string value cannot hold this unescaped).
fn is_preview(line: &str) -> bool {
    line.contains(r#""event":"preview""#)
}

/// Daemon lines to the page, the page's preview changes to the daemon. `Ok` when the page
/// went; an error when the daemon did (or the page stopped reading).
async fn pump(ws: &mut WebSocket, link: &mut Link) -> anyhow::Result<()> {
    let mut frames = Frames::default();
    loop {
        tokio::select! {
            line = link.next_line() => {
                let line = line?;
                let preview = is_preview(&line);
                if preview && frames.in_flight.is_some() {
                    frames.waiting = Some(line);
                    continue;
                }
                if preview {
                    frames.in_flight = Some(Instant::now());
                }
                if send(ws, line).await.is_err() {
                    return Ok(());
                }
            }
            msg = ws.recv() => match msg {
                Some(Ok(Message::Text(t))) => {
                    if is_painted(t.as_str()) {
                        frames.in_flight = None;
                        if let Some(next) = frames.waiting.take() {
                            frames.in_flight = Some(Instant::now());
                            if send(ws, next).await.is_err() {
                                return Ok(());
                            }
                        }
                    } else if let Some(req) = page_request(t.as_str()) {
                        link.send_request(&req).await?;
                    }
                }
                Some(Ok(_)) => {}
                Some(Err(_)) | None => return Ok(()),
            },
            () = unpainted(frames.in_flight) => {
                tracing::info!("a page painted no frame for {PAINT_TIMEOUT:?}: dropped");
                return Ok(());
            }
        }
    }
}

/// The page's word that it painted the frame sent last.
fn is_painted(text: &str) -> bool {
    serde_json::from_str::<Value>(text).is_ok_and(|v| v.get("painted").is_some())
}

/// The daemon request a page's message asks for (None: not one the page may send).
fn page_request(text: &str) -> Option<Request> {
    let v: Value = serde_json::from_str(text).ok()?;
    let p = v.get("preview")?;
    if p.is_null() {
        return Some(Request::PreviewStop {});
    }
    let crop = p
        .get("crop")
        .and_then(|c| serde_json::from_value(c.clone()).ok());
    Some(preview(
        p.get("max_fps")
            .and_then(Value::as_f64)
            .unwrap_or(DEFAULT_FPS),
        p.get("scale").and_then(Value::as_f64),
        crop,
    ))
}

/// A text message to the page, or an error when it has not taken it in time.
async fn send(ws: &mut WebSocket, text: String) -> anyhow::Result<()> {
    match tokio::time::timeout(SEND_TIMEOUT, ws.send(Message::Text(text.into()))).await {
        Ok(r) => Ok(r?),
        Err(_) => anyhow::bail!("the page took no message for {SEND_TIMEOUT:?}: dropped"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pages_ask_for_previews_and_pauses_only() {
        assert_eq!(
            page_request(r#"{"preview": null}"#),
            Some(Request::PreviewStop {})
        );
        assert_eq!(
            page_request(r#"{"preview": {"max_fps": 20, "scale": 1, "crop": [1, 2, 30, 40]}}"#),
            Some(preview(20.0, Some(1.0), Some([1, 2, 30, 40])))
        );
        assert_eq!(page_request(r#"{"kind": "stop"}"#), None);
        assert_eq!(page_request(r#"{"painted": true}"#), None);
        assert!(is_painted(r#"{"painted": true}"#));
        assert_eq!(page_request("not json"), None);
    }
}

#[cfg(test)]
mod preview_lines {
    use super::is_preview;

    #[test]
    fn preview_events_are_told_from_other_lines() {
        let frame = r#"{"type":"event","job_id":0,"event":"preview","index":null}"#;
        assert!(is_preview(frame));
        assert!(!is_preview(
            r#"{"type":"event","job_id":3,"event":"step","index":1}"#
        ));
        // A label that quotes it is escaped on the wire.
        assert!(!is_preview(
            r#"{"type":"reply","result":{"label":"\"event\":\"preview\""}}"#
        ));
    }
}
