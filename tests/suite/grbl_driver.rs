//! rigd's GRBL driver against the GRBL emulator, over a real pseudo-terminal through the
//! real `serialport` code path. The emulator's parser lives in sim/, the driver's in
//! src/hw/: they share nothing.

use crate::support::emulated::{self, replug, step, time_per_step, unplug};
use rigd::hw::grbl::{GrblOptions, GrblStage, GrblState, OnAlarm};
use rigd::hw::grbl_codes::GrblAlarm;
use rigd::hw::limits::TravelLimits;
use rigd::hw::{HwError, MotionState, Stage, StageStatus};
use rigd::sim::grbl::{GrblSim, GrblSimOptions};
use rigd::sim::motion::{AxisParams, Profile};
use std::time::{Duration, Instant};

const SETTLE: Duration = Duration::from_secs(3);
/// The axis' positioning error is 2 µm RMS: 5 sigma.
const TRUE_POSITION_TOL_UM: f64 = 10.0;

type Rig = emulated::Rig<GrblSim, GrblOptions>;

fn rig_with(sim_opts: GrblSimOptions) -> Rig {
    let spawn = |axis, link: &_| GrblSim::spawn(axis, sim_opts, Some(link));
    Rig::spawn(AxisParams::default(), "grbl", spawn, |port| {
        let limits = TravelLimits::new(-1_000.0, 20_000.0, 5_000.0).unwrap();
        let mut opts = GrblOptions::new(port, limits);
        opts.banner_timeout_ms = 500;
        opts.reply_timeout_ms = 200;
        opts.home_timeout_ms = 3_000;
        opts
    })
}

fn rig() -> Rig {
    rig_with(GrblSimOptions::default())
}

#[test]
fn connect_waits_for_the_banner_and_reports_idle() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    assert_eq!(s.banners_seen(), 1);
    let st = s.status().unwrap();
    assert_eq!(st.state, MotionState::Idle);
    assert_eq!(st.position_um, 0.0);
}

#[test]
fn a_board_that_does_not_reset_on_open_is_asked_not_reset() {
    // No DTR reset: opening is silent, so the banner wait times out and the driver asks for
    // a status report. It sends no soft reset: the board may be mid-move.
    let r = rig_with(GrblSimOptions {
        reset_on_open: false,
        ..GrblSimOptions::default()
    });
    let t = Instant::now();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    assert!(t.elapsed() >= Duration::from_millis(r.opts.banner_timeout_ms));
    assert_eq!(s.banners_seen(), 0);
    assert_eq!(s.status().unwrap().state, MotionState::Idle);
    assert_eq!(step(&mut s, 50.0, SETTLE).unwrap(), 50.0);
}

#[test]
fn a_board_that_never_answers_times_out_naming_the_banner() {
    let r = rig_with(GrblSimOptions {
        boot_delay: Duration::from_secs(5),
        ..GrblSimOptions::default()
    });
    let mut opts = r.opts.clone();
    opts.banner_timeout_ms = 100;
    match GrblStage::connect("axis", opts).unwrap_err() {
        HwError::Timeout { waiting_for, .. } => {
            assert!(
                waiting_for.contains("banner or status report"),
                "{waiting_for}"
            )
        }
        e => panic!("expected a timeout, got {e}"),
    }
}

#[test]
fn relative_and_absolute_moves_end_within_the_positioning_error() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    for _ in 0..3 {
        s.move_rel(50.0).unwrap();
        s.wait_settled(SETTLE).unwrap();
    }
    let p = s.position_um().unwrap();
    assert!((p - 150.0).abs() < 1.0, "reported {p}");
    assert!((r.true_um() - 150.0).abs() < TRUE_POSITION_TOL_UM);
    s.move_abs(2_000.0).unwrap();
    let p = s.wait_settled(SETTLE).unwrap();
    assert!((p - 2_000.0).abs() < 1.0, "reported {p}");
    assert!((r.true_um() - 2_000.0).abs() < TRUE_POSITION_TOL_UM);
    s.move_rel(-500.0).unwrap();
    let p = s.wait_settled(SETTLE).unwrap();
    assert!((p - 1_500.0).abs() < 1.0, "reported {p}");
}

