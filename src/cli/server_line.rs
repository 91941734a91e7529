//! The daemon's lines as a client reads them: tolerant where the daemon is strict, so an
//! older rigctl keeps working against a newer rigd (docs/protocol.md, "Compatibility").
//!
//! - A line type or an event kind this build does not know is skipped, not an error.
//! - Unknown fields are ignored (serde's default on the wire structs).
//! - A known event whose nested document does not decode (a newer daemon's `job` with a
//!   field this build lacks, a `detail` with a new `kind`) is kept without that document.
//! - An error code this build does not know reads as `ErrorCode::Other`.

use crate::daemon::protocol::{ServerLine, EVENT_KINDS};
use serde_json::Value;

/// A line from the daemon, decoded.
#[derive(Debug)]
pub enum Decoded {
    Line(Box<ServerLine>),
    /// Something this build does not know (named), skipped.
    Skipped(String),
}

/// Decode one line from the daemon. An error only for a line that is not JSON, has no
/// `type`, or is a reply or a known event whose required fields do not decode.
pub fn decode(line: &str) -> Result<Decoded, String> {
    let value: Value = serde_json::from_str(line).map_err(|e| format!("not JSON ({e})"))?;
    let ty = value.get("type").and_then(Value::as_str);
    match ty {
        Some("reply") => {}
        Some("event") => match value.get("event").and_then(Value::as_str) {
            Some(k) if EVENT_KINDS.contains(&k) => {}
            Some(k) => return Ok(Decoded::Skipped(format!("event `{k}`"))),
            None => return Err("an event line without `event`".into()),
        },
        Some(other) => return Ok(Decoded::Skipped(format!("line type `{other}`"))),
        None => return Err("a line without `type`".into()),
    }
    match serde_json::from_value::<ServerLine>(value.clone()) {
        Ok(l) => Ok(Decoded::Line(Box::new(l))),
        Err(first) => without_documents(value).ok_or_else(|| first.to_string()),
    }
}

/// The line decoded again without its nested objects (the optional documents), if that
/// works; which ones were left out is logged.
fn without_documents(mut value: Value) -> Option<Decoded> {
    let map = value.as_object_mut()?;
    let nested: Vec<String> = map
        .iter()
        .filter(|(_, v)| v.is_object())
        .map(|(k, _)| k.clone())
        .collect();
    if nested.is_empty() {
        return None;
    }
    for k in &nested {
        map.remove(k);
    }
    let line = serde_json::from_value::<ServerLine>(value).ok()?;
    tracing::debug!("rigd sent {nested:?} in a shape this rigctl does not know: left out");
    Some(Decoded::Line(Box::new(line)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::protocol::{ErrorCode, Event, EventBody};

    fn line(text: &str) -> ServerLine {
        match decode(text) {
            Ok(Decoded::Line(l)) => *l,
            other => panic!("{text}: {other:?}"),
        }
    }

    fn event(text: &str) -> Event {
        match line(text) {
            ServerLine::Event(e) => e,
            other => panic!("not an event: {other:?}"),
        }
    }

    #[test]
    fn unknown_kinds_and_line_types_are_skipped() {
        let skipped = |text: &str| match decode(text) {
            Ok(Decoded::Skipped(what)) => what,
            other => panic!("{text}: {other:?}"),
        };
        assert_eq!(
            skipped(r#"{"type":"event","v":1,"job_id":1,"event":"levitated","at_index":3}"#),
            "event `levitated`"
        );
        assert_eq!(
            skipped(r#"{"type":"notice","v":1,"text":"hi"}"#),
            "line type `notice`"
        );
        assert!(decode("not json").unwrap_err().starts_with("not JSON"));
        assert_eq!(decode(r#"{"v":1}"#).unwrap_err(), "a line without `type`");
        // A known kind that misses a required field is still an error.
        let e = decode(r#"{"type":"event","v":1,"job_id":1,"event":"started"}"#).unwrap_err();
        assert!(e.contains("session"), "{e}");
    }

    #[test]
    fn unknown_fields_are_ignored_at_every_level() {
        let e = event(
            r#"{"type":"event","v":1,"job_id":2,"event":"finished","session":"s","results_path":"/x","new":{"a":1}}"#,
        );
        assert_eq!(
            (e.job_id, e.body),
            (
                2,
                EventBody::Finished {
                    session: "s".into()
                }
            )
        );
        // A newer daemon's job (a field this build's strict JobSpec refuses): kept without it.
        let e = event(
            r#"{"type":"event","v":1,"job_id":3,"event":"accepted","queue_position":0,"total_frames":4,"job":{"step_um":5,"steps":4,"plan":{"kind":"grid"}}}"#,
        );
        assert!(matches!(
            e.body,
            EventBody::Accepted {
                total_frames: 4,
                job: None,
                ..
            }
        ));
        // A failure detail with a kind this build does not know: the reason stays.
        let e = event(
            r#"{"type":"event","v":1,"job_id":3,"event":"failed","reason":"r","detail":{"kind":"paused_too_long"}}"#,
        );
        assert!(
            matches!(e.body, EventBody::Failed { ref reason, detail: None, .. } if reason == "r")
        );
        let ServerLine::Reply(r) = line(
            r#"{"type":"reply","v":1,"id":4,"ok":false,"error":{"code":"quota","message":"m","hint":"h"},"extra":true}"#,
        ) else {
            panic!("not a reply")
        };
        let err = r.error.unwrap();
        assert_eq!((err.code, err.message.as_str()), (ErrorCode::Other, "m"));
    }
}
