//! GRBL 1.1 axis driver (G-code over serial), in µm; GRBL speaks mm.
//!
//! The protocol rules it follows (GRBL's interface docs):
//! - Opening the port resets most boards: wait for the `Grbl 1.1…` banner (with a deadline;
//!   a board that does not reset on open gets a soft reset 0x18 and a second wait).
//! - One line at a time, each answered `ok` or `error:N`. `ok` only means "accepted into the
//!   planner", so `wait_settled` syncs with `G4 P0` (answered once the planner is empty) and
//!   then confirms `<Idle|…>` with a `?` status report.
//! - Push messages (`[MSG:…]`, `ALARM:N`, `<…>` reports, a banner after a reset) are not
//!   replies: they update what the driver knows and the wait goes on.
//! - Abort is feed hold `!`, wait for the hold to complete, soft reset 0x18, unlock.
//! - A timeout leaves a reply possibly in flight: the next command first drains the line.
//! - A vanished port drops the connection; the next call reopens it (or `reconnect()`).
//! - Limits are checked against the last target: GRBL's G91 moves are relative to the end of
//!   what is planned. When the driver does not know it (after connecting, an alarm, a
//!   reset), the position of an `Idle` report is the target; a stage that is not idle then
//!   is refused a move, since where it will end is unknown.
//! - `unlock()` is `$X` (after a soft reset if GRBL requires one), confirmed by a report that
//!   is no longer `Alarm`; `home()` is `$H` within `home_timeout_ms`.

use super::grbl_codes::{GrblAlarm, GrblErrorCode};
use super::limits::TravelLimits;
use super::serial::{Deadline, OverSerial, SerialLink};
use super::{HwError, MotionState, Stage, StageStatus};
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// What to do when the controller is in alarm (at connect, or after a fault) and a move is
/// asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OnAlarm {
    /// Refuse with the alarm: a person checks the machine, then homes or unlocks.
    #[default]
    Fail,
    /// Soft-reset if GRBL requires it, then `$X` and carry on (position may be off).
    Unlock,
}

/// `[axis] driver = "grbl"` settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GrblOptions {
    /// Serial device (`/dev/ttyUSB0`, `/dev/serial/by-id/…`, or a sim-grbl pty).
    pub port: String,
    #[serde(default = "defaults::baud")]
    pub baud: u32,
    /// Feed rate of moves, µm/s (sent as F in mm/min).
    #[serde(default = "defaults::feed_um_s")]
    pub feed_um_s: f64,
    /// Wait for the banner after opening (an Arduino bootloader takes ~1.5 s).
    #[serde(default = "defaults::banner_timeout_ms")]
    pub banner_timeout_ms: u64,
    /// Wait for an `ok`/`error` or a status report.
    #[serde(default = "defaults::reply_timeout_ms")]
    pub reply_timeout_ms: u64,
    /// Wait for the homing cycle.
    #[serde(default = "defaults::home_timeout_ms")]
    pub home_timeout_ms: u64,
    #[serde(default)]
    pub on_alarm: OnAlarm,
    /// Run `$H` right after connecting.
    #[serde(default)]
    pub home_on_connect: bool,
    pub limits: TravelLimits,
}

mod defaults {
    pub fn baud() -> u32 {
        115_200
    }
    pub fn feed_um_s() -> f64 {
        10_000.0
    }
    pub fn banner_timeout_ms() -> u64 {
        2_500
    }
    pub fn reply_timeout_ms() -> u64 {
        1_000
    }
    pub fn home_timeout_ms() -> u64 {
        60_000
    }
}

