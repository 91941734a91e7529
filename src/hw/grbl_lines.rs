//! GRBL's lines, classified: replies (`ok`, `error:N`), pushes (`ALARM:N`, `[MSG:…]`, the
//! banner, `[…]` settings and build info) and `<…>` status reports, parsed into a state and
//! an X position in µm. Nothing here talks to a port.

/// GRBL's machine states as reported in `<State|…>`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GrblState {
    Idle,
    Run,
    /// `Hold:0` complete, `Hold:1` still decelerating.
    Hold {
        complete: bool,
    },
    Jog,
    Alarm,
    Door,
    Check,
    Home,
    Sleep,
}

impl std::fmt::Display for GrblState {
    /// As GRBL itself spells it in `<State|…>`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            GrblState::Idle => "Idle",
            GrblState::Run => "Run",
            GrblState::Hold { complete: true } => "Hold:0",
            GrblState::Hold { complete: false } => "Hold:1",
            GrblState::Jog => "Jog",
            GrblState::Alarm => "Alarm",
            GrblState::Door => "Door",
            GrblState::Check => "Check",
            GrblState::Home => "Home",
            GrblState::Sleep => "Sleep",
        })
    }
}

/// One `?` status report.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GrblReport {
    pub state: GrblState,
    /// Machine X position, µm.
    pub position_um: f64,
}

/// One line from GRBL, classified.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Line {
    Ok,
    Error(u32),
    Alarm(u32),
    Status(GrblReport),
    Banner(String),
    Msg(String),
    /// `$N=V`: one of the settings `$$` lists.
    Setting(u32, f64),
    Blank,
    Garbage(String),
}

pub(super) fn classify(raw: &[u8]) -> Line {
    let Ok(text) = std::str::from_utf8(raw) else {
        return Line::Garbage(String::from_utf8_lossy(raw).into_owned());
    };
    let t = text.trim();
    if t.is_empty() {
        return Line::Blank;
    }
    if t == "ok" {
        return Line::Ok;
    }
    if let Some(n) = t.strip_prefix("error:") {
        return n.parse().map_or(Line::Garbage(t.into()), Line::Error);
    }
    if let Some(n) = t.strip_prefix("ALARM:") {
        return n.parse().map_or(Line::Garbage(t.into()), Line::Alarm);
    }
    if t.starts_with("Grbl ") {
        return Line::Banner(t.into());
    }
    if t.starts_with('<') {
        return parse_report(t).map_or(Line::Garbage(t.into()), Line::Status);
    }
    if let Some((n, v)) = t.strip_prefix('$').and_then(|kv| kv.split_once('=')) {
        if let (Ok(n), Ok(v)) = (n.parse(), v.parse::<f64>()) {
            if v.is_finite() {
                return Line::Setting(n, v);
            }
        }
    }
    if t.starts_with('[') && t.ends_with(']') {
        return Line::Msg(t.into());
    }
    Line::Garbage(t.into())
}

/// `<Idle|MPos:1.000,0.000,0.000|FS:0,0>` (or `WPos` with `WCO`).
pub(super) fn parse_report(t: &str) -> Option<GrblReport> {
    let body = t.strip_prefix('<')?.strip_suffix('>')?;
    let mut fields = body.split('|');
    let state_field = fields.next()?;
    let (name, sub) = match state_field.split_once(':') {
        Some((n, s)) => (n, Some(s)),
        None => (state_field, None),
    };
    let state = match name {
        "Idle" => GrblState::Idle,
        "Run" => GrblState::Run,
        "Hold" => GrblState::Hold {
            complete: matches!(sub, None | Some("0")),
        },
        "Jog" => GrblState::Jog,
        "Alarm" => GrblState::Alarm,
        "Door" => GrblState::Door,
        "Check" => GrblState::Check,
        "Home" => GrblState::Home,
        "Sleep" => GrblState::Sleep,
        _ => return None,
    };
    let first_mm = |v: &str| -> Option<f64> {
        let x: f64 = v.split(',').next()?.trim().parse().ok()?;
        x.is_finite().then_some(x)
    };
    let (mut mpos, mut wpos, mut wco) = (None, None, None);
    for f in fields {
        if let Some(v) = f.strip_prefix("MPos:") {
            mpos = Some(first_mm(v)?);
        } else if let Some(v) = f.strip_prefix("WPos:") {
            wpos = Some(first_mm(v)?);
        } else if let Some(v) = f.strip_prefix("WCO:") {
            wco = Some(first_mm(v)?);
        }
    }
    let mm = mpos.or_else(|| wpos.map(|w| w + wco.unwrap_or(0.0)))?;
    Some(GrblReport {
        state,
        position_um: mm * 1000.0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_are_classified_without_mistaking_pushes_for_replies() {
        assert_eq!(classify(b"ok"), Line::Ok);
        assert_eq!(classify(b"error:22"), Line::Error(22));
        assert_eq!(classify(b"ALARM:1"), Line::Alarm(1));
        assert!(matches!(
            classify(b"Grbl 1.1h ['$' for help]"),
            Line::Banner(_)
        ));
        assert!(matches!(classify(b"[MSG:Reset to continue]"), Line::Msg(_)));
        assert!(matches!(classify(b"\xff\xfe#ok"), Line::Garbage(_)));
        assert!(matches!(classify(b"okay"), Line::Garbage(_)));
        assert_eq!(classify(b"$100=250.000"), Line::Setting(100, 250.0));
        assert!(matches!(classify(b"$100=nan"), Line::Garbage(_)));
        assert!(matches!(classify(b"error:x"), Line::Garbage(_)));
    }

    #[test]
    fn status_reports_give_state_and_position_in_um() {
        let r = parse_report("<Hold:1|MPos:12.345,0.000,0.000|FS:600,0>").unwrap();
        assert_eq!(r.state, GrblState::Hold { complete: false });
        assert!((r.position_um - 12_345.0).abs() < 1e-6);
        let r = parse_report("<Idle|WPos:1.000,0,0|FS:0,0|WCO:-0.500,0,0>").unwrap();
        assert!((r.position_um - 500.0).abs() < 1e-9);
        assert!(parse_report("<Idle|FS:0,0>").is_none());
        assert!(parse_report("<Dancing|MPos:0,0,0>").is_none());
        assert!(parse_report("<Idle|MPos:nan,0,0>").is_none());
    }
}