#[test]
fn ok_is_not_done_but_wait_settled_is() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    // 4 mm at 20 mm/s: ~0.2 s of motion, far longer than an `ok`.
    s.move_rel(4_000.0).unwrap();
    assert!(
        r.axis.is_moving(Instant::now()),
        "ok came back before motion ended"
    );
    assert_eq!(s.status().unwrap().state, MotionState::Moving);
    s.wait_settled(SETTLE).unwrap();
    assert!(!r.axis.is_moving(Instant::now()));
    assert_eq!(s.status().unwrap().state, MotionState::Idle);
}

#[test]
fn stop_mid_move_halts_short_and_leaves_the_axis_usable() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    s.move_rel(5_000.0).unwrap();
    std::thread::sleep(Duration::from_millis(60));
    s.stop().unwrap();
    let here = s.position_um().unwrap();
    assert!(here > 100.0 && here < 4_900.0, "stopped at {here}");
    assert!(!r.axis.is_moving(Instant::now()));
    assert_eq!(s.status().unwrap().state, MotionState::Idle);
    s.move_rel(100.0).unwrap();
    let p = s.wait_settled(SETTLE).unwrap();
    assert!((p - (here + 100.0)).abs() < 1.5, "{p} vs {here}+100");
}

/// Feed hold (`!`, as the controller's button) mid-move, then the driver's `resume` (cycle
/// start `~`) and the move issued again, as the engine does after a pause: the axis goes on
/// to the held target, the second move a no-op.
#[test]
fn resume_after_a_feed_hold_goes_on_to_the_held_target() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    s.move_abs(4_000.0).unwrap();
    // status() answers from the last report, renewed at the poll budget: watch for 5 s.
    let watch = |s: &mut GrblStage, f: &dyn Fn(&StageStatus) -> bool| {
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(5) {
            let st = s.status().unwrap();
            if f(&st) {
                return Some(st.position_um);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        None
    };
    std::thread::sleep(Duration::from_millis(60));
    // Someone presses the controller's feed-hold button, the axis under way.
    r.sim.faults().update(|f| f.feed_hold = true);
    let held = watch(&mut s, &|st| st.state == MotionState::Holding).expect("the controller holds");
    assert!(held > 200.0 && held < 3_900.0, "held at {held}");
    s.resume().unwrap();
    s.move_abs(4_000.0).unwrap();
    let p = s.wait_settled(SETTLE).unwrap();
    assert!((p - 4_000.0).abs() < 1.5, "{p}");
    let t = r.axis.position_at(Instant::now());
    assert!((t - 4_000.0).abs() < TRUE_POSITION_TOL_UM, "{t}");
    // Nothing held: resume is harmless.
    s.resume().unwrap();
    assert_eq!(s.status().unwrap().state, MotionState::Idle);
}

#[test]
fn home_sets_the_origin() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    s.move_abs(1_000.0).unwrap();
    s.wait_settled(SETTLE).unwrap();
    s.home().unwrap();
    assert_eq!(s.position_um().unwrap(), 0.0);
    assert!(r.true_um().abs() < 1e-9);
}

#[test]
fn a_controller_locked_at_boot_follows_the_alarm_policy() {
    let locked = GrblSimOptions {
        alarm_on_boot: true,
        ..GrblSimOptions::default()
    };
    // fail: the move is refused with the alarm, and nothing moves.
    let r = rig_with(locked.clone());
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    assert_eq!(s.status().unwrap().state, MotionState::Alarm);
    let e = s.move_rel(50.0).unwrap_err();
    assert!(matches!(e, HwError::Alarm { .. }), "{e}");
    assert!(!r.axis.is_moving(Instant::now()));
    // home clears it.
    s.home().unwrap();
    assert_eq!(step(&mut s, 50.0, SETTLE).unwrap(), 50.0);

    // unlock: `$X` then the move.
    let r = rig_with(locked.clone());
    let mut opts = r.opts.clone();
    opts.on_alarm = OnAlarm::Unlock;
    let mut s = GrblStage::connect("axis", opts).unwrap();
    assert_eq!(step(&mut s, 50.0, SETTLE).unwrap(), 50.0);

    // home_on_connect: ready at once.
    let r = rig_with(locked);
    let mut opts = r.opts.clone();
    opts.home_on_connect = true;
    let mut s = GrblStage::connect("axis", opts).unwrap();
    assert_eq!(s.status().unwrap().state, MotionState::Idle);
}