impl GrblOptions {
    /// Options with the defaults above.
    pub fn new(port: impl Into<String>, limits: TravelLimits) -> GrblOptions {
        GrblOptions {
            port: port.into(),
            baud: defaults::baud(),
            feed_um_s: defaults::feed_um_s(),
            banner_timeout_ms: defaults::banner_timeout_ms(),
            reply_timeout_ms: defaults::reply_timeout_ms(),
            home_timeout_ms: defaults::home_timeout_ms(),
            on_alarm: OnAlarm::Fail,
            home_on_connect: false,
            limits,
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        self.limits.validate()?;
        if !(self.feed_um_s.is_finite() && self.feed_um_s > 0.0) {
            return Err(format!(
                "feed_um_s must be positive, not {}",
                self.feed_um_s
            ));
        }
        if self.port.is_empty() {
            return Err("port is empty".into());
        }
        Ok(())
    }
}

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
enum Line {
    Ok,
    Error(u32),
    Alarm(u32),
    Status(GrblReport),
    Banner(String),
    Msg(String),
    Blank,
    Garbage(String),
}

fn classify(raw: &[u8]) -> Line {
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
    if t.starts_with('[') && t.ends_with(']') {
        return Line::Msg(t.into());
    }
    Line::Garbage(t.into())
}

/// `<Idle|MPos:1.000,0.000,0.000|FS:0,0>` (or `WPos` with `WCO`).
fn parse_report(t: &str) -> Option<GrblReport> {
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

/// Controller-side lock the driver knows about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Lock {
    /// The alarm code, if GRBL said which (a boot lock has none).
    alarm: Option<u32>,
    /// GRBL accepts nothing but a soft reset (after a hard or soft limit).
    needs_reset: bool,
}

/// A GRBL-driven axis.
#[derive(Debug)]
pub struct GrblStage {
    name: String,
    opts: GrblOptions,
    link: SerialLink,
    /// Where the last accepted move ends, µm (None: ask the controller).
    target_um: Option<f64>,
    lock: Option<Lock>,
    garbage_lines: u64,
    banners_seen: u64,
}

/// How long a line must stay quiet to count as drained.
const DRAIN_QUIET: Duration = Duration::from_millis(30);
/// Status polling interval while waiting for Idle or a completed hold.
const POLL: Duration = Duration::from_millis(2);
/// How often a homing cycle looks for a `stop` while it waits for its `ok`.
const HOME_POLL: Duration = Duration::from_millis(10);

impl GrblStage {
    /// A driver that connects on first use (lazy open). Fails only on bad options.
    pub fn new(name: impl Into<String>, opts: GrblOptions) -> Result<GrblStage, HwError> {
        let name = name.into();
        opts.validate().map_err(|message| HwError::Other {
            device: name.clone(),
            message: format!("bad grbl options: {message}"),
        })?;
        Ok(GrblStage {
            link: SerialLink::new(&name, &opts.port, opts.baud, DRAIN_QUIET),
            name,
            opts,
            target_um: None,
            lock: None,
            garbage_lines: 0,
            banners_seen: 0,
        })
    }

    /// A driver connected now (banner received, alarm policy applied).
    pub fn connect(name: impl Into<String>, opts: GrblOptions) -> Result<GrblStage, HwError> {
        let mut s = GrblStage::new(name, opts)?;
        s.reconnect()?;
        Ok(s)
    }

    /// Close and reopen the port (after `PortGone`, or to pick up a replugged adapter).
    pub fn reconnect(&mut self) -> Result<(), HwError> {
        self.reopen()
    }

    pub fn is_connected(&self) -> bool {
        self.link.is_open()
    }

    /// Lines that were neither replies nor known push messages (line noise), so far.
    pub fn garbage_lines(&self) -> u64 {
        self.garbage_lines
    }

    /// Banners seen (one per connect, plus one per reset).
    pub fn banners_seen(&self) -> u64 {
        self.banners_seen
    }

    /// The alarm the controller is locked in, if the driver knows of one.
    pub fn alarm(&self) -> Option<GrblAlarm> {
        self.lock.and_then(|l| l.alarm).map(GrblAlarm::from_code)
    }

    /// Send one raw line (bring-up, `$$`, `$I`) and wait for its `ok`.
    pub fn send_line(&mut self, line: &str) -> Result<(), HwError> {
        let dl = self.reply_deadline();
        self.guard(|s| {
            s.ensure_connected()?;
            s.command(line, dl)
        })
    }

    /// One status report.
    pub fn report(&mut self) -> Result<GrblReport, HwError> {
        let dl = self.reply_deadline();
        self.guard(|s| {
            s.ensure_connected()?;
            s.query(dl)
        })
    }

    fn reply_deadline(&self) -> Deadline {
        Deadline::after(Duration::from_millis(self.opts.reply_timeout_ms))
    }

