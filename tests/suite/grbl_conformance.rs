//! One script, played to GRBL 1.1h's own firmware and to the sim's GRBL emulator set up as
//! the firmware's defaults: the replies must agree (not their timing). Status reports are
//! compared by state and machine position (the firmware's extra fields, `Pn:`, `WCO:` and
//! `Ov:`, come and go); positions after a hold, which depend on when it came, by state only.

use crate::support::firmware::{Firmware, RawClient};
use rigd::sim::grbl::{GrblSim, GrblSimOptions};
use rigd::sim::motion::{Axis, AxisParams};
use std::sync::Arc;
use std::time::Duration;

/// How a step's replies end, and how its status reports compare.
#[derive(Clone, Copy)]
enum Until {
    /// `ok` or `error:N`.
    Reply,
    /// The banner after a reset.
    Banner,
    /// A status report (`?`), compared by state and position.
    Report,
    /// A status report, compared by state only.
    State,
    /// Status reports polled every 100 ms until one in this state; the distinct states seen
    /// on the way are the reply.
    Reaches(&'static str),
    /// Whatever comes within a second (a held GRBL reads no line).
    Nothing,
}

/// `(ms to wait first, bytes to send, what ends the reply)`, in order. The waits let a move
/// get up to speed before it is held, reset or cancelled.
const SCRIPT: &[(u64, &[u8], Until)] = &[
    (150, b"$I\n", Until::Reply),
    (0, b"$$\n", Until::Reply),
    (0, b"G91 G1 X0.05 F600\n", Until::Reply),
    (0, b"G4 P0\n", Until::Reply),
    (0, b"?", Until::Report),
    (0, b"G90 G1 X0.15\n", Until::Reply),
    (0, b"G4 P0\n", Until::Reply),
    (0, b"?", Until::Report),
    (0, b"G1 X1.0001 F300\n", Until::Reply),
    (0, b"G4 P0\n", Until::Reply),
    (0, b"?", Until::Report),
    // `$$` is refused while moving; a feed hold at full speed brakes (Hold:1) to a completed
    // hold (Hold:0), during which no line is read ...
    (0, b"G1 X9 F500\n", Until::Reply),
    // The `ok` comes once the move is planned; 200 ms on, both are moving (for seconds).
    (200, b"$$\n", Until::Reply),
    (1000, b"!", Until::Reaches("Hold:0")),
    (0, b"$$\n", Until::Nothing),
    // ... and a reset clears it (the waiting line too) without an alarm.
    (0, b"\x18", Until::Banner),
    (0, b"?", Until::State),
    // A reset while moving is ALARM:3 and a lock until $X.
    (0, b"G1 X1 F500\n", Until::Reply),
    (300, b"\x18", Until::Banner),
    (0, b"?", Until::State),
    (0, b"G1 X1\n", Until::Reply),
    (0, b"$X\n", Until::Reply),
    (0, b"?", Until::State),
    // The reset cleared the modal feed rate.
    (0, b"G1 X1\n", Until::Reply),
    (0, b"$H\n", Until::Reply),
    // A jog refuses G-code, and jog cancel ends it without an alarm.
    (0, b"$J=G91 X10 F300\n", Until::Reply),
    (150, b"G1 X2 F300\n", Until::Reply),
    (800, b"\x85", Until::Reaches("Idle")),
    // A feed hold when idle is a completed hold; cycle start ends it.
    (0, b"!", Until::Reaches("Hold:0")),
    (0, b"~", Until::Reaches("Idle")),
    (0, b"G1 X0.5 F300\n", Until::Reply),
    (0, b"G4 P0\n", Until::Reply),
    (0, b"?", Until::Report),
];

const WITHIN: Duration = Duration::from_secs(20);

/// A status report reduced to what both must agree on.
fn report(line: &str, with_position: bool) -> String {
    let body = line.trim_start_matches('<').trim_end_matches('>');
    let mut fields = body.split('|');
    let state = fields.next().unwrap_or_default().to_string();
    if !with_position {
        return state;
    }
    let mpos = fields.find(|f| f.starts_with("MPos:")).unwrap_or("no MPos");
    format!("{state}|{mpos}")
}

/// Play the script on `port`; each step's replies, normalised.
fn play(port: &str) -> Vec<Vec<String>> {
    let mut c = RawClient::open(port);
    // Whatever the board said while booting (the firmware: `error:7` on a fresh EEPROM).
    while c.line(Duration::from_millis(1500)).is_some() {}
    SCRIPT
        .iter()
        .map(|&(wait_ms, bytes, until)| {
            std::thread::sleep(Duration::from_millis(wait_ms));
            c.send(bytes);
            replies(&mut c, until)
        })
        .collect()
}

fn replies(c: &mut RawClient, until: Until) -> Vec<String> {
    let is_report = |l: &str| l.starts_with('<');
    let lines = match until {
        Until::Reply => c.until(|l| l == "ok" || l.starts_with("error:"), WITHIN),
        Until::Banner => c.until(|l| l.starts_with("Grbl "), WITHIN),
        Until::Report | Until::State => c.until(is_report, WITHIN),
        Until::Reaches(state) => return reaches(c, state),
        Until::Nothing => {
            return std::iter::from_fn(|| c.line(Duration::from_secs(1))).collect();
        }
    };
    lines
        .into_iter()
        .filter(|l| !l.is_empty())
        .map(|l| match until {
            Until::Report if is_report(&l) => report(&l, true),
            _ if is_report(&l) => report(&l, false),
            _ => l,
        })
        .collect()
}

/// Poll until a report in `state`; the distinct states on the way.
fn reaches(c: &mut RawClient, state: &str) -> Vec<String> {
    let mut seen: Vec<String> = Vec::new();
    for _ in 0..200 {
        // After the realtime command took effect: GRBL reports before it acts on a
        // command that comes with the `?`.
        std::thread::sleep(Duration::from_millis(100));
        c.send(b"?");
        let lines = c.until(|l| l.starts_with('<'), WITHIN);
        let now = report(lines.last().unwrap(), false);
        if seen.last() != Some(&now) {
            seen.push(now.clone());
        }
        if now == state {
            return seen;
        }
    }
    panic!("never reached {state}: {seen:?}")
}

/// The emulator as GRBL 1.1h's defaults: 250 steps/mm, 500 mm/min, 10 mm/s², 200 mm of
/// travel, homing off.
fn emulator() -> GrblSim {
    let axis = Arc::new(Axis::new(AxisParams {
        max_speed_um_s: 500.0 * 1000.0 / 60.0,
        accel_um_s2: 10_000.0,
        position_error_rms_um: 0.0,
        hard_min_um: -100_000.0,
        hard_max_um: 100_000.0,
        ..AxisParams::default()
    }));
    let opts = GrblSimOptions {
        steps_per_mm: 250.0,
        homing_enabled: false,
        ..GrblSimOptions::default()
    };
    GrblSim::spawn(axis, opts, None).unwrap()
}

#[test]
fn the_emulator_answers_the_script_as_the_firmware_does() {
    let Some(fw) = Firmware::start("the_emulator_answers_the_script_as_the_firmware_does") else {
        return;
    };
    // One after the other: the firmware's clock runs in approximate real time, and a
    // second peer playing beside it would load the machine it keeps time on.
    let firmware = play(&fw.port);
    drop(fw);
    let emu = emulator();
    let emulated = play(&emu.path().to_string_lossy());
    for (i, ((_, sent, _), (f, e))) in SCRIPT
        .iter()
        .zip(firmware.iter().zip(&emulated))
        .enumerate()
    {
        assert_eq!(
            f,
            e,
            "step {i} ({:?}): the firmware answered {f:?}, the emulator {e:?}",
            String::from_utf8_lossy(sent)
        );
    }
}