#[test]
fn soft_limits_and_max_step_are_refused_before_anything_is_sent() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    let e = s.move_abs(25_000.0).unwrap_err();
    assert!(matches!(e, HwError::Limit { .. }), "{e}");
    let e = s.move_rel(5_001.0).unwrap_err();
    assert!(e.to_string().contains("maximum step"), "{e}");
    let e = s.move_rel(-1_500.0).unwrap_err();
    assert!(e.to_string().contains("soft travel limits"), "{e}");
    assert!(!r.axis.is_moving(Instant::now()));
    assert_eq!(s.position_um().unwrap(), 0.0);
}

#[test]
fn controller_errors_are_typed_with_grbl_text() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    match s.send_line("G20").unwrap_err() {
        HwError::Controller { code, message, .. } => {
            assert_eq!(code, 20);
            assert!(message.contains("Unsupported command"), "{message}");
        }
        e => panic!("expected a controller error, got {e}"),
    }
    // A line without a feed rate: GRBL's error 22.
    let e = s.send_line("G1 X1").unwrap_err();
    assert!(matches!(e, HwError::Controller { code: 22, .. }), "{e}");
    // The driver is still in step afterwards.
    assert_eq!(step(&mut s, 50.0, SETTLE).unwrap(), 50.0);
}

/// The move in progress on the emulated axis: its start and planned profile (model time).
fn planned_move(r: &Rig) -> (Instant, Profile) {
    r.axis
        .current_move()
        .expect("the driver's move is in progress")
}

#[test]
fn the_drivers_feed_rate_is_the_speed_the_axis_moves_at() {
    let r = rig();
    let mut opts = r.opts.clone();
    // 2 mm/s: sent as F120.0.
    opts.feed_um_s = 2_000.0;
    let mut s = GrblStage::connect("axis", opts).unwrap();
    s.move_rel(1_000.0).unwrap();
    let (start, slow) = planned_move(&r);
    assert!((slow.peak_speed_um_s() - 2_000.0).abs() < 1e-6);
    // 1 mm at 2 mm/s: ~0.5 s (4 ms ramps at 0.5 m/s²), not the 0.09 s of top speed.
    assert!(
        (slow.duration_s() - 0.504).abs() < 0.01,
        "{}",
        slow.duration_s()
    );
    // A quarter of a second in (model time): half way, 4 µm of ramp + 246 ms at 2 mm/s.
    let at_250ms = r.axis.position_at(start + Duration::from_millis(250));
    assert!((at_250ms - 496.0).abs() < 0.5, "{at_250ms}");
    let p = s.wait_settled(SETTLE).unwrap();
    assert_eq!(p, 1_000.0);
    assert!((r.true_um() - 1_000.0).abs() < TRUE_POSITION_TOL_UM);

    // The same move with a feed above the axis' 20 mm/s: GRBL clamps it to its max rate.
    drop(s);
    let mut opts = r.opts.clone();
    opts.feed_um_s = 100_000.0;
    let mut s = GrblStage::connect("axis", opts).unwrap();
    s.move_abs(0.0).unwrap();
    let (start, fast) = planned_move(&r);
    assert_eq!(fast.peak_speed_um_s(), 20_000.0);
    assert!(fast.duration_s() < slow.duration_s() / 4.0);
    // 50 ms in (model time) it has covered 400 µm of ramp + 10 ms at 20 mm/s; the 2 mm/s
    // move had covered 4 µm of ramp + 46 ms at 2 mm/s.
    let covered = fast.from_um - r.axis.position_at(start + Duration::from_millis(50));
    let slow_covered = slow.position_after(0.05) - slow.from_um;
    assert!((covered - 600.0).abs() < 0.5, "{covered}");
    assert!((slow_covered - 96.0).abs() < 0.5, "{slow_covered}");
    s.wait_settled(SETTLE).unwrap();
}

#[test]
fn a_g1_without_a_feed_rate_is_refused_with_grbl_error_22() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    let e = s.send_line("G90 G1 X2").unwrap_err();
    match &e {
        HwError::Controller { code, message, .. } => {
            assert_eq!(*code, 22);
            assert!(message.contains("Undefined feed rate"), "{message}");
        }
        _ => panic!("expected GRBL error 22, got {e}"),
    }
    // What a user reads: the device, the code and GRBL's text.
    let text = e.to_string();
    assert!(
        text.starts_with("axis: error 22: Undefined feed rate"),
        "{text}"
    );
    assert!(!r.axis.is_moving(Instant::now()));
    assert_eq!(s.position_um().unwrap(), 0.0);
    // G0 needs no feed and moves at the max rate.
    s.send_line("G90 G0 X1").unwrap();
    assert_eq!(planned_move(&r).1.peak_speed_um_s(), 20_000.0);
    assert_eq!(s.wait_settled(SETTLE).unwrap(), 1_000.0);
    // The driver's own moves carry F, so they work and set the modal feed...
    assert_eq!(step(&mut s, 50.0, SETTLE).unwrap(), 1_050.0);
    // ...which a bare G1 then uses: the default 10 mm/s.
    s.send_line("G90 G1 X3").unwrap();
    assert!((planned_move(&r).1.peak_speed_um_s() - 10_000.0).abs() < 1e-6);
    assert_eq!(s.wait_settled(SETTLE).unwrap(), 3_000.0);
}

