//! rigd's GRBL driver against GRBL 1.1h's own firmware (tests/support/firmware.rs): it
//! connects without resetting the controller, reads `$100`/`$110`/`$120`, moves in whole
//! motor steps, polls `?` at no more than 5 Hz, and stops a move with a feed hold and a reset
//! that raise no alarm.

use crate::support::firmware::Firmware;
use rigd::hw::grbl::{GrblOptions, GrblStage};
use rigd::hw::limits::TravelLimits;
use rigd::hw::{MotionState, Stage};
use std::time::{Duration, Instant};

/// GRBL 1.1h's defaults: `$100=250` (4 µm steps), `$110=500` mm/min, `$120=10` mm/s².
const STEP_UM: f64 = 4.0;

/// The driver on the firmware's port. Replies may take 3 s: the firmware's simulated clock
/// runs slow on a loaded machine.
fn connect(fw: &Firmware) -> GrblStage {
    let limits = TravelLimits::new(-50_000.0, 50_000.0, 50_000.0).unwrap();
    let mut opts = GrblOptions::new(fw.port.clone(), limits);
    opts.reply_timeout_ms = 3_000;
    GrblStage::connect("axis", opts).unwrap()
}

/// Soft resets (0x18) sent to the firmware so far.
fn resets(fw: &Firmware) -> usize {
    fw.sent().iter().filter(|&&b| b == 0x18).count()
}

/// Wait for the move just sent as the engine does: `status()` every 2 ms until idle, then
/// `wait_settled`. Returns where the axis settled.
fn follow(s: &mut GrblStage) -> f64 {
    let t0 = Instant::now();
    while s.status().unwrap().state != MotionState::Idle {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "the move never ended"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    s.wait_settled(Duration::from_secs(30)).unwrap()
}

#[test]
fn the_driver_reads_the_firmwares_settings_without_resetting_it() {
    let Some(fw) = Firmware::start("the_driver_reads_the_firmwares_settings") else {
        return;
    };
    let s = connect(&fw);
    let m = s.machine().expect("$$ read at connect");
    assert_eq!(m.controller, "grbl");
    assert!((m.motor_step_um - STEP_UM).abs() < 1e-9, "{m:?}");
    assert!(
        (m.max_rate_um_s - 500.0 * 1000.0 / 60.0).abs() < 1e-6,
        "{m:?}"
    );
    assert!((m.accel_um_s2 - 10_000.0).abs() < 1e-6, "{m:?}");
    assert_eq!(resets(&fw), 0, "connecting sent a soft reset");
}

#[test]
fn steps_are_whole_motor_steps_and_the_reported_position_says_which() {
    let Some(fw) = Firmware::start("steps_are_whole_motor_steps") else {
        return;
    };
    let mut s = connect(&fw);
    let m = s.machine().unwrap();
    let mut reached = Vec::new();
    for i in 1..=4 {
        s.move_rel(50.0).unwrap();
        let at = follow(&mut s);
        let commanded = 50.0 * f64::from(i);
        // GRBL rounds each target to the nearest step: within half a step (and the report's
        // 1 µm), on a whole step.
        assert!(
            (at - commanded).abs() <= STEP_UM / 2.0 + 1e-6,
            "{at} vs {commanded}"
        );
        assert!((at / STEP_UM - (at / STEP_UM).round()).abs() < 1e-6, "{at}");
        assert_eq!(m.reached_um(commanded, at), at);
        reached.push(at);
    }
    // 12.5, 25, 37.5, 50 steps: the half steps round up in the firmware's floats.
    assert_eq!(reached, vec![52.0, 100.0, 152.0, 200.0]);
}

#[test]
fn status_is_polled_at_5_hz_at_most_during_a_move() {
    let Some(fw) = Firmware::start("status_is_polled_at_5_hz_at_most") else {
        return;
    };
    let mut s = connect(&fw);
    let polls_before = s.polls();
    let t0 = Instant::now();
    // 3 mm at 10 mm/s² never reaches the firmware's 8.3 mm/s: 2·sqrt(d/a) = 1.095 s.
    s.move_rel(3_000.0).unwrap();
    let planned_s = s.planned_move().unwrap().as_secs_f64();
    assert!((planned_s - 1.0954).abs() < 1e-3, "{planned_s}");
    let at = follow(&mut s);
    let secs = t0.elapsed().as_secs_f64();
    let polls = s.polls() - polls_before;
    assert!((at - 3_000.0).abs() < 1e-6, "{at}");
    // At 5 Hz, plus the report that confirms the end.
    assert!(
        (polls as f64) <= secs * 5.0 + 2.0,
        "{polls} polls in {secs:.2} s"
    );
    let sent_polls = fw.sent().iter().filter(|&&b| b == b'?').count() as u64;
    assert!(
        sent_polls >= polls,
        "{sent_polls} on the wire, {polls} counted"
    );
}

#[test]
fn a_stop_mid_move_brakes_without_an_alarm_and_the_next_move_runs() {
    let Some(fw) = Firmware::start("a_stop_mid_move_brakes_without_an_alarm") else {
        return;
    };
    let mut s = connect(&fw);
    s.move_abs(4_000.0).unwrap();
    std::thread::sleep(Duration::from_millis(500));
    s.stop().unwrap();
    let st = s.status().unwrap();
    assert_eq!(st.state, MotionState::Idle, "{st:?}");
    assert!(
        st.position_um > 0.0 && st.position_um < 4_000.0,
        "stopped at {}",
        st.position_um
    );
    let received = String::from_utf8_lossy(&fw.received()).into_owned();
    assert!(!received.contains("ALARM"), "{received}");
    assert!(fw.sent().contains(&b'!'), "no feed hold was sent");
    // The planner was cleared: the next move starts from where the axis stopped.
    s.move_rel(100.0).unwrap();
    let at = follow(&mut s);
    assert!(
        (at - (st.position_um + 100.0)).abs() <= STEP_UM,
        "{at} after {st:?}"
    );
}