    /// After (re)opening: wait for the banner, learn the lock state, home if configured.
    fn greet(&mut self) -> Result<(), HwError> {
        self.lock = None;
        self.target_um = None;
        let banner = Duration::from_millis(self.opts.banner_timeout_ms);
        match self.wait_banner(Deadline::after(banner)) {
            Ok(()) => {}
            Err(HwError::Timeout { .. }) => {
                // No reset on open (DTR not wired, or a board already booted): ask for one.
                tracing::info!(device = %self.name, "no banner on open; sending a soft reset");
                self.link.write(&[0x18])?;
                self.wait_banner(Deadline::after(banner))?;
            }
            Err(e) => return Err(e),
        }
        // The report tells us whether GRBL booted locked.
        let dl = self.reply_deadline();
        let report = self.query(dl)?;
        self.target_um = Some(report.position_um);
        if self.opts.home_on_connect {
            self.home_cycle()?;
        }
        tracing::info!(device = %self.name, port = %self.opts.port, "grbl connected");
        Ok(())
    }

    /// Read until the banner; everything before it is boot noise.
    fn wait_banner(&mut self, dl: Deadline) -> Result<(), HwError> {
        loop {
            let raw = self.link.read_line(dl, "the Grbl banner")?;
            match classify(&raw) {
                Line::Banner(b) => {
                    self.note(&Line::Banner(b));
                    return Ok(());
                }
                other => self.note(&other),
            }
        }
    }

    /// Update what we know from a push message (or count line noise).
    fn note(&mut self, line: &Line) {
        match line {
            Line::Alarm(code) => {
                let alarm = GrblAlarm::from_code(*code);
                tracing::warn!(device = %self.name, %alarm, "grbl alarm");
                self.lock = Some(Lock {
                    alarm: Some(*code),
                    needs_reset: alarm.needs_reset(),
                });
                self.target_um = None;
            }
            Line::Msg(m) => {
                if m.contains("Reset to continue") {
                    let alarm = self.lock.and_then(|l| l.alarm);
                    self.lock = Some(Lock {
                        alarm,
                        needs_reset: true,
                    });
                } else if m.contains("to unlock") && self.lock.is_none() {
                    self.lock = Some(Lock {
                        alarm: None,
                        needs_reset: false,
                    });
                }
                tracing::debug!(device = %self.name, msg = %m, "grbl message");
            }
            Line::Status(r) => match r.state {
                GrblState::Alarm if self.lock.is_none() => {
                    self.lock = Some(Lock {
                        alarm: None,
                        needs_reset: false,
                    })
                }
                GrblState::Alarm => {}
                _ => self.lock = None,
            },
            Line::Banner(b) => {
                self.banners_seen += 1;
                self.target_um = None;
                // A reset clears the reset requirement; an alarm lock may survive it.
                if let Some(l) = &mut self.lock {
                    l.needs_reset = false;
                }
                tracing::debug!(device = %self.name, banner = %b, "grbl banner");
            }
            Line::Garbage(g) => {
                self.garbage_lines += 1;
                tracing::warn!(device = %self.name, line = %g, "ignoring line noise");
            }
            Line::Ok | Line::Error(_) => {
                tracing::warn!(device = %self.name, ?line, "stray reply ignored");
            }
            Line::Blank => {}
        }
    }

    /// Send one line and wait for its `ok` / `error:N`.
    fn command(&mut self, line: &str, dl: Deadline) -> Result<(), HwError> {
        self.link.write_line(line)?;
        let waiting_for = format!("reply to {line:?}");
        loop {
            let raw = self.link.read_line(dl, &waiting_for)?;
            match classify(&raw) {
                Line::Ok => return Ok(()),
                Line::Error(code) => {
                    let e = GrblErrorCode::from_code(code);
                    return Err(HwError::Controller {
                        device: self.name.clone(),
                        code: code as i32,
                        message: format!("{} (for {line:?})", e.text()),
                    });
                }
                Line::Alarm(code) => {
                    self.note(&Line::Alarm(code));
                    return Err(self.alarm_error(Some(code)));
                }
                Line::Banner(b) => {
                    self.note(&Line::Banner(b));
                    return Err(HwError::Other {
                        device: self.name.clone(),
                        message: format!("controller reset while waiting for the {waiting_for}"),
                    });
                }
                other => self.note(&other),
            }
        }
    }

