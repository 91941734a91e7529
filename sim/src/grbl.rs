//! A GRBL 1.1 controller on a pseudo-terminal, driving a simulated [`Axis`] (its X axis).
//!
//! What it does, as GRBL does: the banner on open (a DTR reset) and after a soft reset;
//! one `ok` / `error:N` per line; realtime `?` `!` `~` and 0x18 picked out of the stream;
//! motion queued in a planner so `ok` comes back before the move is done, while `G4 P0`
//! answers only once the planner is empty; `$H` homing, `$X` unlock, `$J=` jogging; a move
//! past the axis' hard limits runs into the limit switch and raises `ALARM:1`, after which
//! only a soft reset is accepted. Units are mm in G-code; the axis is in µm.
//!
//! Feed: G1 moves at the modal feed rate F (mm/min, kept until changed or reset; a G1 with
//! none set is `error:22`), G0 at the max rate (`$110`, the axis' top speed), a jog at its
//! own F; every rate is clamped to the max rate, and the axis' acceleration (`$120`)
//! shapes every move.
//!
//! This parser is the emulator's own: rigd's driver (src/hw/grbl.rs) shares none of it.

use crate::motion::Axis;
use crate::serve::{serve, Controller, Faults, Outbox, Served};
use std::collections::VecDeque;
use std::io;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

pub const BANNER: &str = "Grbl 1.1h ['$' for help]";

#[derive(Debug, Clone, PartialEq)]
pub struct GrblSimOptions {
    /// Time from the port opening to the banner (a real Arduino bootloader: ~1.5 s).
    pub boot_delay: Duration,
    /// `$22=1`: homing cycle enabled.
    pub homing_enabled: bool,
    /// Boot (and soft reset) into Alarm until `$H` or `$X`, as GRBL does with homing enabled.
    pub alarm_on_boot: bool,
    /// Machine position the homing cycle assigns at the switch (µm).
    pub home_position_um: f64,
    /// Opening the port resets the board (DTR wired to reset, as on an Arduino). When
    /// false, opening is silent: no reset, no banner.
    pub reset_on_open: bool,
    /// `$100`: motor steps per mm. Targets are whole steps, rounded as the firmware rounds
    /// them (its parser and planner work in 32-bit floats). Default 1000: a 200-step motor
    /// at 16 microsteps on a 3.2 mm leadscrew, so every whole-µm step is whole motor steps
    /// (GRBL's own default, 250, makes a 4 µm step).
    pub steps_per_mm: f64,
}

impl Default for GrblSimOptions {
    fn default() -> Self {
        GrblSimOptions {
            boot_delay: Duration::from_millis(20),
            homing_enabled: true,
            alarm_on_boot: false,
            home_position_um: 0.0,
            reset_on_open: true,
            steps_per_mm: 1000.0,
        }
    }
}

/// A running GRBL emulator.
pub struct GrblSim {
    served: Served,
}

impl GrblSim {
    /// Serve a GRBL controller for `axis` on a new pty; `link`, if given, is a stable symlink
    /// to it that survives the port vanishing and coming back.
    pub fn spawn(
        axis: Arc<Axis>,
        opts: GrblSimOptions,
        link: Option<&Path>,
    ) -> io::Result<GrblSim> {
        let faults = Faults::default();
        let ctrl = Grbl::new(axis, opts, faults.clone());
        let served = serve(ctrl, faults, link, "sim-grbl")?;
        Ok(GrblSim { served })
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

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    Idle,
    Run,
    Jog,
    /// A feed hold: braking (`Hold:1`) until `complete` (`Hold:0`).
    Hold {
        complete: bool,
    },
    Home,
    Alarm,
}

impl State {
    fn report_name(self) -> &'static str {
        match self {
            State::Idle => "Idle",
            State::Run => "Run",
            State::Jog => "Jog",
            State::Hold { complete: true } => "Hold:0",
            State::Hold { complete: false } => "Hold:1",
            State::Home => "Home",
            State::Alarm => "Alarm",
        }
    }

    fn held(self) -> bool {
        matches!(self, State::Hold { .. })
    }
}

#[derive(Debug, Clone, Copy)]
struct Planned {
    target_um: f64,
    feed_mm_min: f64,
    jog: bool,
}

#[derive(Debug, Clone, Copy)]
enum Block {
    /// `G4 P<s>`: waits for the planner to empty, then dwells.
    Dwell { secs: f64, since: Option<Instant> },
    /// `$H`: the homing cycle runs until `ends`.
    Homing { ends: Instant },
}

