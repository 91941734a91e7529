//! A Physik Instrumente GCS piezo controller (E-709 / E-727 style, one axis) on a pty.
//!
//! GCS as PI controllers speak it: LF-terminated ASCII commands; queries (`...?`) answer
//! `axis=value` lines, motion and setup commands answer nothing, and a failed command only
//! sets the error code that `ERR?` returns (and clears). Single-byte commands `#5` (0x05,
//! motion status as a hex bit mask) and `#24` (0x18, stop all axes) act at once. The axis
//! is on target only after the closed loop has settled (`settle` after the move ends).
//!
//! This parser is the emulator's own: rigd's driver (src/hw/gcs.rs) shares none of it.

use crate::motion::Axis;
use crate::serve::{serve, Controller, Faults, Outbox, Served};
use std::io;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Debug, Clone, PartialEq)]
pub struct GcsSimOptions {
    /// The axis identifier (`1` on E-709/E-727).
    pub axis_id: String,
    /// µm per GCS position unit (PI piezos are configured in µm: 1.0).
    pub um_per_unit: f64,
    /// Closed-loop settling after the motion profile ends, before `ONT?` says 1.
    pub settle: Duration,
    /// Servo state at power-on.
    pub servo_on_at_boot: bool,
    /// Where the reference move `FRF` ends, µm (the sensor's reference point).
    pub reference_um: f64,
    pub idn: String,
}

impl Default for GcsSimOptions {
    fn default() -> Self {
        GcsSimOptions {
            axis_id: "1".into(),
            um_per_unit: 1.0,
            settle: Duration::from_millis(10),
            servo_on_at_boot: false,
            reference_um: 0.0,
            idn: "(c)2026 Physik Instrumente (PI) GmbH & Co. KG, E-709, 0, 01.00.00 (simulated)"
                .into(),
        }
    }
}

/// PI's error codes the emulator raises.
pub mod code {
    pub const NO_ERROR: i32 = 0;
    pub const PARAM_SYNTAX: i32 = 1;
    pub const UNKNOWN_COMMAND: i32 = 2;
    pub const MOVE_SERVO_OFF: i32 = 5;
    pub const POS_OUT_OF_LIMITS: i32 = 7;
    pub const STOPPED: i32 = 10;
    pub const INVALID_AXIS: i32 = 15;
    pub const MOTION_ERROR: i32 = -1024;
}

/// A running GCS emulator.
pub struct GcsSim {
    served: Served,
}

impl GcsSim {
    pub fn spawn(axis: Arc<Axis>, opts: GcsSimOptions, link: Option<&Path>) -> io::Result<GcsSim> {
        let faults = Faults::default();
        let ctrl = Gcs::new(axis, opts, faults.clone());
        let served = serve(ctrl, faults, link, "sim-gcs")?;
        Ok(GcsSim { served })
    }
    pub fn path(&self) -> std::path::PathBuf {
        self.served.path()
    }
    pub fn faults(&self) -> &Faults {
        self.served.faults()
    }
    /// Bytes the emulator has received from clients (see [`Served::bytes_received`]).
    pub fn bytes_received(&self) -> u64 {
        self.served.bytes_received()
    }
}

struct Gcs {
    axis: Arc<Axis>,
    opts: GcsSimOptions,
    faults: Faults,
    line: Vec<u8>,
    servo: bool,
    error: i32,
    target_um: f64,
    /// When the closed loop is settled on the target.
    on_target_at: Instant,
    /// An injected motion error due at this instant.
    fault_at: Option<Instant>,
    /// A reference move (`FRF`) was started; `FRF?` says 1 once it is on target.
    referencing: bool,
}

impl Gcs {
    fn new(axis: Arc<Axis>, opts: GcsSimOptions, faults: Faults) -> Gcs {
        let now = Instant::now();
        let target_um = axis.reported_um(now);
        let servo = opts.servo_on_at_boot;
        Gcs {
            axis,
            opts,
            faults,
            line: Vec::new(),
            servo,
            error: code::NO_ERROR,
            target_um,
            on_target_at: now,
            fault_at: None,
            referencing: false,
        }
    }

    fn set_error(&mut self, code: i32) {
        // PI keeps the first error until ERR? reads it.
        if self.error == code::NO_ERROR {
            self.error = code;
        }
    }

    fn units(&self, um: f64) -> f64 {
        um / self.opts.um_per_unit
    }

