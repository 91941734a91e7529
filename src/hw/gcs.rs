//! Physik Instrumente GCS driver for a piezo flexure stage (E-709, E-727, … one axis), in µm.
//!
//! GCS rules it follows (PI's GCS manuals):
//! - Motion and setup commands (`SVO`, `MOV`, `MVR`, `STP`, `HLT`) send no reply; a failure
//!   only sets the controller's error code, so every motion command is followed by `ERR?`
//!   (which also clears it). Queries answer `axis=value` lines, LF-terminated.
//! - The servo (closed loop) must be on to move: `SVO <axis> 1` at connect.
//! - A move is finished when `ONT? <axis>` says 1: the closed loop has settled in its
//!   on-target window, which is later than the end of the motion profile.
//! - Stop is `HLT <axis>` (decelerate) which sets error 10 "stopped by command": expected.
//! - Every read has a deadline; a vanished port drops the connection and the next call
//!   reopens it (or `reconnect()`).
//!
//! - Limits are checked against the controller's own target (`MOV?`), never the sensor
//!   reading (`POS?`): `MVR` is relative to the last target, and a move that timed out may
//!   still be under way. Every move is sent as `MOV` to the target that was checked.
//!
//! `home()` moves to the configured `home_um` (within `move_timeout_ms`), or with
//! `home_reference` runs the reference move `FRF` (within `home_timeout_ms`, confirmed by
//! `FRF?`). `unlock()` reads and clears the error (`ERR?`) and switches the servo back on.

use super::limits::TravelLimits;
use super::serial::{Deadline, OverSerial, SerialLink};
use super::{HwError, MotionState, Stage, StageStatus};
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// `[piezo] driver = "gcs"` settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GcsOptions {
    pub port: String,
    #[serde(default = "defaults::baud")]
    pub baud: u32,
    /// GCS axis identifier.
    #[serde(default = "defaults::axis")]
    pub axis: String,
    /// µm per GCS position unit (PI piezo controllers are normally set up in µm: 1).
    #[serde(default = "defaults::um_per_unit")]
    pub um_per_unit: f64,
    #[serde(default = "defaults::reply_timeout_ms")]
    pub reply_timeout_ms: u64,
    /// Switch the servo on when connecting.
    #[serde(default = "defaults::yes")]
    pub servo_on_connect: bool,
    /// Where `home()` moves, µm.
    #[serde(default)]
    pub home_um: f64,
    /// `home()` runs the reference move `FRF` instead of moving to `home_um`.
    #[serde(default)]
    pub home_reference: bool,
    /// Deadline for `home()`'s move to `home_um` to settle on target.
    #[serde(default = "defaults::move_timeout_ms")]
    pub move_timeout_ms: u64,
    /// Deadline for the reference move `FRF`.
    #[serde(default = "defaults::home_timeout_ms")]
    pub home_timeout_ms: u64,
    pub limits: TravelLimits,
}

mod defaults {
    pub fn baud() -> u32 {
        115_200
    }
    pub fn axis() -> String {
        "1".into()
    }
    pub fn um_per_unit() -> f64 {
        1.0
    }
    pub fn reply_timeout_ms() -> u64 {
        500
    }
    pub fn yes() -> bool {
        true
    }
    pub fn move_timeout_ms() -> u64 {
        30_000
    }
    pub fn home_timeout_ms() -> u64 {
        60_000
    }
}

impl GcsOptions {
    pub fn new(port: impl Into<String>, limits: TravelLimits) -> GcsOptions {
        GcsOptions {
            port: port.into(),
            baud: defaults::baud(),
            axis: defaults::axis(),
            um_per_unit: defaults::um_per_unit(),
            reply_timeout_ms: defaults::reply_timeout_ms(),
            servo_on_connect: true,
            home_um: 0.0,
            home_reference: false,
            move_timeout_ms: defaults::move_timeout_ms(),
            home_timeout_ms: defaults::home_timeout_ms(),
            limits,
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        self.limits.validate()?;
        if !(self.um_per_unit.is_finite() && self.um_per_unit > 0.0) {
            return Err(format!(
                "um_per_unit must be positive, not {}",
                self.um_per_unit
            ));
        }
        if self.axis.is_empty() || self.axis.contains(char::is_whitespace) {
            return Err(format!("axis {:?} is not a GCS axis identifier", self.axis));
        }
        if self.port.is_empty() {
            return Err("port is empty".into());
        }
        Ok(())
    }
}

/// The meaning of the GCS error codes a piezo controller commonly returns.
pub fn gcs_error_text(code: i32) -> &'static str {
    match code {
        0 => "No error",
        1 => "Parameter syntax error",
        2 => "Unknown command",
        3 => "Command length out of limits or command buffer overrun",
        5 => "Unallowable move attempted on unreferenced axis, or move attempted with servo off",
        7 => "Position out of limits",
        8 => "Velocity out of limits",
        10 => "Controller was stopped by command",
        15 => "Invalid axis identifier",
        17 => "Parameter out of range",
        -1024 => "Motion error: position error too large, servo is switched off automatically",
        _ => "see the controller's GCS manual for this code",
    }
}