struct Grbl {
    axis: Arc<Axis>,
    opts: GrblSimOptions,
    faults: Faults,
    /// Banner due at this instant (board booting): input is ignored until then.
    booting_until: Option<Instant>,
    line: Vec<u8>,
    pending: VecDeque<Vec<u8>>,
    state: State,
    /// After a hard limit: nothing but a soft reset is accepted.
    critical: bool,
    absolute: bool,
    feed_mm_min: Option<f64>,
    rapid: bool,
    /// Where the last planned move ends (the parser's position), mm, in the firmware's
    /// 32-bit float.
    plan_end_mm: f32,
    /// A feed hold (or jog cancel) brakes until then.
    braking_until: Option<Instant>,
    queue: VecDeque<Planned>,
    current: Option<(Planned, Instant)>,
    block: Option<Block>,
    /// An alarm due at an instant (a move into the limit switch, or an injected fault).
    alarm_at: Option<(Instant, u32)>,
}

impl Grbl {
    fn new(axis: Arc<Axis>, opts: GrblSimOptions, faults: Faults) -> Grbl {
        let here = axis.reported_um(Instant::now());
        Grbl {
            axis,
            opts,
            faults,
            booting_until: None,
            line: Vec::new(),
            pending: VecDeque::new(),
            state: State::Idle,
            critical: false,
            absolute: true,
            feed_mm_min: None,
            rapid: true,
            plan_end_mm: (here / 1000.0) as f32,
            braking_until: None,
            queue: VecDeque::new(),
            current: None,
            block: None,
            alarm_at: None,
        }
    }

    fn moving(&self) -> bool {
        self.current.is_some()
            || matches!(self.state, State::Run | State::Jog | State::Home)
            || self.axis.is_moving(Instant::now())
    }

    /// Everything a reset (power-on or 0x18) clears.
    fn reset(&mut self, now: Instant) {
        self.axis.stop();
        self.line.clear();
        self.pending.clear();
        self.queue.clear();
        self.current = None;
        self.block = None;
        self.alarm_at = None;
        self.absolute = true;
        self.rapid = true;
        self.feed_mm_min = None;
        self.braking_until = None;
        self.plan_end_mm = (self.axis.reported_um(now) / 1000.0) as f32;
    }

    fn banner(&mut self, out: &mut Outbox) {
        out.push(format!("\r\n{BANNER}\r\n"));
        if self.state == State::Alarm {
            out.push("[MSG:'$H'|'$X' to unlock]\r\n");
        }
    }

    fn soft_reset(&mut self, now: Instant, out: &mut Outbox) {
        // As GRBL's mc_reset: in motion, homing, or braking into a hold, the steps are lost.
        let was_moving = matches!(
            self.state,
            State::Run | State::Jog | State::Home | State::Hold { complete: false }
        ) || (self.state == State::Idle && self.moving());
        self.reset(now);
        if was_moving {
            out.push("ALARM:3\r\n");
            self.state = State::Alarm;
        } else if self.critical || self.state == State::Alarm {
            // An alarm survives the reset: '$H' or '$X' clears it.
            self.state = State::Alarm;
        } else {
            self.state = State::Idle;
        }
        self.critical = false;
        self.banner(out);
    }

    fn status(&self, now: Instant) -> String {
        // The controller counts whole steps.
        let spm = self.opts.steps_per_mm;
        let x_mm = (self.axis.reported_um(now) / 1000.0 * spm).round() / spm;
        let feed = match (&self.current, self.state) {
            (Some((p, _)), State::Run | State::Jog) => p.feed_mm_min,
            _ => 0.0,
        };
        format!(
            "<{}|MPos:{x_mm:.3},0.000,0.000|FS:{feed:.0},0>\r\n",
            self.state.report_name()
        )
    }

    fn raise_alarm(&mut self, code: u32, now: Instant, out: &mut Outbox) {
        self.axis.stop();
        self.queue.clear();
        self.current = None;
        self.block = None;
        self.pending.clear();
        self.alarm_at = None;
        self.braking_until = None;
        self.plan_end_mm = (self.axis.reported_um(now) / 1000.0) as f32;
        self.state = State::Alarm;
        self.critical = true;
        out.push(format!("ALARM:{code}\r\n"));
        out.push("[MSG:Reset to continue]\r\n");
    }

    /// `!` (or jog cancel 0x85 while jogging): brake at the axis' acceleration. A move's rest
    /// waits for `~` in `Hold`; a jog is cancelled, its queue flushed, back to `Idle` once at
    /// rest. Idle, GRBL still enters a (complete) hold.
    fn feed_hold(&mut self, now: Instant) {
        match self.state {
            State::Run | State::Jog => {
                let jog = self.state == State::Jog;
                let brake = self.axis.brake();
                match self.current.take() {
                    Some((p, _)) if !jog => self.queue.push_front(p),
                    _ => {}
                }
                if jog {
                    self.queue.clear();
                    self.plan_end_mm = (self.axis.commanded_um() / 1000.0) as f32;
                } else {
                    self.state = State::Hold { complete: false };
                }
                self.alarm_at = None;
                self.braking_until = Some(now + brake);
            }
            State::Idle => self.state = State::Hold { complete: true },
            _ => {}
        }
    }