#[test]
fn a_move_into_the_hard_limit_raises_alarm_1() {
    let r = rig();
    let mut opts = r.opts.clone();
    // Soft limits wider than the machine: the hard limit (-5 mm) is what stops it.
    opts.limits = TravelLimits::new(-10_000.0, 20_000.0, 10_000.0).unwrap();
    let mut s = GrblStage::connect("axis", opts).unwrap();
    s.move_abs(-6_000.0).unwrap();
    match s.wait_settled(SETTLE).unwrap_err() {
        HwError::Alarm { code, message, .. } => {
            assert_eq!(code, 1);
            assert!(message.starts_with("Hard limit"), "{message}");
        }
        e => panic!("expected ALARM:1, got {e}"),
    }
    assert_eq!(s.alarm(), Some(GrblAlarm::HardLimit));
}

#[test]
fn fault_alarm_mid_move_then_recovery_by_policy() {
    let r = rig();
    let mut opts = r.opts.clone();
    opts.on_alarm = OnAlarm::Unlock;
    let mut s = GrblStage::connect("axis", opts).unwrap();
    r.sim.faults().update(|f| f.alarm_mid_move = true);
    s.move_rel(4_000.0).unwrap();
    let e = s.wait_settled(SETTLE).unwrap_err();
    assert!(matches!(e, HwError::Alarm { code: 1, .. }), "{e}");
    let stopped = r.true_um();
    assert!(stopped > 100.0 && stopped < 3_900.0, "stopped at {stopped}");
    // unlock policy: soft reset (GRBL demands it after ALARM:1), $X, move on.
    s.move_rel(100.0).unwrap();
    let p = s.wait_settled(SETTLE).unwrap();
    assert!((p - stopped - 100.0).abs() < 5.0, "{p} vs {stopped}+100");
}

#[test]
fn fault_alarm_mid_move_with_fail_policy_refuses_until_homed() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    r.sim.faults().update(|f| f.alarm_mid_move = true);
    s.move_rel(4_000.0).unwrap();
    assert!(matches!(
        s.wait_settled(SETTLE),
        Err(HwError::Alarm { code: 1, .. })
    ));
    assert!(matches!(
        s.move_rel(50.0),
        Err(HwError::Alarm { code: 1, .. })
    ));
    s.home().unwrap();
    assert_eq!(step(&mut s, 50.0, SETTLE).unwrap(), 50.0);
}

#[test]
fn fault_no_reply_times_out_then_the_driver_resyncs() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    r.sim.faults().update(|f| f.drop_replies = 1);
    let t = Instant::now();
    let e = s.move_rel(50.0).unwrap_err();
    match &e {
        HwError::Timeout {
            timeout_ms,
            waiting_for,
            ..
        } => {
            assert_eq!(*timeout_ms, 200);
            assert!(waiting_for.contains("G91 G1"), "{waiting_for}");
        }
        _ => panic!("expected a timeout, got {e}"),
    }
    assert!(t.elapsed() < Duration::from_millis(600));
    // The line was executed, only its `ok` was lost: the next sync still works.
    let p = s.wait_settled(SETTLE).unwrap();
    assert_eq!(p, 50.0);
    assert_eq!(step(&mut s, 50.0, SETTLE).unwrap(), 100.0);
}

#[test]
fn fault_late_reply_is_not_taken_for_the_next_one() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    // Later than the 200 ms reply deadline: a timeout, then the stale `ok` must be drained
    // rather than answer the next command.
    r.sim.faults().update(|f| {
        f.late_replies = 1;
        f.late_by = Duration::from_millis(250);
    });
    assert!(matches!(s.move_rel(50.0), Err(HwError::Timeout { .. })));
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(s.wait_settled(SETTLE).unwrap(), 50.0);
    // Late but within the deadline: just slow.
    r.sim.faults().update(|f| {
        f.late_replies = 1;
        f.late_by = Duration::from_millis(50);
    });
    assert_eq!(step(&mut s, 50.0, SETTLE).unwrap(), 100.0);
}