    fn halt(&mut self, now: Instant) {
        if self.axis.is_moving(now) {
            self.axis.stop();
        }
        self.target_um = self.axis.reported_um(now);
        self.on_target_at = now + self.opts.settle;
        self.fault_at = None;
        self.set_error(code::STOPPED);
    }

    /// Start a move; false if the controller refused it (the error is set).
    fn move_to(&mut self, target_um: f64, now: Instant) -> bool {
        if !self.servo {
            self.set_error(code::MOVE_SERVO_OFF);
            return false;
        }
        match self.axis.command_move(target_um) {
            Ok(dur) => {
                self.target_um = target_um;
                // The axis' clock starts inside `command_move`, after `now` (see grbl.rs).
                let ends = self.axis.move_ends_at().max(now + dur);
                self.on_target_at = ends + self.opts.settle;
                if self.faults.take_alarm_mid_move() {
                    self.fault_at = Some(now + dur / 2);
                }
                true
            }
            Err(_) => {
                self.set_error(code::POS_OUT_OF_LIMITS);
                false
            }
        }
    }

    /// Parse `<axis> <value>` pairs for one axis; GCS error 1 or 15 on failure.
    fn axis_value(&self, args: &[&str]) -> Result<f64, i32> {
        match args {
            [id, v] => {
                if *id != self.opts.axis_id {
                    return Err(code::INVALID_AXIS);
                }
                let v: f64 = v.parse().map_err(|_| code::PARAM_SYNTAX)?;
                if !v.is_finite() {
                    return Err(code::PARAM_SYNTAX);
                }
                Ok(v)
            }
            _ => Err(code::PARAM_SYNTAX),
        }
    }

    /// Queries name one axis (or none, meaning all: here, the one).
    fn query_axis(&self, args: &[&str]) -> Result<(), i32> {
        match args {
            [] => Ok(()),
            [id] if *id == self.opts.axis_id => Ok(()),
            [_] => Err(code::INVALID_AXIS),
            _ => Err(code::PARAM_SYNTAX),
        }
    }

    fn on_target(&self, now: Instant) -> bool {
        self.servo && now >= self.on_target_at
    }

    fn command(&mut self, line: &str, now: Instant, out: &mut Outbox) {
        let mut parts = line.split_whitespace();
        let Some(cmd) = parts.next() else { return };
        let args: Vec<&str> = parts.collect();
        let id = self.opts.axis_id.clone();
        let result: Result<Option<String>, i32> = match cmd.to_ascii_uppercase().as_str() {
            "*IDN?" => Ok(Some(self.opts.idn.clone())),
            "ERR?" => Ok(Some(std::mem::take(&mut self.error).to_string())),
            "SVO" => self.axis_value(&args).and_then(|v| {
                if v == 0.0 || v == 1.0 {
                    // Only a change of state moves the target (to where the axis is): `SVO 1`
                    // with the loop already closed leaves a move in progress alone.
                    if self.servo != (v == 1.0) {
                        self.servo = v == 1.0;
                        if !self.servo {
                            self.axis.stop();
                        }
                        self.target_um = self.axis.reported_um(now);
                    }
                    Ok(None)
                } else {
                    Err(code::PARAM_SYNTAX)
                }
            }),
            "SVO?" => self
                .query_axis(&args)
                .map(|_| Some(format!("{id}={}", u8::from(self.servo)))),
            "MOV" => self.axis_value(&args).map(|v| {
                self.move_to(v * self.opts.um_per_unit, now);
                None
            }),
            "MVR" => self.axis_value(&args).map(|d| {
                let target = self.target_um + d * self.opts.um_per_unit;
                self.move_to(target, now);
                None
            }),
            "POS?" => self.query_axis(&args).map(|_| {
                // The sensor sees the real position, positioning error included.
                let p = self.units(self.axis.position_at(now));
                Some(format!("{id}={p:.6}"))
            }),
            "MOV?" => self
                .query_axis(&args)
                .map(|_| Some(format!("{id}={:.6}", self.units(self.target_um)))),
            "ONT?" => self
                .query_axis(&args)
                .map(|_| Some(format!("{id}={}", u8::from(self.on_target(now))))),
            "TMN?" => self.query_axis(&args).map(|_| {
                let v = self.units(self.axis.params().hard_min_um);
                Some(format!("{id}={v:.6}"))
            }),
            "TMX?" => self.query_axis(&args).map(|_| {
                let v = self.units(self.axis.params().hard_max_um);
                Some(format!("{id}={v:.6}"))
            }),
            // Reference move: to the reference point; FRF? is 1 once it has settled there.
            "FRF" => self.query_axis(&args).map(|_| {
                self.referencing = self.move_to(self.opts.reference_um, now);
                None
            }),
            "FRF?" => self.query_axis(&args).map(|_| {
                let done = self.referencing && self.on_target(now);
                Some(format!("{id}={}", u8::from(done)))
            }),
            "STP" => {
                self.halt(now);
                Ok(None)
            }
            "HLT" => match args.as_slice() {
                [] => {
                    self.halt(now);
                    Ok(None)
                }
                [a] if *a == id => {
                    self.halt(now);
                    Ok(None)
                }
                _ => Err(code::INVALID_AXIS),
            },
            _ => Err(code::UNKNOWN_COMMAND),
        };
        match result {
            Ok(Some(reply)) => out.reply(format!("{reply}\n")),
            Ok(None) => {}
            Err(c) => self.set_error(c),
        }
    }
}