    /// `$$`: GRBL 1.1h's settings at their defaults, with X's from this emulator's axis.
    fn settings(&self) -> String {
        let p = self.axis.params();
        let x = [
            self.opts.steps_per_mm,
            p.max_speed_um_s * 60.0 / 1000.0,
            p.accel_um_s2 / 1000.0,
            (p.hard_max_um - p.hard_min_um) / 1000.0,
        ];
        let homing = u8::from(self.opts.homing_enabled);
        let mut s = format!(
            "$0=10\r\n$1=25\r\n$2=0\r\n$3=0\r\n$4=0\r\n$5=0\r\n$6=0\r\n$10=1\r\n\
             $11=0.010\r\n$12=0.002\r\n$13=0\r\n$20=0\r\n$21=0\r\n$22={homing}\r\n$23=0\r\n\
             $24=25.000\r\n$25=500.000\r\n$26=250\r\n$27=1.000\r\n$30=1000\r\n$31=0\r\n\
             $32=0\r\n"
        );
        // $100.. steps/mm, $110.. max rate, $120.. acceleration, $130.. travel: X from the
        // axis, Y and Z at GRBL's defaults.
        let yz = [250.0, 500.0, 10.0, 200.0];
        for (i, (xv, d)) in x.iter().zip(yz).enumerate() {
            let n = 100 + 10 * i;
            s += &format!("${n}={xv:.3}\r\n${}={d:.3}\r\n${}={d:.3}\r\n", n + 1, n + 2);
        }
        s
    }

    /// Start the next planned move if the axis is free.
    fn start_next(&mut self, now: Instant) {
        if self.current.is_some() || self.state.held() {
            return;
        }
        let Some(p) = self.queue.pop_front() else {
            return;
        };
        let params = self.axis.params();
        let (lo, hi) = (params.hard_min_um, params.hard_max_um);
        // Past the hard limits the carriage runs into the switch.
        let reach = p.target_um.clamp(lo, hi);
        let speed_um_s = p.feed_mm_min * 1000.0 / 60.0;
        let dur = self
            .axis
            .command_move_at(reach, speed_um_s)
            .unwrap_or(Duration::ZERO);
        // The axis starts its clock inside `command_move_at`, after `now`: end the move when
        // the axis does, or a thread preempted in between reports Idle short of the target.
        let ends = self.axis.move_ends_at().max(now + dur);
        if reach != p.target_um {
            self.alarm_at = Some((ends, 1));
        } else if self.faults.take_alarm_mid_move() {
            self.alarm_at = Some((ends - dur / 2, 1));
        }
        self.current = Some((p, ends));
        self.state = if p.jog { State::Jog } else { State::Run };
    }

    fn run_line(&mut self, raw: &[u8], now: Instant, out: &mut Outbox) {
        let text: String = String::from_utf8_lossy(raw)
            .chars()
            .filter(|c| !c.is_whitespace())
            .collect::<String>()
            .to_ascii_uppercase();
        let res = if let Some(sys) = text.strip_prefix('$') {
            self.system(sys, now, out)
        } else if text.is_empty() {
            Ok(Reply::Ok)
        } else if matches!(self.state, State::Alarm | State::Jog) {
            Err(9)
        } else {
            self.gcode(&text, false)
        };
        match res {
            Ok(Reply::Ok) => out.reply("ok\r\n"),
            Ok(Reply::Later) => {}
            Err(code) => out.reply(format!("error:{code}\r\n")),
        }
    }

    fn system(&mut self, cmd: &str, now: Instant, out: &mut Outbox) -> Result<Reply, u32> {
        match cmd {
            "" => {
                out.reply(
                    "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]\r\n",
                );
                Ok(Reply::Ok)
            }
            "X" => {
                if self.state == State::Alarm {
                    out.push("[MSG:Caution: Unlocked]\r\n");
                    self.state = State::Idle;
                }
                Ok(Reply::Ok)
            }
            "H" => {
                if !self.opts.homing_enabled {
                    return Err(5);
                }
                if !matches!(self.state, State::Idle | State::Alarm) {
                    return Err(8);
                }
                let home = self.opts.home_position_um;
                // Seek the switch, then a short pull-off: modelled as one move plus 50 ms.
                let dur = self.axis.command_move(home).unwrap_or(Duration::ZERO);
                self.state = State::Home;
                self.block = Some(Block::Homing {
                    ends: now + dur + Duration::from_millis(50),
                });
                Ok(Reply::Later)
            }
            "I" => {
                out.reply("[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\n");
                Ok(Reply::Ok)
            }
            "G" => {
                let mode = if self.absolute { "G90" } else { "G91" };
                let motion = if self.rapid { "G0" } else { "G1" };
                let f = self.feed_mm_min.unwrap_or(0.0);
                out.reply(format!(
                    "[GC:{motion} G54 G17 G21 {mode} G94 M5 M9 T0 F{f:.0} S0]\r\n"
                ));
                Ok(Reply::Ok)
            }
            "$" => {
                // Too long to print while moving, as GRBL says (held, no line is read).
                if self.state == State::Run {
                    return Err(8);
                }
                out.reply(self.settings());
                Ok(Reply::Ok)
            }
            _ => {
                if let Some(jog) = cmd.strip_prefix("J=") {
                    if !matches!(self.state, State::Idle | State::Jog) {
                        return Err(8);
                    }
                    return self.gcode(jog, true);
                }
                Err(3)
            }
        }
    }