    /// Ask for a `?` status report.
    fn query(&mut self, dl: Deadline) -> Result<GrblReport, HwError> {
        self.link.write(b"?")?;
        loop {
            let raw = self.link.read_line(dl, "a status report")?;
            match classify(&raw) {
                Line::Status(r) => {
                    self.note(&Line::Status(r));
                    return Ok(r);
                }
                other => self.note(&other),
            }
        }
    }

    fn alarm_error(&self, code: Option<u32>) -> HwError {
        match code {
            Some(c) => HwError::Alarm {
                device: self.name.clone(),
                code: c,
                message: GrblAlarm::from_code(c).text().to_string(),
            },
            None => HwError::Alarm {
                device: self.name.clone(),
                code: 0,
                message: "controller is locked in alarm state ('$H' to home or '$X' to unlock)"
                    .into(),
            },
        }
    }

    /// Before a move: apply the alarm policy if GRBL is locked.
    fn ensure_unlocked(&mut self) -> Result<(), HwError> {
        let Some(lock) = self.lock else {
            return Ok(());
        };
        match self.opts.on_alarm {
            OnAlarm::Fail => Err(self.alarm_error(lock.alarm)),
            OnAlarm::Unlock => {
                let alarm = lock.alarm.map_or("none".into(), |a| a.to_string());
                tracing::warn!(device = %self.name, alarm = %alarm, needs_reset = lock.needs_reset,
                    "unlocking per on_alarm = \"unlock\"");
                if lock.needs_reset {
                    self.soft_reset()?;
                }
                let dl = self.reply_deadline();
                self.command("$X", dl)?;
                self.lock = None;
                self.target_um = None;
                Ok(())
            }
        }
    }

    /// 0x18 and wait for the banner.
    fn soft_reset(&mut self) -> Result<(), HwError> {
        self.link.write(&[0x18])?;
        let dl = Deadline::after(Duration::from_millis(self.opts.banner_timeout_ms));
        self.wait_banner(dl)
    }

    /// Where moves start from: the last target, or the position of an idle controller.
    fn start_um(&mut self) -> Result<f64, HwError> {
        if let Some(t) = self.target_um {
            return Ok(t);
        }
        let dl = self.reply_deadline();
        let r = self.query(dl)?;
        match r.state {
            GrblState::Idle | GrblState::Alarm | GrblState::Check | GrblState::Sleep => {
                Ok(r.position_um)
            }
            other => Err(HwError::Other {
                device: self.name.clone(),
                message: format!(
                    "the controller is {other:?} at {:.1} µm and its target is unknown: \
                     wait for the move to end (or stop it) before moving again",
                    r.position_um
                ),
            }),
        }
    }

    /// A wait that ran out while GRBL kept answering: say what it reports. Its target is
    /// forgotten, so no move is planned on top of one that has not ended.
    fn still_moving(&mut self, dl: Deadline) -> HwError {
        self.target_um = None;
        let state = match self.query(self.reply_deadline()) {
            Ok(r) => format!("still {} at {:.1} µm", r.state, r.position_um),
            Err(e) => return e,
        };
        HwError::NotSettled {
            device: self.name.clone(),
            timeout_ms: dl.budget.as_millis() as u64,
            state,
        }
    }

    /// `$X` (after a soft reset if GRBL asks for one), confirmed by a report out of alarm.
    fn unlock_now(&mut self) -> Result<(), HwError> {
        if self.lock.is_some_and(|l| l.needs_reset) {
            self.soft_reset()?;
        }
        let dl = self.reply_deadline();
        self.command("$X", dl)?;
        let r = self.query(dl)?;
        if r.state == GrblState::Alarm {
            return Err(self.alarm_error(self.lock.and_then(|l| l.alarm)));
        }
        self.lock = None;
        self.target_um = Some(r.position_um);
        tracing::info!(device = %self.name, at_um = r.position_um, "unlocked ($X)");
        Ok(())
    }

    fn feed_mm_min(&self) -> f64 {
        self.opts.feed_um_s * 60.0 / 1000.0
    }

