//! GRBL 1.1 axis driver (G-code over serial), in µm; GRBL speaks mm.
//!
//! The protocol rules it follows (GRBL's interface docs, and GRBL 1.1h's own firmware in
//! `tests/suite/grbl_firmware.rs`):
//! - Opening the port resets most boards: wait for the `Grbl 1.1…` banner. A board that
//!   does not reset on open may be mid-move, so it is asked for a status report, never reset.
//!   `$$` then gives the motor step (`$100`), top speed (`$110`) and acceleration (`$120`):
//!   [`Stage::machine`].
//! - One line at a time, each answered `ok` or `error:N`. `ok` only means "accepted into the
//!   planner": a move is followed by `G4 P0`, whose `ok` comes once the planner is empty —
//!   that `ok` is the move's end. Any other line waits for it first.
//! - `?` at 5 Hz on average (`status_poll_hz`, [`PollBudget`]; GRBL asks for no more, since
//!   each report costs the main loop that feeds the stepper): `status()` answers from the
//!   last report while it stands ([`POLL`] at rest, longer while a move's `ok` is awaited).
//!   The report that confirms a move's end counts too, so steps come at 5 a second at most.
//! - Push messages (`[MSG:…]`, `ALARM:N`, `<…>` reports, a banner after a reset) are not
//!   replies: they update what the driver knows and the wait goes on.
//! - Stop is a feed hold `!` (or jog cancel 0x85 for a jog), polled at 10 Hz until the hold
//!   completes (`Hold:0`), then a soft reset, which clears the planner without an alarm. A
//!   controller still moving after braking twice over (or homing) is reset anyway as the last
//!   resort: `ALARM:3`, the position lost, a fault for the user to clear.
//! - A timeout leaves a reply possibly in flight: the next command first drains the line.
//! - A vanished port drops the connection; the next call reopens it (or `reconnect()`).
//! - Limits are checked against the last target: GRBL's G91 moves are relative to the end of
//!   what is planned. When the driver does not know it (after connecting, an alarm, a
//!   reset), the position of an `Idle` report is the target; a stage that is not idle then
//!   is refused a move, since where it will end is unknown.
//! - Waits scale with the move's planned time at the controller's rate and acceleration.
//! - `unlock()` is `$X` (after a soft reset if GRBL requires one), confirmed by a report that
//!   is not `Alarm`; `home()` is `$H` within `home_timeout_ms`.

use super::grbl_codes::{GrblAlarm, GrblErrorCode};
use super::grbl_lines::{classify, Line};
pub use super::grbl_lines::{GrblReport, GrblState};
use super::limits::TravelLimits;
use super::poll_budget::PollBudget;
use super::serial::{Deadline, OverSerial, SerialLink};
use super::{HwError, MotionState, Stage, StageMachine, StageStatus};
use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant};

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
    /// Average rate of `?` status reports, Hz: GRBL asks for 5 at most, 10 "may be
    /// possible" (a config may set up to [`MAX_POLL_HZ`]). Each step's end is confirmed by
    /// one, so it also caps steps per second.
    #[serde(default = "defaults::status_poll_hz")]
    pub status_poll_hz: f64,
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
    pub fn status_poll_hz() -> f64 {
        5.0
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
            status_poll_hz: defaults::status_poll_hz(),
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
        if !(self.status_poll_hz.is_finite() && self.status_poll_hz > 0.0) {
            return Err(format!(
                "status_poll_hz must be a positive number, not {}",
                self.status_poll_hz
            ));
        }
        if self.port.is_empty() {
            return Err("port is empty".into());
        }
        Ok(())
    }
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
    /// A move the controller accepted whose end is not yet known: the `ok` to the `G4 P0`
    /// sent behind it comes once the planner has run dry.
    in_flight: bool,
    /// No line has been sent since the last `G4 P0` was answered: the planner is empty.
    synced: bool,
    /// The last status report and when it came: `status()` answers from it between polls.
    last: Option<(Instant, GrblReport)>,
    /// The `?` rate budget ([`GrblOptions::status_poll_hz`]).
    budget: PollBudget,
    /// `$100`/`$110`/`$120`, read at connect.
    machine: Option<StageMachine>,
    /// How long the last move sent takes at the controller's rate.
    planned: Option<Duration>,
    polls: u64,
    garbage_lines: u64,
    banners_seen: u64,
}