    /// One G-code block (whitespace removed, upper case).
    fn gcode(&mut self, text: &str, jog: bool) -> Result<Reply, u32> {
        let words = parse_words(text)?;
        let mut absolute = self.absolute;
        let mut motion: Option<bool> = None; // Some(true) = rapid G0
        let mut dwell = false;
        let (mut x, mut f, mut p) = (None, None, None);
        for (letter, value) in words {
            match letter {
                'G' => match (value.fract() == 0.0).then_some(value as i64) {
                    Some(0) => motion = Some(true),
                    Some(1) => motion = Some(false),
                    Some(4) => dwell = true,
                    Some(90) => absolute = true,
                    Some(91) => absolute = false,
                    Some(17 | 21 | 54 | 94) => {}
                    _ => return Err(20),
                },
                'X' => x = Some(value),
                'Y' | 'Z' => {} // a single-axis rig: accepted, nothing moves
                'F' => f = Some(value),
                'P' => p = Some(value),
                'N' => {}
                _ => return Err(20),
            }
        }
        if jog {
            // Jogs carry their own mode and feed and leave the parser's modes alone.
            let Some(f) = f else { return Err(22) };
            if f < 0.0 {
                return Err(4);
            }
            if f == 0.0 {
                return Err(22);
            }
            let Some(x) = x else { return Ok(Reply::Ok) };
            if dwell || motion.is_some() {
                return Err(16);
            }
            self.plan(x, absolute, f, true);
            return Ok(Reply::Ok);
        }
        self.absolute = absolute;
        if let Some(f) = f {
            if f < 0.0 {
                return Err(4);
            }
            self.feed_mm_min = Some(f);
        }
        if dwell {
            let secs = p.ok_or(28u32)?;
            if secs < 0.0 {
                return Err(4);
            }
            self.block = Some(Block::Dwell { secs, since: None });
            return Ok(Reply::Later);
        }
        if let Some(m) = motion {
            self.rapid = m;
        }
        if let Some(x) = x {
            let feed = if self.rapid {
                self.max_rate_mm_min()
            } else {
                self.feed_mm_min.filter(|f| *f > 0.0).ok_or(22u32)?
            };
            self.plan(x, self.absolute, feed, false);
        }
        Ok(Reply::Ok)
    }

    /// `$110`: the axis' top speed, in mm/min.
    fn max_rate_mm_min(&self) -> f64 {
        self.axis.params().max_speed_um_s * 60.0 / 1000.0
    }

    /// Queue a move to X word `x_mm` (absolute, or relative to the parser's position), to
    /// the nearest whole motor step as GRBL's planner rounds it: `lround` of the 32-bit
    /// product of mm and steps/mm.
    fn plan(&mut self, x_mm: f64, absolute: bool, feed_mm_min: f64, jog: bool) {
        let target_mm = if absolute {
            x_mm as f32
        } else {
            self.plan_end_mm + x_mm as f32
        };
        let spm = self.opts.steps_per_mm;
        let steps = f64::from(target_mm * spm as f32).round();
        let target_um = steps / spm * 1000.0;
        // GRBL's planner caps every rate at the axis' max rate.
        let feed_mm_min = feed_mm_min.min(self.max_rate_mm_min());
        self.queue.push_back(Planned {
            target_um,
            feed_mm_min,
            jog,
        });
        self.plan_end_mm = target_mm;
        if self.state == State::Idle {
            self.state = if jog { State::Jog } else { State::Run };
        }
    }
}

enum Reply {
    Ok,
    /// The `ok` comes when the command completes (dwell, homing).
    Later,
}