    fn home_cycle(&mut self) -> Result<(), HwError> {
        if self.lock.is_some_and(|l| l.needs_reset) {
            self.soft_reset()?;
        }
        let dl = Deadline::after(Duration::from_millis(self.opts.home_timeout_ms));
        self.command("$H", dl)?;
        self.lock = None;
        let dl = self.reply_deadline();
        self.target_um = Some(self.query(dl)?.position_um);
        Ok(())
    }

    /// `$H`, its reply awaited in short reads so `stopped()` is polled between them. GRBL
    /// takes no feed hold during homing: a stop is a soft reset, after which it is in alarm
    /// (`Ok(true)`; `status` reports it, `unlock` or `home` clears it).
    fn home_cycle_until(&mut self, stopped: &dyn Fn() -> bool) -> Result<bool, HwError> {
        if self.lock.is_some_and(|l| l.needs_reset) {
            self.soft_reset()?;
        }
        let dl = Deadline::after(Duration::from_millis(self.opts.home_timeout_ms));
        self.link.write_line("$H")?;
        let waiting_for = "reply to \"$H\"";
        loop {
            if stopped() {
                tracing::warn!(device = %self.name, "homing stopped: soft reset");
                self.soft_reset()?;
                self.target_um = None;
                return Ok(true);
            }
            let left = dl.at.saturating_duration_since(std::time::Instant::now());
            let poll = Deadline::after(HOME_POLL.min(left));
            let raw = match self.link.read_line(poll, waiting_for) {
                Ok(raw) => raw,
                Err(HwError::Timeout { .. }) if !dl.expired() => continue,
                Err(HwError::Timeout { .. }) => {
                    return Err(HwError::Timeout {
                        device: self.name.clone(),
                        timeout_ms: dl.budget.as_millis() as u64,
                        waiting_for: waiting_for.to_string(),
                    })
                }
                Err(e) => return Err(e),
            };
            match classify(&raw) {
                Line::Ok => break,
                Line::Error(code) => {
                    return Err(HwError::Controller {
                        device: self.name.clone(),
                        code: code as i32,
                        message: format!("{} (for \"$H\")", GrblErrorCode::from_code(code).text()),
                    })
                }
                Line::Alarm(code) => {
                    self.note(&Line::Alarm(code));
                    return Err(self.alarm_error(Some(code)));
                }
                other => self.note(&other),
            }
        }
        self.lock = None;
        let dl = self.reply_deadline();
        self.target_um = Some(self.query(dl)?.position_um);
        Ok(false)
    }

    fn move_to(&mut self, target_um: f64, gcode: String) -> Result<(), HwError> {
        self.ensure_unlocked()?;
        let dl = self.reply_deadline();
        self.command(&gcode, dl)?;
        self.target_um = Some(target_um);
        Ok(())
    }
}

impl OverSerial for GrblStage {
    fn link(&mut self) -> &mut SerialLink {
        &mut self.link
    }

    fn handshake(&mut self) -> Result<(), HwError> {
        self.greet()
    }

    fn port_lost(&mut self) {
        self.target_um = None;
    }
}

fn state_of(s: GrblState) -> MotionState {
    match s {
        GrblState::Idle | GrblState::Check | GrblState::Sleep => MotionState::Idle,
        GrblState::Run | GrblState::Jog => MotionState::Moving,
        GrblState::Hold { .. } | GrblState::Door => MotionState::Holding,
        GrblState::Home => MotionState::Homing,
        GrblState::Alarm => MotionState::Alarm,
    }
}

impl Stage for GrblStage {
    fn name(&self) -> &str {
        &self.name
    }