/// How long a line must stay quiet to count as drained.
const DRAIN_QUIET: Duration = Duration::from_millis(30);
/// How long a report stands for the current state when nothing is moving.
pub const POLL: Duration = Duration::from_millis(200);
/// How long a report stands for the current state while a move runs: a move's end comes
/// as the `ok` to its `G4 P0`, so following it needs few reports, and the budget is kept
/// for the report that confirms where it ended.
const FOLLOW: Duration = Duration::from_millis(500);
/// The most a config may set for a real board: GRBL's interface document says "10Hz may be
/// possible". (An emulator, which has no stepper to starve, may be polled faster.)
pub const MAX_POLL_HZ: f64 = 10.0;
/// The budget `rigd --sim` gives its emulated GRBL: it has no stepper to starve, and a
/// step's confirming report then never waits.
pub const EMULATOR_POLL_HZ: f64 = 100.0;
/// Between `?` polls while a stop waits for the feed hold to complete (10 Hz, GRBL's most).
const STOP_POLL: Duration = Duration::from_millis(100);
/// A read that takes only what has already arrived.
const NO_WAIT: Duration = Duration::from_millis(1);
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
            budget: PollBudget::new(opts.status_poll_hz, Instant::now()),
            name,
            opts,
            target_um: None,
            lock: None,
            in_flight: false,
            synced: false,
            last: None,
            machine: None,
            planned: None,
            polls: 0,
            garbage_lines: 0,
            banners_seen: 0,
        })
    }

    /// A driver connected now (banner or status report received, alarm policy applied).
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

    /// Status reports asked for (`?` sent), so far.
    pub fn polls(&self) -> u64 {
        self.polls
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

    /// One status report, asked for now.
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

    /// Everything known of the controller's state, forgotten (a new connection).
    fn forget(&mut self) {
        self.lock = None;
        self.target_um = None;
        self.in_flight = false;
        self.synced = false;
        self.last = None;
    }

    /// After (re)opening: wait for the banner (or ask for a report: a board that does not
    /// reset on open may be mid-move, and is never reset for it), learn the lock state and
    /// the machine settings, home if configured.
    fn greet(&mut self) -> Result<(), HwError> {
        self.forget();
        let banner = Duration::from_millis(self.opts.banner_timeout_ms);
        match self.wait_banner(Deadline::after(banner)) {
            Ok(()) => {}
            Err(HwError::Timeout { .. }) => {
                tracing::info!(device = %self.name, "no banner on open; asking for a status report");
            }
            Err(e) => return Err(e),
        }
        let report = self
            .query(self.reply_deadline())
            .map_err(|e| self.silent(e))?;
        if matches!(report.state, GrblState::Idle | GrblState::Alarm) {
            self.target_um = Some(report.position_um);
            self.read_machine();
        } else {
            tracing::warn!(device = %self.name, state = %report.state, at_um = report.position_um,
                "connected to a controller that is busy: no move until it is idle");
        }
        if self.opts.home_on_connect {
            self.home_cycle()?;
        }
        tracing::info!(device = %self.name, port = %self.opts.port, "grbl connected");
        Ok(())
    }

    /// A connect that heard neither a banner nor a report: say what was tried.
    fn silent(&self, e: HwError) -> HwError {
        match e {
            HwError::Timeout { timeout_ms, .. } => HwError::Timeout {
                device: self.name.clone(),
                timeout_ms,
                waiting_for: format!(
                    "a Grbl banner or status report on {} at {} baud: is a GRBL controller \
                     there, at that baud?",
                    self.opts.port, self.opts.baud
                ),
            },
            e => e,
        }
    }

    /// `$$`: the motor step, top speed and acceleration of X. A controller that refuses
    /// leaves them unknown (moves still work; their deadlines do not scale, and steps are
    /// not checked against the motor's).
    fn read_machine(&mut self) {
        let dl = self.reply_deadline();
        match self.command_collect("$$", dl) {
            Ok(settings) => {
                let get = |n| settings.iter().find(|(k, _)| *k == n).map(|(_, v)| *v);
                self.machine = match (get(100), get(110), get(120)) {
                    (Some(spm), Some(rate), Some(acc)) if spm > 0.0 && rate > 0.0 && acc > 0.0 => {
                        Some(StageMachine {
                            controller: "grbl".into(),
                            motor_step_um: 1000.0 / spm,
                            max_rate_um_s: rate * 1000.0 / 60.0,
                            accel_um_s2: acc * 1000.0,
                        })
                    }
                    _ => None,
                };
                tracing::info!(device = %self.name, machine = ?self.machine, "grbl settings read");
            }
            Err(e) => tracing::warn!(device = %self.name, "cannot read $$: {e}"),
        }
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

    /// Update what we know from a line that is not the reply awaited (a push message, the
    /// `ok` that ends a move in flight), or count line noise.
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
                self.in_flight = false;
                self.last = None;
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
            Line::Status(r) => {
                self.last = Some((Instant::now(), *r));
                match r.state {
                    GrblState::Alarm if self.lock.is_none() => {
                        self.lock = Some(Lock {
                            alarm: None,
                            needs_reset: false,
                        })
                    }
                    GrblState::Alarm => {}
                    _ => self.lock = None,
                }
            }
            Line::Banner(b) => {
                self.banners_seen += 1;
                self.target_um = None;
                self.in_flight = false;
                self.last = None;
                // A reset clears the reset requirement; an alarm lock may survive it.
                if let Some(l) = &mut self.lock {
                    l.needs_reset = false;
                }
                tracing::debug!(device = %self.name, banner = %b, "grbl banner");
            }
            Line::Ok if self.in_flight => {
                // The `G4 P0` behind the move: the planner is empty, the move is over.
                self.in_flight = false;
                self.synced = true;
                self.last = None;
            }
            Line::Error(code) if self.in_flight => {
                tracing::warn!(device = %self.name, code, "the sync after a move was refused");
                self.in_flight = false;
                self.last = None;
            }
            Line::Garbage(g) => {
                self.garbage_lines += 1;
                tracing::warn!(device = %self.name, line = %g, "ignoring line noise");
            }
            Line::Ok | Line::Error(_) | Line::Setting(..) => {
                tracing::warn!(device = %self.name, ?line, "stray reply ignored");
            }
            Line::Blank => {}
        }
    }

    /// Send one line and wait for its `ok` / `error:N` (after the move in flight ended: the
    /// next `ok` is its sync's).
    fn command(&mut self, line: &str, dl: Deadline) -> Result<(), HwError> {
        self.command_collect(line, dl).map(drop)
    }

    /// [`command`](Self::command), keeping the `$N=V` lines that come before the `ok`.
    fn command_collect(&mut self, line: &str, dl: Deadline) -> Result<Vec<(u32, f64)>, HwError> {
        let dl = if self.in_flight {
            self.finish_in_flight(Deadline::after(self.move_budget(dl.budget)))?;
            // The reply's own deadline starts once the move has ended.
            Deadline::after(dl.budget)
        } else {
            dl
        };
        self.synced = false;
        self.link.write_line(line)?;
        let waiting_for = format!("reply to {line:?}");
        let mut settings = Vec::new();
        loop {
            let raw = self.link.read_line(dl, &waiting_for)?;
            match classify(&raw) {
                Line::Ok => return Ok(settings),
                Line::Setting(n, v) => settings.push((n, v)),
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

    /// Ask for a `?` status report, within the poll budget (waiting for it if need be).
    fn query(&mut self, dl: Deadline) -> Result<GrblReport, HwError> {
        let wait = self.budget.wait(Instant::now());
        std::thread::sleep(wait);
        self.query_now(dl.later_by(wait))
    }

    /// Ask for a `?` status report now: a stop watching the axis brake does not wait.
    fn query_now(&mut self, mut dl: Deadline) -> Result<GrblReport, HwError> {
        loop {
            self.budget.spend(Instant::now());
            self.link.write(b"?")?;
            self.polls += 1;
            match self.await_report(dl)? {
                Some(r) => return Ok(r),
                // The reply came mangled (line noise; grbl-sim's output races now and
                // then): ask again, within the budget and the same deadline.
                None => {
                    let wait = self.budget.wait(Instant::now());
                    std::thread::sleep(wait);
                    dl = dl.later_by(wait);
                }
            }
        }
    }

    /// The reply to a `?`, the lines before it taken in (`None`: it came mangled).
    fn await_report(&mut self, dl: Deadline) -> Result<Option<GrblReport>, HwError> {
        loop {
            let raw = self.link.read_line(dl, "a status report")?;
            match classify(&raw) {
                Line::Status(r) => {
                    self.note(&Line::Status(r));
                    return Ok(Some(r));
                }
                Line::Garbage(g) if g.starts_with('<') => {
                    tracing::warn!(device = %self.name, line = %g, "a mangled status report");
                    self.garbage_lines += 1;
                    return Ok(None);
                }
                other => self.note(&other),
            }
        }
    }

    /// The latest report: the last one while it stands for the current state (with the
    /// lines that came since taken in), else a new one.
    fn current_report(&mut self) -> Result<GrblReport, HwError> {
        let stands = if self.in_flight {
            self.take_waiting_lines()?;
            FOLLOW
        } else {
            POLL
        };
        match self.last {
            Some((at, r)) if at.elapsed() < stands => Ok(r),
            _ => self.query(self.reply_deadline()),
        }
    }

    /// Take in the lines that have arrived, without waiting for more.
    fn take_waiting_lines(&mut self) -> Result<(), HwError> {
        loop {
            match self
                .link
                .read_line(Deadline::after(NO_WAIT), "lines waiting")
            {
                Ok(raw) => self.note(&classify(&raw)),
                Err(HwError::Timeout { .. }) => return Ok(()),
                Err(e) => return Err(e),
            }
        }
    }

    /// Wait for the `ok` that ends the move in flight, polling `?` every [`FOLLOW`] to follow
    /// it (an alarm ends the wait). A wait that runs out forgets the move.
    fn finish_in_flight(&mut self, dl: Deadline) -> Result<(), HwError> {
        while self.in_flight {
            let left = dl.at.saturating_duration_since(Instant::now());
            let next_poll = self.last.map_or(Duration::ZERO, |(at, _)| {
                FOLLOW.saturating_sub(at.elapsed())
            });
            let tick = Deadline::after(left.min(next_poll).max(NO_WAIT));
            match self
                .link
                .read_line(tick, "the end of the move (the ok to G4 P0)")
            {
                Ok(raw) => match classify(&raw) {
                    Line::Alarm(code) => {
                        self.note(&Line::Alarm(code));
                        return Err(self.alarm_error(Some(code)));
                    }
                    line => self.note(&line),
                },
                Err(HwError::Timeout { .. }) if dl.expired() => {
                    self.in_flight = false;
                    return Err(self.still_moving(dl));
                }
                Err(HwError::Timeout { .. }) => {
                    let r = self.query(self.reply_deadline())?;
                    if r.state == GrblState::Alarm {
                        self.in_flight = false;
                        return Err(self.alarm_error(self.lock.and_then(|l| l.alarm)));
                    }
                }
                Err(e) => {
                    self.in_flight = false;
                    return Err(e);
                }
            }
        }
        Ok(())
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
                    "the controller is {other} at {:.1} µm and its target is unknown: \
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
        if self.machine.is_none() {
            self.read_machine();
        }
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
        if self.in_flight {
            let budget = self.move_budget(Duration::from_millis(self.opts.reply_timeout_ms));
            self.finish_in_flight(Deadline::after(budget))?;
        }
        let dl = Deadline::after(Duration::from_millis(self.opts.home_timeout_ms));
        self.synced = false;
        self.link.write_line("$H")?;
        let waiting_for = "reply to \"$H\"";
        loop {
            if stopped() {
                tracing::warn!(device = %self.name, "homing stopped: soft reset");
                self.soft_reset()?;
                self.target_um = None;
                return Ok(true);
            }
            let left = dl.at.saturating_duration_since(Instant::now());
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

    /// Send the move, then `G4 P0` behind it without waiting: its `ok` marks the move's end.
    fn move_to(&mut self, from_um: f64, target_um: f64, gcode: String) -> Result<(), HwError> {
        self.ensure_unlocked()?;
        let dl = self.reply_deadline();
        self.command(&gcode, dl)?;
        self.target_um = Some(target_um);
        let distance_um = target_um - from_um;
        self.planned = Some(match &self.machine {
            Some(m) => m.move_time(distance_um, self.opts.feed_um_s),
            None => Duration::from_secs_f64(distance_um.abs() / self.opts.feed_um_s),
        });
        self.sync_now()?;
        // Until a report says otherwise, the axis is on its way.
        let here = self.last.map_or(from_um, |(_, r)| r.position_um);
        self.last = Some((
            Instant::now(),
            GrblReport {
                state: GrblState::Run,
                position_um: here,
            },
        ));
        Ok(())
    }

    /// Send `G4 P0` now: the next `ok` marks the end of whatever the planner holds.
    fn sync_now(&mut self) -> Result<(), HwError> {
        self.link.write_line("G4 P0")?;
        self.in_flight = true;
        self.last = None;
        Ok(())
    }

    /// How long a wait for the move in flight may take: `timeout`, or the move's planned
    /// time and a reply's deadline if that is longer.
    fn move_budget(&self, timeout: Duration) -> Duration {
        let planned = self.planned.unwrap_or(Duration::ZERO);
        timeout.max(planned * 2 + Duration::from_millis(self.opts.reply_timeout_ms))
    }

    /// How long a feed hold may take to complete: braking from the feed, twice over, and a
    /// reply's deadline.
    fn brake_budget(&self) -> Duration {
        let brake = match &self.machine {
            Some(m) => m.brake_time(self.opts.feed_um_s),
            None => Duration::from_secs(1),
        };
        brake * 3 + Duration::from_millis(self.opts.reply_timeout_ms)
    }
}

/// Stopping: a feed hold, braked out under control, then the planner cleared by a reset
/// that raises no alarm (GRBL keeps its position after a completed hold). A reset of a
/// moving controller is only the last resort: it raises `ALARM:3` (position lost).
impl GrblStage {
    fn stop_now(&mut self) -> Result<(), HwError> {
        let r = self.query_now(self.reply_deadline())?;
        let r = match r.state {
            // Nothing moves in alarm; a hold that already completed needs no feed hold.
            GrblState::Alarm => {
                self.in_flight = false;
                return Ok(());
            }
            GrblState::Idle | GrblState::Check | GrblState::Sleep => {
                // A move may have just ended, its `ok` on the way: take it in.
                let dl = self.reply_deadline();
                self.finish_in_flight(dl)?;
                self.target_um = Some(r.position_um);
                return Ok(());
            }
            GrblState::Hold { complete: true } => r,
            GrblState::Home => return self.last_resort(r, Duration::ZERO),
            GrblState::Jog => {
                self.link.write(&[0x85])?; // jog cancel: brakes and flushes, no alarm
                self.brake()?
            }
            GrblState::Run | GrblState::Hold { complete: false } | GrblState::Door => {
                self.link.write(b"!")?;
                self.brake()?
            }
        };
        match r.state {
            GrblState::Idle => {}
            GrblState::Hold { complete: true } | GrblState::Door => self.soft_reset()?,
            _ => return self.last_resort(r, self.brake_budget()),
        }
        let r = self.query(self.reply_deadline())?;
        if r.state == GrblState::Alarm {
            return Err(self.alarm_error(self.lock.and_then(|l| l.alarm)));
        }
        self.target_um = Some(r.position_um);
        Ok(())
    }

    /// Poll at [`STOP_POLL`] until the controller has braked to rest (a completed hold, or
    /// idle after a jog cancel), within [`brake_budget`](Self::brake_budget). Returns the
    /// last report either way.
    fn brake(&mut self) -> Result<GrblReport, HwError> {
        let dl = Deadline::after(self.brake_budget());
        loop {
            std::thread::sleep(STOP_POLL);
            let r = self.query_now(self.reply_deadline())?;
            let braking = matches!(
                r.state,
                GrblState::Run | GrblState::Jog | GrblState::Hold { complete: false }
            );
            if !braking || dl.expired() {
                self.in_flight = false;
                return Ok(r);
            }
        }
    }

    /// The controller did not come to rest under a feed hold (or is homing, which only a
    /// reset ends): reset it anyway, and say what it answered and that its position is lost.
    fn last_resort(&mut self, r: GrblReport, waited: Duration) -> Result<(), HwError> {
        tracing::warn!(device = %self.name, state = %r.state, at_um = r.position_um,
            "soft reset of a moving controller: the last resort of a stop");
        self.soft_reset()?;
        let after = self.query(self.reply_deadline())?;
        let code = self.lock.and_then(|l| l.alarm);
        let then = if after.state == GrblState::Alarm {
            format!(
                "it is in alarm{}: the position is lost until it is homed, or unlocked \
                 once the machine is checked",
                code.map_or(String::new(), |c| format!(" ({c})"))
            )
        } else {
            format!("it reports {} at {:.1} µm", after.state, after.position_um)
        };
        Err(HwError::Alarm {
            device: self.name.clone(),
            code: code.unwrap_or(0),
            message: format!(
                "the controller answered {} at {:.1} µm {} after a feed hold; rigd \
                 soft-reset it as the last resort of a stop, and {then}",
                r.state,
                r.position_um,
                if waited.is_zero() {
                    "(a homing cycle ends only by a reset)".to_string()
                } else {
                    format!("for {} ms", waited.as_millis())
                },
            ),
        })
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
        self.in_flight = false;
        self.last = None;
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
            s.move_to(from, target, g)
        })
    }

    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError> {
        self.guard(|s| {
            s.opts.limits.check_abs(&s.name, target_um)?;
            s.ensure_connected()?;
            let from = s.start_um()?;
            s.opts.limits.check_move(&s.name, from, target_um)?;
            let g = format!("G90 G1 X{:.5} F{:.1}", target_um / 1000.0, s.feed_mm_min());
            s.move_to(from, target_um, g)
        })
    }

    fn wait_settled(&mut self, timeout: Duration) -> Result<f64, HwError> {
        let dl = Deadline::after(timeout);
        self.guard(|s| {
            s.ensure_connected()?;
            if let Some(l) = s.lock {
                return Err(s.alarm_error(l.alarm));
            }
            if !s.in_flight && !s.synced {
                // A line since the last sync may have moved the axis (`send_line`).
                s.sync_now()?;
            }
            s.finish_in_flight(dl)?;
            // The planner is empty: a report confirms Idle (a fresh one, unless the last
            // came after the move's end).
            loop {
                let r = s.current_report()?;
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
        Ok(self.status()?.position_um)
    }

    fn stop(&mut self) -> Result<(), HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            s.stop_now()
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
                        "still {} at {:.1} µm after cycle start (a safety door open?)",
                        r.state, r.position_um
                    ),
                }),
                _ => Ok(()),
            }
        })
    }

    fn status(&mut self) -> Result<StageStatus, HwError> {
        let r = self.guard(|s| {
            s.ensure_connected()?;
            s.current_report()
        })?;
        Ok(StageStatus {
            state: state_of(r.state),
            position_um: r.position_um,
        })
    }

    fn machine(&self) -> Option<StageMachine> {
        self.machine.clone()
    }

    fn planned_move(&self) -> Option<Duration> {
        self.planned
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_are_checked() {
        let lim = TravelLimits::new(0.0, 1000.0, 100.0).unwrap();
        let mut o = GrblOptions::new("/dev/null", lim);
        o.feed_um_s = 0.0;
        let e = GrblStage::new("axis", o).unwrap_err();
        assert!(e.to_string().contains("feed_um_s"), "{e}");
        let mut o = GrblOptions::new("/dev/null", lim);
        o.status_poll_hz = f64::NAN;
        let e = GrblStage::new("axis", o).unwrap_err();
        assert!(e.to_string().contains("status_poll_hz"), "{e}");
        let toml = "port = \"/dev/ttyUSB0\"\non_alarm = \"unlock\"\n[limits]\nmin_um = 0\nmax_um = 1e5\nmax_step_um = 500\n";
        let o: GrblOptions = toml::from_str(toml).unwrap();
        assert_eq!(o.on_alarm, OnAlarm::Unlock);
        assert_eq!(o.baud, 115_200);
    }
}