/// The value in an `<axis>=<value>` reply line, if it is for `axis`.
fn axis_field<'a>(line: &'a str, axis: &str) -> Option<&'a str> {
    let (id, v) = line.split_once('=')?;
    (id.trim() == axis).then_some(v.trim())
}

/// Error 10 after our own STP/HLT is the controller confirming the stop.
const STOPPED_BY_COMMAND: i32 = 10;
const DRAIN_QUIET: Duration = Duration::from_millis(20);
const POLL: Duration = Duration::from_millis(1);

/// A PI GCS piezo axis.
#[derive(Debug)]
pub struct GcsStage {
    name: String,
    opts: GcsOptions,
    link: SerialLink,
    idn: Option<String>,
    garbage_lines: u64,
}

impl GcsStage {
    /// A driver that connects on first use.
    pub fn new(name: impl Into<String>, opts: GcsOptions) -> Result<GcsStage, HwError> {
        let name = name.into();
        opts.validate().map_err(|message| HwError::Other {
            device: name.clone(),
            message: format!("bad gcs options: {message}"),
        })?;
        Ok(GcsStage {
            link: SerialLink::new(&name, &opts.port, opts.baud, DRAIN_QUIET),
            name,
            opts,
            idn: None,
            garbage_lines: 0,
        })
    }

    /// A driver connected now (identified, error cleared, servo on).
    pub fn connect(name: impl Into<String>, opts: GcsOptions) -> Result<GcsStage, HwError> {
        let mut s = GcsStage::new(name, opts)?;
        s.reconnect()?;
        Ok(s)
    }

    /// Close and reopen the port (after `PortGone`, or to switch the servo back on).
    pub fn reconnect(&mut self) -> Result<(), HwError> {
        self.reopen()
    }

    pub fn is_connected(&self) -> bool {
        self.link.is_open()
    }

    /// The controller's `*IDN?` answer, once connected.
    pub fn idn(&self) -> Option<&str> {
        self.idn.as_deref()
    }

    pub fn garbage_lines(&self) -> u64 {
        self.garbage_lines
    }