/// Split a block into (letter, value) words: GRBL's error 1 for a missing letter, 2 for a
/// bad number.
fn parse_words(text: &str) -> Result<Vec<(char, f64)>, u32> {
    let mut words = Vec::new();
    let mut chars = text.chars().peekable();
    while let Some(c) = chars.next() {
        if !c.is_ascii_alphabetic() {
            return Err(1);
        }
        let mut num = String::new();
        while let Some(&d) = chars.peek() {
            if d.is_ascii_digit() || d == '.' || d == '-' || d == '+' {
                num.push(d);
                chars.next();
            } else {
                break;
            }
        }
        let v = read_float(&num).ok_or(2u32)?;
        words.push((c, f64::from(v)));
    }
    Ok(words)
}

/// A number as GRBL 1.1h's `read_float` reads it: sign, up to 8 significant digits into an
/// integer, then scaled by 32-bit float multiplications (by 0.01, 0.1 or 10, each done in
/// double on the PC build and stored back to float). None: no digits, or more than one sign
/// or point.
fn read_float(text: &str) -> Option<f32> {
    let (neg, digits) = match text.as_bytes().first() {
        Some(b'-') => (true, &text[1..]),
        Some(b'+') => (false, &text[1..]),
        _ => (false, text),
    };
    let (mut int, mut exp, mut ndigit, mut decimal) = (0u32, 0i32, 0u32, false);
    for c in digits.bytes() {
        match c {
            b'0'..=b'9' => {
                ndigit += 1;
                if ndigit <= 8 {
                    exp -= i32::from(decimal);
                    int = int * 10 + u32::from(c - b'0');
                } else if !decimal {
                    exp += 1;
                }
            }
            b'.' if !decimal => decimal = true,
            _ => return None,
        }
    }
    if ndigit == 0 {
        return None;
    }
    let mut v = int as f32;
    if v != 0.0 {
        while exp <= -2 {
            v = (f64::from(v) * 0.01) as f32;
            exp += 2;
        }
        if exp < 0 {
            v = (f64::from(v) * 0.1) as f32;
        }
        while exp > 0 {
            v = (f64::from(v) * 10.0) as f32;
            exp -= 1;
        }
    }
    Some(if neg { -v } else { v })
}

impl Controller for Grbl {
    fn on_open(&mut self, now: Instant, _out: &mut Outbox) {
        if !self.opts.reset_on_open {
            return;
        }
        // DTR resets the board: everything stops, and the banner comes after the boot delay.
        self.reset(now);
        self.critical = false;
        self.state = if self.opts.alarm_on_boot {
            State::Alarm
        } else {
            State::Idle
        };
        self.booting_until = Some(now + self.opts.boot_delay);
    }

    fn on_close(&mut self) {
        self.booting_until = None;
    }

    fn on_bytes(&mut self, bytes: &[u8], now: Instant, out: &mut Outbox) {
        if self.booting_until.is_some() {
            return; // the bootloader swallows it
        }
        for &b in bytes {
            match b {
                b'?' => out.reply(self.status(now)),
                b'!' => self.feed_hold(now),
                0x85 if self.state == State::Jog => self.feed_hold(now),
                b'~' => {
                    // Cycle start resumes only a hold that has completed.
                    if self.state == (State::Hold { complete: true }) {
                        self.state = State::Run;
                        self.start_next(now);
                        if self.current.is_none() {
                            self.state = State::Idle;
                        }
                    }
                }
                0x18 => self.soft_reset(now, out),
                b'\r' => {}
                b'\n' => {
                    let line = std::mem::take(&mut self.line);
                    if !self.critical {
                        self.pending.push_back(line);
                    }
                }
                0x80..=0xff => {} // overrides and other realtime commands: ignored
                _ => {
                    if self.line.len() < 80 {
                        self.line.push(b);
                    }
                }
            }
        }
    }