impl Controller for Gcs {
    fn on_open(&mut self, _now: Instant, _out: &mut Outbox) {
        // A PI controller does not reset on open and sends nothing.
        self.line.clear();
    }

    fn on_bytes(&mut self, bytes: &[u8], now: Instant, out: &mut Outbox) {
        for &b in bytes {
            match b {
                // #5: motion status, bit 0 = axis 1 moving.
                0x05 => {
                    let moving = self.axis.is_moving(now) || !self.on_target(now) && self.servo;
                    out.reply(format!("{:X}\n", u8::from(moving)));
                }
                // #24: stop all axes.
                0x18 => self.halt(now),
                b'\n' => {
                    let line = std::mem::take(&mut self.line);
                    let text = String::from_utf8_lossy(&line).trim().to_string();
                    self.command(&text, now, out);
                }
                b'\r' => {}
                _ => {
                    if self.line.len() < 256 {
                        self.line.push(b);
                    }
                }
            }
        }
    }

    fn tick(&mut self, now: Instant, _out: &mut Outbox) -> Option<Instant> {
        if let Some(t) = self.fault_at {
            if now >= t {
                // The position error grew too large: the controller switches the servo off.
                self.axis.stop();
                self.servo = false;
                self.fault_at = None;
                self.target_um = self.axis.reported_um(now);
                self.error = code::MOTION_ERROR;
            } else {
                return Some(t);
            }
        }
        if self.axis.is_moving(now) && self.faults.take_alarm_mid_move() {
            let ends = self.axis.move_ends_at();
            let t = now + (ends - now) / 2;
            self.fault_at = Some(t);
            return Some(t);
        }
        None
    }

    fn line_end(&self) -> &'static [u8] {
        b"\n"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::AxisParams;
    use crate::pty::TestClient;

    const T: Duration = Duration::from_secs(2);

    #[test]
    fn motion_commands_are_silent_and_errors_wait_for_err_query() {
        let axis = Arc::new(Axis::new(AxisParams {
            max_speed_um_s: 500.0,
            hard_min_um: 0.0,
            hard_max_um: 100.0,
            position_error_rms_um: 0.0,
            ..AxisParams::default()
        }));
        let sim = GcsSim::spawn(axis.clone(), GcsSimOptions::default(), None).unwrap();
        let mut c = TestClient::open(&sim.path());
        c.send(b"MOV 1 10\nERR?\n");
        assert_eq!(c.line(T).unwrap(), "5"); // servo off
        c.send(b"SVO 1 1\nMOV 1 150\nERR?\n");
        assert_eq!(c.line(T).unwrap(), "7"); // out of limits
        c.send(b"ERR?\n");
        assert_eq!(c.line(T).unwrap(), "0"); // read clears it
        c.send(b"MOV 1 50\n\x05");
        assert_eq!(c.line(T).unwrap(), "1"); // #5: moving
        c.send(b"ONT? 1\n");
        assert_eq!(c.line(T).unwrap(), "1=0");
        c.send(&[0x18]); // #24: stop
        c.send(b"ERR?\n");
        assert_eq!(c.line(T).unwrap(), "10");
        assert!(!axis.is_moving(Instant::now()));
        c.send(b"POS? 2\nERR?\n");
        assert_eq!(c.line(T).unwrap(), "15"); // no such axis: no reply, error 15
    }
}