#[test]
fn a_mangled_status_report_is_asked_for_again() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    let polls = s.polls();
    r.sim.faults().update(|f| f.mangle_reports = 1);
    let t0 = Instant::now();
    assert_eq!(s.report().unwrap().state, GrblState::Idle);
    // The second `?` comes at once, well within the reply deadline.
    assert!(
        t0.elapsed() < Duration::from_millis(500),
        "{:?}",
        t0.elapsed()
    );
    assert_eq!(s.polls() - polls, 2);
    assert_eq!(s.garbage_lines(), 1);
}

#[test]
fn fault_garbage_lines_are_skipped_and_counted() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    r.sim.faults().update(|f| f.garbage_replies = 4);
    assert_eq!(step(&mut s, 50.0, SETTLE).unwrap(), 50.0);
    assert!(s.garbage_lines() >= 3, "counted {}", s.garbage_lines());
}

#[test]
fn fault_port_gone_is_reported_then_reopened_on_next_use() {
    let r = rig();
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    s.move_rel(50.0).unwrap();
    s.wait_settled(SETTLE).unwrap();
    unplug(r.sim.faults());
    let e = s.report().unwrap_err();
    assert!(matches!(e, HwError::PortGone { .. }), "{e}");
    assert!(!s.is_connected());
    // Still gone: reopening fails cleanly.
    assert!(matches!(s.position_um(), Err(HwError::PortGone { .. })));
    replug(r.sim.faults());
    // Lazy reopen: banner again, position kept by the controller.
    let p = s.position_um().unwrap();
    assert!(s.is_connected());
    assert_eq!(p, 50.0);
    assert_eq!(step(&mut s, 50.0, SETTLE).unwrap(), 100.0);
}

/// Time per 50 µm step through the full GRBL sync (move, G4 P0, `?`), with the default sim
/// axis (20 mm/s, 0.5 m/s²). A study, not a timed test: `cargo test --test suite grbl_driver:: --
/// --ignored --nocapture`; the figure is in docs/stages.md.
#[test]
#[ignore]
fn study_time_per_50um_step() {
    let r = rig();
    // The emulator's budget, as `rigd --sim` polls it; at the default 5 Hz back-to-back
    // steps would wait for the budget (200 ms a step).
    let mut opts = r.opts.clone();
    opts.status_poll_hz = rigd::hw::grbl::EMULATOR_POLL_HZ;
    let mut s = GrblStage::connect("axis", opts).unwrap();
    let n = 50;
    let per = time_per_step(&mut s, 50.0, n, SETTLE);
    let motion = Duration::from_secs_f64(2.0 * (50.0f64 / 500_000.0).sqrt());
    println!(
        "GRBL: {per:?} per 50 µm step ({motion:?} of it is motion), {n} steps, final {} µm",
        s.position_um().unwrap()
    );
}

/// `unlock()` is `$X` (after the soft reset GRBL requires after ALARM:1), confirmed by a
/// report out of alarm: on a boot lock and after a hard-limit alarm mid-move.
#[test]
fn unlock_clears_a_boot_lock_and_an_alarm_mid_move() {
    let r = rig_with(GrblSimOptions {
        alarm_on_boot: true,
        ..GrblSimOptions::default()
    });
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    assert_eq!(s.status().unwrap().state, MotionState::Alarm);
    s.unlock().unwrap();
    assert_eq!(s.status().unwrap().state, MotionState::Idle);
    r.sim.faults().update(|f| f.alarm_mid_move = true);
    s.move_rel(4_000.0).unwrap();
    let e = s.wait_settled(SETTLE).unwrap_err();
    assert!(matches!(e, HwError::Alarm { code: 1, .. }), "{e}");
    assert!(matches!(s.move_rel(10.0), Err(HwError::Alarm { .. })));
    s.unlock().unwrap();
    assert_eq!(s.status().unwrap().state, MotionState::Idle);
    let at = s.position_um().unwrap();
    assert!(at > 0.0 && at < 4_000.0, "stopped short: {at}");
    let p = step(&mut s, 50.0, SETTLE).unwrap();
    assert!(
        (p - at - 50.0).abs() < TRUE_POSITION_TOL_UM,
        "{p} after {at}"
    );
}