    /// Whether the closed loop reports on target.
    pub fn on_target(&mut self) -> Result<bool, HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            s.query_on_target()
        })
    }

    fn deadline(&self) -> Deadline {
        Deadline::after(Duration::from_millis(self.opts.reply_timeout_ms))
    }

    /// After (re)opening: identify, clear an old error, switch the servo on.
    fn setup(&mut self) -> Result<(), HwError> {
        // Whatever an earlier session left in the buffers is not ours.
        self.link.mark_stale();
        let idn = self.query_line("*IDN?", |l| (!l.is_empty()).then(|| l.to_string()))?;
        tracing::info!(device = %self.name, idn = %idn, "gcs controller connected");
        self.idn = Some(idn);
        let old = self.query_error()?;
        if old != 0 {
            tracing::info!(device = %self.name, code = old, "cleared an old controller error");
        }
        if self.opts.servo_on_connect {
            let cmd = format!("SVO {} 1", self.opts.axis);
            self.send(&cmd)?;
            self.check_error(&cmd, false)?;
        }
        Ok(())
    }

    /// Send a command that has no reply.
    fn send(&mut self, cmd: &str) -> Result<(), HwError> {
        self.link.write_line(cmd)
    }

    /// Send bytes, then read lines until `parse` accepts one (others are line noise).
    fn ask<T>(
        &mut self,
        bytes: &[u8],
        what: &str,
        parse: impl Fn(&str) -> Option<T>,
    ) -> Result<T, HwError> {
        self.link.write(bytes)?;
        let dl = self.deadline();
        loop {
            let raw = self.link.read_line(dl, &format!("reply to {what}"))?;
            let text = std::str::from_utf8(&raw).map(str::trim);
            match text.ok().and_then(&parse) {
                Some(v) => return Ok(v),
                None => {
                    self.garbage_lines += 1;
                    tracing::warn!(device = %self.name, line = %String::from_utf8_lossy(&raw),
                        waiting_for = what, "ignoring unexpected line");
                }
            }
        }
    }

    fn query_line<T>(
        &mut self,
        cmd: &str,
        parse: impl Fn(&str) -> Option<T>,
    ) -> Result<T, HwError> {
        let mut b = cmd.as_bytes().to_vec();
        b.push(b'\n');
        self.ask(&b, cmd, parse)
    }

    fn query_error(&mut self) -> Result<i32, HwError> {
        self.query_line("ERR?", |l| l.parse::<i32>().ok())
    }

    /// `ERR?` after a command; a nonzero code becomes a typed error.
    fn check_error(&mut self, after: &str, stop_expected: bool) -> Result<(), HwError> {
        match self.query_error()? {
            0 => Ok(()),
            STOPPED_BY_COMMAND if stop_expected => Ok(()),
            code => Err(HwError::Controller {
                device: self.name.clone(),
                code,
                message: format!("{} (after {after:?})", gcs_error_text(code)),
            }),
        }
    }

    fn query_on_target(&mut self) -> Result<bool, HwError> {
        let cmd = format!("ONT? {}", self.opts.axis);
        let axis = self.opts.axis.clone();
        self.query_line(&cmd, |l| match axis_field(l, &axis)? {
            "1" => Some(true),
            "0" => Some(false),
            _ => None,
        })
    }

    fn query_position(&mut self) -> Result<f64, HwError> {
        let cmd = format!("POS? {}", self.opts.axis);
        let axis = self.opts.axis.clone();
        let units = self.query_line(&cmd, |l| {
            let v: f64 = axis_field(l, &axis)?.parse().ok()?;
            v.is_finite().then_some(v)
        })?;
        Ok(units * self.opts.um_per_unit)
    }

    /// The controller's own target (`MOV?`): where the last move was commanded to end.
    fn query_target(&mut self) -> Result<f64, HwError> {
        let cmd = format!("MOV? {}", self.opts.axis);
        let axis = self.opts.axis.clone();
        let units = self.query_line(&cmd, |l| {
            let v: f64 = axis_field(l, &axis)?.parse().ok()?;
            v.is_finite().then_some(v)
        })?;
        Ok(units * self.opts.um_per_unit)
    }

    /// `MOV` to a target already checked.
    fn move_to(&mut self, target_um: f64) -> Result<(), HwError> {
        let cmd = format!(
            "MOV {} {:.6}",
            self.opts.axis,
            target_um / self.opts.um_per_unit
        );
        self.send(&cmd)?;
        self.check_error(&cmd, false)
    }

    /// Wait for on-target within `timeout`, then confirm with `FRF?` when referencing.
    fn wait_home(&mut self, timeout: Duration, referencing: bool) -> Result<(), HwError> {
        self.wait_settled(timeout)?;
        if !referencing {
            return Ok(());
        }
        let cmd = format!("FRF? {}", self.opts.axis);
        let axis = self.opts.axis.clone();
        let done =
            self.guard(|s| s.query_line(&cmd, |l| axis_field(l, &axis).map(|v| v == "1")))?;
        if !done {
            return Err(HwError::Other {
                device: self.name.clone(),
                message: "the reference move ended but FRF? says the axis is not referenced".into(),
            });
        }
        Ok(())
    }

    fn query_servo(&mut self) -> Result<bool, HwError> {
        let svo = format!("SVO? {}", self.opts.axis);
        let axis = self.opts.axis.clone();
        self.query_line(&svo, |l| axis_field(l, &axis).map(|v| v == "1"))
    }
}

impl OverSerial for GcsStage {
    fn link(&mut self) -> &mut SerialLink {
        &mut self.link
    }

    fn handshake(&mut self) -> Result<(), HwError> {
        self.setup()
    }

    fn port_lost(&mut self) {}
}

impl Stage for GcsStage {
    fn name(&self) -> &str {
        &self.name
    }