    fn move_rel(&mut self, delta_um: f64) -> Result<(), HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            let from = s.start_um()?;
            let target = s.opts.limits.check_rel(&s.name, from, delta_um)?;
            let g = format!("G91 G1 X{:.5} F{:.1}", delta_um / 1000.0, s.feed_mm_min());
            s.move_to(target, g)
        })
    }

    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError> {
        self.guard(|s| {
            s.opts.limits.check_abs(&s.name, target_um)?;
            s.ensure_connected()?;
            let from = s.start_um()?;
            s.opts.limits.check_move(&s.name, from, target_um)?;
            let g = format!("G90 G1 X{:.5} F{:.1}", target_um / 1000.0, s.feed_mm_min());
            s.move_to(target_um, g)
        })
    }

    fn wait_settled(&mut self, timeout: Duration) -> Result<f64, HwError> {
        let dl = Deadline::after(timeout);
        self.guard(|s| {
            s.ensure_connected()?;
            if let Some(l) = s.lock {
                return Err(s.alarm_error(l.alarm));
            }
            // `ok` to G4 P0 comes once the planner has run dry; `?` confirms Idle.
            match s.command("G4 P0", dl) {
                Err(HwError::Timeout { .. }) => return Err(s.still_moving(dl)),
                r => r?,
            }
            loop {
                let r = s.query(dl)?;
                match r.state {
                    GrblState::Idle => return Ok(r.position_um),
                    GrblState::Alarm => return Err(s.alarm_error(s.lock.and_then(|l| l.alarm))),
                    _ if dl.expired() => {
                        return Err(HwError::NotSettled {
                            device: s.name.clone(),
                            timeout_ms: dl.budget.as_millis() as u64,
                            state: format!("still {} at {:.1} µm", r.state, r.position_um),
                        })
                    }
                    _ => std::thread::sleep(POLL),
                }
            }
        })
    }

    fn position_um(&mut self) -> Result<f64, HwError> {
        Ok(self.report()?.position_um)
    }

    fn stop(&mut self) -> Result<(), HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            let locked_before = s.lock.is_some();
            // Feed hold first so the axis decelerates under control and keeps its position.
            s.link.write(b"!")?;
            let dl = s.reply_deadline();
            loop {
                let r = s.query(dl)?;
                match r.state {
                    GrblState::Hold { complete: false } | GrblState::Run | GrblState::Jog => {
                        if dl.expired() {
                            break;
                        }
                        std::thread::sleep(POLL);
                    }
                    _ => break,
                }
            }
            // Then a reset flushes the planner; GRBL keeps the position after a completed hold.
            s.soft_reset()?;
            let dl = s.reply_deadline();
            let r = s.query(dl)?;
            if r.state == GrblState::Alarm && !locked_before {
                // Our own abort locked it: the hold completed, so the position is sound.
                s.command("$X", dl)?;
                s.lock = None;
            }
            s.target_um = Some(r.position_um);
            Ok(())
        })
    }

    fn home(&mut self) -> Result<(), HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            s.home_cycle()
        })
    }

    fn home_stoppable(&mut self, stopped: &dyn Fn() -> bool) -> Result<bool, HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            s.home_cycle_until(stopped)
        })
    }

    fn unlock(&mut self) -> Result<(), HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            s.unlock_now()
        })
    }

    fn reconnect(&mut self) -> Result<(), HwError> {
        self.reopen()
    }

    fn resume(&mut self) -> Result<(), HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            // Cycle start: a realtime byte, answered by no `ok`.
            s.link.write(b"~")?;
            let r = s.query(s.reply_deadline())?;
            match r.state {
                GrblState::Hold { .. } | GrblState::Door => Err(HwError::Other {
                    device: s.name.clone(),
                    message: format!(
                        "still holding at {:.1} µm after cycle start (a safety door open?)",
                        r.position_um
                    ),
                }),
                _ => Ok(()),
            }
        })
    }

    fn status(&mut self) -> Result<StageStatus, HwError> {
        let r = self.report()?;
        Ok(StageStatus {
            state: state_of(r.state),
            position_um: r.position_um,
        })
    }
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

    #[test]
    fn options_are_checked() {
        let lim = TravelLimits::new(0.0, 1000.0, 100.0).unwrap();
        let mut o = GrblOptions::new("/dev/null", lim);
        o.feed_um_s = 0.0;
        let e = GrblStage::new("axis", o).unwrap_err();
        assert!(e.to_string().contains("feed_um_s"), "{e}");
        let toml = "port = \"/dev/ttyUSB0\"\non_alarm = \"unlock\"\n[limits]\nmin_um = 0\nmax_um = 1e5\nmax_step_um = 500\n";
        let o: GrblOptions = toml::from_str(toml).unwrap();
        assert_eq!(o.on_alarm, OnAlarm::Unlock);
        assert_eq!(o.baud, 115_200);
    }
}