    fn tick(&mut self, now: Instant, out: &mut Outbox) -> Option<Instant> {
        if let Some(t) = self.booting_until {
            if now < t {
                return Some(t);
            }
            self.booting_until = None;
            self.banner(out);
        }
        if self.faults.take_feed_hold() {
            self.feed_hold(now);
        }
        if self.braking_until.is_some_and(|t| now >= t) {
            self.braking_until = None;
            self.state = match self.state {
                State::Hold { .. } => State::Hold { complete: true },
                State::Jog => State::Idle,
                s => s,
            };
        }
        if let Some((t, code)) = self.alarm_at {
            if now >= t {
                self.raise_alarm(code, now, out);
            }
        }
        if let Some((_, ends)) = self.current {
            if now >= ends && self.alarm_at.is_none() {
                self.current = None;
            } else if self.alarm_at.is_none() && self.faults.take_alarm_mid_move() {
                self.alarm_at = Some((now + (ends - now) / 2, 1));
            }
        }
        self.start_next(now);
        if self.current.is_none()
            && self.queue.is_empty()
            && self.braking_until.is_none()
            && matches!(self.state, State::Run | State::Jog)
        {
            self.state = State::Idle;
        }
        let planner_empty = self.current.is_none() && self.queue.is_empty() && !self.state.held();
        match self.block {
            // The dwell starts once the planner has run dry; its `ok` comes after it.
            Some(Block::Dwell { secs, since }) if planner_empty => {
                let since = since.unwrap_or(now);
                if now >= since + Duration::from_secs_f64(secs) {
                    self.block = None;
                    out.reply("ok\r\n");
                } else {
                    self.block = Some(Block::Dwell {
                        secs,
                        since: Some(since),
                    });
                }
            }
            Some(Block::Homing { ends }) if now >= ends => {
                self.block = None;
                self.axis.set_position(self.opts.home_position_um);
                self.plan_end_mm = (self.opts.home_position_um / 1000.0) as f32;
                self.state = State::Idle;
                out.reply("ok\r\n");
            }
            _ => {}
        }
        // A hold suspends GRBL's main loop: lines wait, unanswered, until `~` or a reset.
        while self.block.is_none() && !self.critical && !self.state.held() {
            let Some(line) = self.pending.pop_front() else {
                break;
            };
            self.run_line(&line, now, out);
            // The planner starts a move as soon as it is queued.
            self.start_next(now);
        }
        // Tick soon while anything is in flight.
        let busy = self.current.is_some()
            || self.braking_until.is_some()
            || !self.queue.is_empty()
            || self.block.is_some()
            || self.alarm_at.is_some();
        busy.then(|| now + Duration::from_millis(1))
    }

    fn line_end(&self) -> &'static [u8] {
        b"\r\n"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::{AxisParams, Profile};
    use crate::pty::TestClient;

    const T: Duration = Duration::from_secs(2);

    fn booted() -> (Arc<Axis>, GrblSim, TestClient) {
        let axis = Arc::new(Axis::new(AxisParams::default()));
        let sim = GrblSim::spawn(axis.clone(), GrblSimOptions::default(), None).unwrap();
        let mut c = TestClient::open(&sim.path());
        assert_eq!(c.line_where(T, |l| !l.is_empty()).unwrap(), BANNER);
        (axis, sim, c)
    }

    #[test]
    fn dwell_is_answered_only_after_the_move_and_hold_resume_work() {
        let (axis, _sim, mut c) = booted();
        c.send(b"G91 G1 X4 F1200\n");
        assert_eq!(c.line(T).unwrap(), "ok");
        std::thread::sleep(Duration::from_millis(60));
        assert!(axis.is_moving(Instant::now()));
        // At 20 mm/s the hold brakes for 40 ms (Hold:1), then holds complete (Hold:0).
        c.send(b"!?");
        let r = c.line(T).unwrap();
        assert!(r.starts_with("<Hold:1|MPos:"), "{r}");
        std::thread::sleep(Duration::from_millis(60));
        c.send(b"?");
        let r = c.line(T).unwrap();
        assert!(r.starts_with("<Hold:0|MPos:"), "{r}");
        assert!(!axis.is_moving(Instant::now()));
        c.send(b"G4 P0\n");
        // Held: the dwell does not complete.
        assert_eq!(c.line(Duration::from_millis(100)), None);
        c.send(b"~");
        assert_eq!(c.line(T).unwrap(), "ok");
        assert!(!axis.is_moving(Instant::now()));
        c.send(b"?");
        assert_eq!(c.line(T).unwrap(), "<Idle|MPos:4.000,0.000,0.000|FS:0,0>");
    }

    #[test]
    fn reset_while_moving_alarms_and_unlock_clears_it() {
        let (_axis, _sim, mut c) = booted();
        c.send(b"G1 X4 F1200\n");
        assert_eq!(c.line(T).unwrap(), "ok");
        c.send(&[0x18]);
        assert_eq!(c.line_where(T, |l| !l.is_empty()).unwrap(), "ALARM:3");
        assert_eq!(c.line_where(T, |l| !l.is_empty()).unwrap(), BANNER);
        c.send(b"G1 X1\n");
        assert_eq!(c.line_where(T, |l| !l.starts_with('[')).unwrap(), "error:9");
        c.send(b"$X\n");
        assert_eq!(c.line_where(T, |l| !l.starts_with('[')).unwrap(), "ok");
        // The reset also cleared the modal feed rate.
        c.send(b"G1 X1\n");
        assert_eq!(c.line(T).unwrap(), "error:22");
        c.send(b"G1 X1 F600\n");
        assert_eq!(c.line(T).unwrap(), "ok");
    }

    /// A booted emulator on an axis without positioning error (exact profile positions).
    fn booted_exact() -> (Arc<Axis>, GrblSim, TestClient) {
        let axis = Arc::new(Axis::new(AxisParams {
            position_error_rms_um: 0.0,
            ..AxisParams::default()
        }));
        let sim = GrblSim::spawn(axis.clone(), GrblSimOptions::default(), None).unwrap();
        let mut c = TestClient::open(&sim.path());
        assert_eq!(c.line_where(T, |l| !l.is_empty()).unwrap(), BANNER);
        (axis, sim, c)
    }

