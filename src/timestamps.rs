//! Times as rigd records and prints them: seconds since the Unix epoch, and RFC 3339 (UTC).

use std::time::SystemTime;

pub fn unix_s(t: SystemTime) -> f64 {
    t.duration_since(SystemTime::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// A time as RFC 3339 UTC, to the second (the epoch for one before it).
pub fn rfc3339(t: SystemTime) -> String {
    rfc3339_unix(crate::timestamps::unix_s(t)).unwrap_or_else(|| "1970-01-01T00:00:00Z".into())
}

/// A time given in seconds since the epoch (as manifests record it); `None` outside
/// `0 < unix_s <= MAX_UNIX_S` (a year the formatter cannot write is never formatted).
pub fn rfc3339_unix(unix_s: f64) -> Option<String> {
    if !(unix_s > 0.0 && unix_s <= crate::bounds::MAX_UNIX_S) {
        return None;
    }
    let t = time::OffsetDateTime::from_unix_timestamp(unix_s.floor() as i64).ok()?;
    t.format(&time::format_description::well_known::Rfc3339)
        .ok()
}