    fn move_rel(&mut self, delta_um: f64) -> Result<(), HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            let from = s.query_target()?;
            let target = s.opts.limits.check_rel(&s.name, from, delta_um)?;
            s.move_to(target)
        })
    }

    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError> {
        self.guard(|s| {
            s.opts.limits.check_abs(&s.name, target_um)?;
            s.ensure_connected()?;
            let from = s.query_target()?;
            s.opts.limits.check_move(&s.name, from, target_um)?;
            s.move_to(target_um)
        })
    }

    fn wait_settled(&mut self, timeout: Duration) -> Result<f64, HwError> {
        let dl = Deadline::after(timeout);
        self.guard(|s| {
            s.ensure_connected()?;
            let mut polls = 0u32;
            loop {
                if s.query_on_target()? {
                    return s.query_position();
                }
                polls += 1;
                // A servo fault never reaches the target: look for it now and then.
                if polls == 8 {
                    polls = 0;
                    s.check_error("waiting for on-target", false)?;
                }
                if dl.expired() {
                    s.check_error("waiting for on-target", false)?;
                    let at = s.query_position()?;
                    return Err(HwError::NotSettled {
                        device: s.name.clone(),
                        timeout_ms: dl.budget.as_millis() as u64,
                        state: format!("ONT? still 0, POS? {at:.4} µm"),
                    });
                }
                std::thread::sleep(POLL);
            }
        })
    }

    fn position_um(&mut self) -> Result<f64, HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            s.query_position()
        })
    }

    fn stop(&mut self) -> Result<(), HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            let cmd = format!("HLT {}", s.opts.axis);
            s.send(&cmd)?;
            s.check_error(&cmd, true)
        })
    }

    /// The configured home: a move to `home_um` (soft limits checked; a configured
    /// position, so not held to `max_step_um`), or the reference move `FRF`.
    fn home(&mut self) -> Result<(), HwError> {
        let referencing = self.opts.home_reference;
        self.guard(|s| {
            s.ensure_connected()?;
            if referencing {
                let cmd = format!("FRF {}", s.opts.axis);
                s.send(&cmd)?;
                s.check_error(&cmd, false)
            } else {
                s.opts.limits.check_abs(&s.name, s.opts.home_um)?;
                s.move_to(s.opts.home_um)
            }
        })?;
        let ms = match referencing {
            true => self.opts.home_timeout_ms,
            false => self.opts.move_timeout_ms,
        };
        self.wait_home(Duration::from_millis(ms), referencing)
    }

    /// Read and clear the error (`ERR?`), switch the servo on again if it opened, and
    /// confirm: `SVO?` 1 and no new error.
    fn unlock(&mut self) -> Result<(), HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            let code = s.query_error()?;
            if code != 0 {
                tracing::info!(device = %s.name, code, text = gcs_error_text(code),
                    "unlock: read and cleared the controller error");
            }
            if s.opts.servo_on_connect && !s.query_servo()? {
                let cmd = format!("SVO {} 1", s.opts.axis);
                s.send(&cmd)?;
                s.check_error(&cmd, false)?;
                if !s.query_servo()? {
                    return Err(HwError::Other {
                        device: s.name.clone(),
                        message: "SVO 1 sent but SVO? still says the servo is off".into(),
                    });
                }
            }
            s.check_error("unlock", false)
        })
    }

    fn reconnect(&mut self) -> Result<(), HwError> {
        self.reopen()
    }

    fn status(&mut self) -> Result<StageStatus, HwError> {
        self.guard(|s| {
            s.ensure_connected()?;
            // #5: motion status, a hex bit mask, bit 0 = first axis moving.
            let mask = s.ask(&[0x05], "#5", |l| u32::from_str_radix(l, 16).ok())?;
            let servo = s.query_servo()?;
            let position_um = s.query_position()?;
            let state = if mask & 1 != 0 {
                MotionState::Moving
            } else if !servo && s.opts.servo_on_connect {
                // The loop opened by itself (motion error): not usable until servo on again.
                MotionState::Alarm
            } else {
                MotionState::Idle
            };
            Ok(StageStatus { state, position_um })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_parse_from_toml_with_defaults() {
        let o: GcsOptions = toml::from_str(
            "port = \"/dev/ttyUSB1\"\n[limits]\nmin_um = 0\nmax_um = 100\nmax_step_um = 20\n",
        )
        .unwrap();
        assert_eq!(o.axis, "1");
        assert_eq!(o.um_per_unit, 1.0);
        assert!(o.servo_on_connect);
        let mut bad = o.clone();
        bad.axis = "1 2".into();
        assert!(GcsStage::new("piezo", bad).is_err());
    }

    #[test]
    fn error_texts_name_the_usual_codes() {
        assert!(gcs_error_text(7).contains("out of limits"));
        assert!(gcs_error_text(5).contains("servo off"));
        assert!(gcs_error_text(-1024).contains("servo is switched off"));
    }
}