    /// Send one motion line, and return the move it started: its start and profile.
    fn start_move(axis: &Axis, c: &mut TestClient, line: &str) -> (Instant, Profile) {
        c.send(format!("{line}\n").as_bytes());
        assert_eq!(c.line(T).unwrap(), "ok", "{line}");
        axis.current_move()
            .unwrap_or_else(|| panic!("{line}: no move in progress"))
    }

    /// Wait for the planner to empty (`G4 P0`).
    fn drain(c: &mut TestClient) {
        c.send(b"G4 P0\n");
        assert_eq!(c.line(T).unwrap(), "ok");
    }

    /// Wait for a jog to end: GRBL refuses G-code (`G4 P0` too) while jogging.
    fn jog_done(c: &mut TestClient) {
        for _ in 0..1000 {
            c.send(b"?");
            if c.line(T).unwrap().starts_with("<Idle|") {
                return;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        panic!("the jog never ended");
    }

    #[test]
    fn g1_cruises_at_the_modal_feed_and_g0_at_the_max_rate() {
        let (axis, _sim, mut c) = booted_exact();
        // F300 mm/min = 5 mm/s: 1 mm takes 0.21 s (0.19 s cruising, 10 ms per ramp).
        let (start, slow) = start_move(&axis, &mut c, "G90 G1 X1 F300");
        assert!((slow.peak_speed_um_s() - 5_000.0).abs() < 1e-9);
        assert!(
            (slow.duration_s() - 0.210).abs() < 1e-9,
            "{}",
            slow.duration_s()
        );
        // 100 ms of model time in: 25 µm of ramp + 90 ms at 5 mm/s.
        let at_100ms = axis.position_at(start + Duration::from_millis(100));
        assert!((at_100ms - 475.0).abs() < 0.5, "{at_100ms}");
        drain(&mut c);
        // F is modal: the next G1 without it runs at 300 mm/min too.
        let (_, modal) = start_move(&axis, &mut c, "G1 X2");
        assert!((modal.peak_speed_um_s() - 5_000.0).abs() < 1e-9);
        drain(&mut c);
        // G0 runs at the max rate ($110 = 1200 mm/min = the axis' 20 mm/s)...
        let (start, rapid) = start_move(&axis, &mut c, "G0 X3");
        assert_eq!(rapid.peak_speed_um_s(), 20_000.0);
        // ... so after the same 100 ms it is 4x farther along than the F300 move was
        // (1 mm at 20 mm/s is over in ~90 ms: it has arrived).
        let rapid_at_100ms = axis.position_at(start + Duration::from_millis(100)) - 2_000.0;
        assert!((rapid_at_100ms - 1_000.0).abs() < 0.5, "{rapid_at_100ms}");
        assert!(rapid.duration_s() < slow.duration_s() / 2.0);
        drain(&mut c);
        // ... and leaves the modal feed alone.
        let (_, after_g0) = start_move(&axis, &mut c, "G1 X4");
        assert!((after_g0.peak_speed_um_s() - 5_000.0).abs() < 1e-9);
        drain(&mut c);
        assert_eq!(axis.position_at(Instant::now()), 4_000.0);
    }

    #[test]
    fn feed_is_proportional_and_clamped_to_the_max_rate() {
        let (axis, _sim, mut c) = booted_exact();
        // 4 mm at 600 and at 150 mm/min: the cruise takes 4x as long.
        let (_, f600) = start_move(&axis, &mut c, "G91 G1 X4 F600");
        c.send(b"?");
        let r = c.line(T).unwrap();
        assert!(r.starts_with("<Run|") && r.ends_with("|FS:600,0>"), "{r}");
        drain(&mut c);
        let (s150, f150) = start_move(&axis, &mut c, "G1 X4 F150");
        assert!((f600.peak_speed_um_s() - 10_000.0).abs() < 1e-9);
        assert!((f150.peak_speed_um_s() - 2_500.0).abs() < 1e-9);
        let cruise = |p: &Profile| p.duration_s() - p.peak_speed_um_s() / 5e5;
        assert!((cruise(&f150) / cruise(&f600) - 4.0).abs() < 1e-9);
        // 1 s of model time into the slow move: 2.5 mm of the 4, not the end.
        let at_1s = axis.position_at(s150 + Duration::from_secs(1)) - 4_000.0;
        assert!((at_1s - 2_493.75).abs() < 0.5, "{at_1s}");
        // Stop it rather than wait 1.6 s.
        c.send(&[0x18]);
        assert_eq!(c.line_where(T, |l| !l.is_empty()).unwrap(), "ALARM:3");
        assert_eq!(c.line_where(T, |l| !l.is_empty()).unwrap(), BANNER);
        c.send(b"$X\n");
        assert_eq!(c.line_where(T, |l| !l.starts_with('[')).unwrap(), "ok");
        // Faster than the max rate: the axis' 20 mm/s, reported as 1200 mm/min.
        let (_, fast) = start_move(&axis, &mut c, "G91 G1 X4 F6000");
        assert_eq!(fast.peak_speed_um_s(), 20_000.0);
        c.send(b"?");
        let r = c.line(T).unwrap();
        assert!(r.ends_with("|FS:1200,0>"), "{r}");
        drain(&mut c);
        // A jog carries its own feed, clamped the same way.
        let (_, jog) = start_move(&axis, &mut c, "$J=G91 X1 F120");
        assert!((jog.peak_speed_um_s() - 2_000.0).abs() < 1e-9);
    }

    #[test]
    fn a_g1_without_a_feed_rate_is_error_22_and_moves_nothing() {
        let (axis, _sim, mut c) = booted_exact();
        for (line, code) in [
            ("G1 X1", "error:22"),
            ("G1 X1 F0", "error:22"),
            ("G1 X1 F-5", "error:4"),
            ("$J=G91 X1", "error:22"),
            ("$J=G91 X1 F0", "error:22"),
            ("$J=G91 X1 F-5", "error:4"),
        ] {
            c.send(format!("{line}\n").as_bytes());
            assert_eq!(c.line(T).unwrap(), code, "{line}");
            assert!(!axis.is_moving(Instant::now()), "{line}");
        }
        // A rapid needs no feed; it does not set one for G1 either.
        let (_, rapid) = start_move(&axis, &mut c, "G0 X1");
        assert_eq!(rapid.peak_speed_um_s(), 20_000.0);
        drain(&mut c);
        c.send(b"G1 X2\n");
        assert_eq!(c.line(T).unwrap(), "error:22");
        // A jog's feed is not modal either.
        let _ = start_move(&axis, &mut c, "$J=G91 X0.1 F600");
        jog_done(&mut c);
        c.send(b"G1 X2\n");
        assert_eq!(c.line(T).unwrap(), "error:22");
        assert_eq!(axis.position_at(Instant::now()), 1_100.0);
    }

    #[test]
    fn targets_are_whole_motor_steps_rounded_as_the_firmware_rounds_them() {
        let axis = Arc::new(Axis::new(AxisParams {
            position_error_rms_um: 0.0,
            ..AxisParams::default()
        }));
        let opts = GrblSimOptions {
            steps_per_mm: 250.0,
            ..GrblSimOptions::default()
        };
        let sim = GrblSim::spawn(axis, opts, None).unwrap();
        let mut c = TestClient::open(&sim.path());
        assert_eq!(c.line_where(T, |l| !l.is_empty()).unwrap(), BANNER);
        // 12.5, 25, 37.5 steps: GRBL's 32-bit floats put each half step just above .5.
        for want in ["0.052", "0.100", "0.152"] {
            c.send(b"G91 G1 X0.05 F600\nG4 P0\n");
            assert_eq!(c.line(T).unwrap(), "ok");
            assert_eq!(c.line(T).unwrap(), "ok");
            c.send(b"?");
            let r = c.line(T).unwrap();
            assert!(r.starts_with(&format!("<Idle|MPos:{want},")), "{r}");
        }
        assert_eq!(read_float("0.15"), Some(0.15f32));
        assert_eq!(read_float("-1.0001"), Some(-1.0001f32));
        assert_eq!(read_float("."), None);
    }

    #[test]
    fn a_reset_after_a_completed_hold_raises_no_alarm() {
        let (_axis, _sim, mut c) = booted();
        c.send(b"G1 X4 F1200\n");
        assert_eq!(c.line(T).unwrap(), "ok");
        std::thread::sleep(Duration::from_millis(60));
        c.send(b"!");
        std::thread::sleep(Duration::from_millis(80));
        c.send(&[0x18]);
        assert_eq!(c.line_where(T, |l| !l.is_empty()).unwrap(), BANNER);
        c.send(b"?");
        let r = c.line(T).unwrap();
        assert!(r.starts_with("<Idle|"), "{r}");
    }

    #[test]
    fn words_are_split_and_bad_ones_get_grbl_codes() {
        assert_eq!(
            parse_words("G91G1X0.05F600").unwrap(),
            vec![
                ('G', 91.0),
                ('G', 1.0),
                ('X', f64::from(0.05f32)),
                ('F', 600.0)
            ]
        );
        assert_eq!(parse_words("91"), Err(1));
        assert_eq!(parse_words("X1.2.3"), Err(2));
    }
}
