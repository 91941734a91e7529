//! Motion limits and drivers: the attacks on the drivers' limits, reproduced
//! over real pseudo-terminals against the GCS and GRBL emulators (their parsers are sim/'s
//! own), each asserting what the stage truly did.
//!
//! Every `rigctl hw` call builds a fresh driver: these tests do too where the attack needs a
//! driver that has no record of the last target.

use rigd::hw::gcs::{GcsOptions, GcsStage};
use rigd::hw::grbl::{GrblOptions, GrblStage};
use rigd::hw::limits::TravelLimits;
use rigd::hw::{HwError, Stage};
use rigd::sim::gcs::{GcsSim, GcsSimOptions};
use rigd::sim::grbl::{GrblSim, GrblSimOptions};
use rigd::sim::motion::AxisParams;
use std::time::{Duration, Instant};

const SETTLE: Duration = Duration::from_secs(3);

type GcsRig = crate::support::emulated::Rig<GcsSim, GcsOptions>;
type GrblRig = crate::support::emulated::Rig<GrblSim, GrblOptions>;

/// A slow 100 µm flexure (40 µm/s: 88 µm take ~2.2 s) positioning to `error_rms_um`.
fn gcs(limits: TravelLimits, error_rms_um: f64) -> GcsRig {
    let params = AxisParams {
        max_speed_um_s: 40.0,
        accel_um_s2: 10_000.0,
        position_error_rms_um: error_rms_um,
        hard_min_um: 0.0,
        hard_max_um: 100.0,
        seed: 11,
    };
    let spawn = |axis, link: &_| GcsSim::spawn(axis, GcsSimOptions::default(), Some(link));
    GcsRig::spawn(params, "piezo", spawn, |port| {
        let mut o = GcsOptions::new(port, limits);
        o.reply_timeout_ms = 300;
        o
    })
}

fn fast_gcs(limits: TravelLimits, error_rms_um: f64) -> GcsRig {
    let params = AxisParams {
        max_speed_um_s: 2_000.0,
        accel_um_s2: 200_000.0,
        position_error_rms_um: error_rms_um,
        hard_min_um: 0.0,
        hard_max_um: 100.0,
        seed: 5,
    };
    let spawn = |axis, link: &_| GcsSim::spawn(axis, GcsSimOptions::default(), Some(link));
    GcsRig::spawn(params, "piezo", spawn, |port| {
        let mut o = GcsOptions::new(port, limits);
        o.reply_timeout_ms = 300;
        o
    })
}

fn lim(min_um: f64, max_um: f64, max_step_um: f64) -> TravelLimits {
    TravelLimits::new(min_um, max_um, max_step_um).unwrap()
}

/// The first GCS attack: soft limits 0–90 µm, a `move-abs 88` that times out while still
/// moving, then (a new `rigctl hw` call) `move-rel 4`. The step is checked against `MOV?`
/// (88 + 4 = 92 > 90) and refused; the piezo ends at 88. (Checked against `POS?`, ~6.7 + 4,
/// `MVR 1 4` would be sent and the piezo would end at 92 µm.)
#[test]
fn a_relative_step_after_a_timed_out_move_is_checked_against_the_target() {
    let r = gcs(lim(0.0, 90.0, 90.0), 0.0);
    let mut first = GcsStage::connect("piezo", r.opts.clone()).unwrap();
    first.move_abs(88.0).unwrap();
    let e = first.wait_settled(Duration::from_millis(150)).unwrap_err();
    assert!(matches!(e, HwError::NotSettled { .. }), "{e}");
    drop(first);
    let reading = r.true_um();
    assert!(reading < 30.0, "still on its way: {reading} µm");
    let mut second = GcsStage::connect("piezo", r.opts.clone()).unwrap();
    let e = second.move_rel(4.0).unwrap_err();
    match &e {
        HwError::Limit { target_um, .. } => assert!((target_um - 92.0).abs() < 1e-9, "{e}"),
        _ => panic!("expected a limit refusal, got {e}"),
    }
    assert!(e.to_string().contains("soft travel limits [0, 90]"), "{e}");
    // The refused step sent nothing: the piezo still ends at 88 µm (±1 nm: no error).
    let at = second.wait_settled(SETTLE).unwrap();
    assert!((at - 88.0).abs() < 1e-3, "ended at {at} µm");
    assert!((r.true_um() - 88.0).abs() < 1e-3);
}

/// The second GCS attack: `move-abs 50` then (a new call) `move-rel 50` on a 0–100 travel:
/// 50 + 50 = 100 from the target, accepted, ends at 100 µm. (Checked against `POS?`, 50.0004
/// with the loop's error, it would be refused as "move to 100.0004 µm".) The tries include
/// ones where the sensor read above 50.
#[test]
fn a_legal_relative_step_is_not_refused_for_the_sensor_noise() {
    // 0.02 µm RMS positioning error: POS? is off the target by about that much (seeded).
    let r = fast_gcs(lim(0.0, 100.0, 100.0), 0.02);
    let mut read_high = 0;
    for _ in 0..6 {
        let mut s = GcsStage::connect("piezo", r.opts.clone()).unwrap();
        s.move_abs(50.0).unwrap();
        if s.wait_settled(SETTLE).unwrap() > 50.0 {
            read_high += 1;
        }
        drop(s);
        let mut s = GcsStage::connect("piezo", r.opts.clone()).unwrap();
        s.move_rel(50.0).unwrap();
        let at = s.wait_settled(SETTLE).unwrap();
        assert!((at - 100.0).abs() < 0.1, "{at}"); // 5 sigma of the 0.02 µm error
    }
    assert!(read_high > 0, "no try had the sensor above the target");
}

/// `max_step_um` is the distance of any move from the last target, absolute moves too.
/// `move-abs 60` with a 50 µm max step is refused: absolute moves are not bounded by the
/// travel alone.
#[test]
fn an_absolute_move_longer_than_max_step_is_refused_gcs() {
    let r = fast_gcs(lim(0.0, 100.0, 50.0), 0.0);
    let mut s = GcsStage::connect("piezo", r.opts.clone()).unwrap();
    let e = s.move_abs(60.0).unwrap_err();
    assert_eq!(
        e.to_string(),
        "piezo: move to 60 µm refused: a move of 60 µm from the last target 0 µm exceeds \
         the maximum step of 50 µm"
    );
    assert!(!r.axis.is_moving(Instant::now()));
    s.move_abs(50.0).unwrap();
    s.wait_settled(SETTLE).unwrap();
    // From 50, 60 is 10 away.
    s.move_abs(60.0).unwrap();
    assert!((s.wait_settled(SETTLE).unwrap() - 60.0).abs() < 1e-3);
}

fn grbl(limits: TravelLimits, speed_um_s: f64) -> GrblRig {
    let params = AxisParams {
        max_speed_um_s: speed_um_s,
        accel_um_s2: 500_000.0,
        position_error_rms_um: 0.0,
        ..AxisParams::default()
    };
    let spawn = |axis, link: &_| GrblSim::spawn(axis, GrblSimOptions::default(), Some(link));
    GrblRig::spawn(params, "grbl", spawn, |port| {
        let mut o = GrblOptions::new(port, limits);
        o.reply_timeout_ms = 300;
        o.feed_um_s = speed_um_s;
        o
    })
}

#[test]
fn an_absolute_move_longer_than_max_step_is_refused_grbl() {
    let r = grbl(lim(0.0, 200_000.0, 5_000.0), 50_000.0);
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    let e = s.move_abs(100_000.0).unwrap_err();
    assert!(
        e.to_string()
            .contains("exceeds the maximum step of 5000 µm"),
        "{e}"
    );
    assert!(!r.axis.is_moving(Instant::now()));
    s.move_abs(5_000.0).unwrap();
    assert!((s.wait_settled(SETTLE).unwrap() - 5_000.0).abs() < 1e-3);
    let e = s.move_abs(10_001.0).unwrap_err();
    assert!(matches!(e, HwError::Limit { .. }), "{e}");
}

/// A settle that runs out while GRBL answers every poll says so (not "no reply within
/// N ms (waiting for reply to \"G4 P0\")"); the move's late `ok` is not taken for the next
/// command's, and no move is planned on top of the unfinished one.
#[test]
fn a_grbl_move_that_outlasts_the_wait_is_not_settled_not_silent() {
    let r = grbl(lim(0.0, 200_000.0, 200_000.0), 5_000.0);
    let mut s = GrblStage::connect("axis", r.opts.clone()).unwrap();
    s.move_abs(2_000.0).unwrap(); // 0.4 s at 5 mm/s
    let e = s.wait_settled(Duration::from_millis(100)).unwrap_err();
    let text = e.to_string();
    assert!(
        matches!(
            e,
            HwError::NotSettled {
                timeout_ms: 100,
                ..
            }
        ),
        "{e}"
    );
    assert!(
        text.contains("still Run") && !text.contains("no reply"),
        "{text}"
    );
    // While it still runs, its target is unknown to the driver: a new move is refused.
    let e = s.move_rel(10.0).unwrap_err();
    assert!(e.to_string().contains("target is unknown"), "{e}");
    std::thread::sleep(Duration::from_millis(500));
    s.move_rel(10.0).unwrap();
    assert!((s.wait_settled(SETTLE).unwrap() - 2_010.0).abs() < 1e-3);
}

#[test]
fn a_gcs_settle_that_runs_out_is_not_settled_not_silent() {
    let r = gcs(lim(0.0, 100.0, 100.0), 0.0);
    let mut s = GcsStage::connect("piezo", r.opts.clone()).unwrap();
    s.move_abs(20.0).unwrap(); // 0.5 s at 40 µm/s
    let e = s.wait_settled(Duration::from_millis(60)).unwrap_err();
    let text = e.to_string();
    assert!(
        text.starts_with("piezo: not settled within 60 ms") && text.contains("ONT? still 0"),
        "{text}"
    );
    assert!((s.wait_settled(SETTLE).unwrap() - 20.0).abs() < 1e-3);
}

/// `home` keeps to `move_timeout_ms`, not a fixed max(reply timeout, 1 s) deadline (with
/// one, a 2.5 s home move would fail at 1 s whatever the config says, and a stuck one at 1 s).
#[test]
fn gcs_home_waits_as_long_as_the_config_says() {
    let r = gcs(lim(0.0, 100.0, 100.0), 0.0);
    let mut opts = r.opts.clone();
    opts.home_um = 80.0; // 2 s away at 40 µm/s
    opts.move_timeout_ms = 200;
    let mut s = GcsStage::connect("piezo", opts.clone()).unwrap();
    let t = Instant::now();
    let e = s.home().unwrap_err();
    assert!(
        matches!(
            e,
            HwError::NotSettled {
                timeout_ms: 200,
                ..
            }
        ),
        "{e}"
    );
    assert!(
        t.elapsed() < Duration::from_millis(900),
        "{:?}",
        t.elapsed()
    );
    drop(s); // the port is opened exclusively
    opts.move_timeout_ms = 5_000;
    let mut s = GcsStage::connect("piezo", opts).unwrap();
    s.home().unwrap();
    assert!((r.true_um() - 80.0).abs() < 1e-3);
}

/// `home_reference`: the reference move FRF, confirmed by FRF?, within `home_timeout_ms`.
#[test]
fn gcs_home_by_reference_move() {
    let r = fast_gcs(lim(0.0, 100.0, 100.0), 0.0);
    let mut s = GcsStage::connect("piezo", r.opts.clone()).unwrap();
    s.move_abs(40.0).unwrap();
    s.wait_settled(SETTLE).unwrap();
    drop(s); // the port is opened exclusively
    let mut opts = r.opts.clone();
    opts.home_reference = true;
    opts.home_um = 99.0; // not used by a reference move
    let mut s = GcsStage::connect("piezo", opts).unwrap();
    s.home().unwrap();
    // The emulator's reference point is 0 µm.
    assert!(r.true_um().abs() < 1e-3, "{}", r.true_um());
}

/// Refusals print numbers short: 1e308 as such, not 309 digits.
#[test]
fn refusals_print_huge_numbers_short() {
    let r = fast_gcs(lim(0.0, 100.0, 100.0), 0.0);
    let mut s = GcsStage::connect("piezo", r.opts.clone()).unwrap();
    let e = s.move_abs(1e308).unwrap_err().to_string();
    assert!(e.contains("1e308") && e.len() < 120, "{e}");
    let e = s.move_rel(-1e300).unwrap_err().to_string();
    assert!(e.contains("-1e300") && e.len() < 120, "{e}");
}

mod jobs {
    //! The same limits for jobs, on a hardware-mode rig (`rigd --config`: rigd's GRBL
    //! driver to the emulator), through the daemon's socket.

    use crate::support::daemon::{
        capture_job, config, events_until_end, submit, subscribe, Daemon,
    };
    use rigd::acquisition::JobSpec;
    use rigd::daemon::protocol::{EventBody, Request};
    use rigd::rig::from_config;
    use rigd::sim::grbl::{GrblSim, GrblSimOptions};
    use rigd::sim::motion::{Axis, AxisParams};
    use std::sync::Arc;
    use std::time::Instant;

    fn rig_text(port: &std::path::Path, extra: &str) -> String {
        format!(
            "[axis]\ndriver = \"grbl\"\nport = \"{}\"\nsoft_min_um = 0.0\nsoft_max_um = 250000.0\n\
             max_step_um = 5000.0\nfeed_um_s = 50000.0\n{extra}\
             [camera]\ndriver = \"sim\"\n[camera.sim]\nwidth = 48\nheight = 32\nsupersample = 2\n\
             frame_period_ms = 2.0\nexposure_ms = 1.0\n",
            port.display()
        )
    }

    fn grbl() -> (Arc<Axis>, GrblSim) {
        let axis = Arc::new(Axis::new(AxisParams {
            max_speed_um_s: 50_000.0,
            accel_um_s2: 2_000_000.0,
            position_error_rms_um: 0.0,
            ..AxisParams::default()
        }));
        let sim = GrblSim::spawn(axis.clone(), GrblSimOptions::default(), None).unwrap();
        (axis, sim)
    }

    /// With max_step_um = 5000 a job of 100 000 µm steps (1000 → 101000 → 201000) is refused
    /// at submit, naming the move and the limit; nothing moves.
    #[test]
    fn a_job_with_steps_over_max_step_is_refused_at_submit() {
        let (axis, sim) = grbl();
        let dir = tempfile::tempdir().unwrap();
        let rig = from_config(&config(dir.path(), &rig_text(&sim.path(), ""))).unwrap();
        let d = Daemon::start_in(rig, dir);
        let mut c = d.client();
        let job = JobSpec {
            start_um: Some(1_000.0),
            ..capture_job(100_000.0, 3, 0)
        };
        let e = c.request(&Request::Submit { job }).unwrap_err().to_string();
        assert!(
            e.contains("the move from 1000 µm to 101000 µm is longer than the axis's max_step_um (5000 µm)"),
            "{e}"
        );
        let huge = JobSpec {
            start_um: Some(1_000.0),
            ..capture_job(1e308, 2, 0)
        };
        let e = c
            .request(&Request::Submit { job: huge })
            .unwrap_err()
            .to_string();
        assert!(e.len() < 300 && e.contains("e308"), "{e}");
        let long_settle = JobSpec {
            settle_ms: 60_001,
            ..capture_job(100.0, 2, 0)
        };
        let e = c
            .request(&Request::Submit { job: long_settle })
            .unwrap_err()
            .to_string();
        assert!(e.contains("`settle_ms` must be at most 60000 ms"), "{e}");
        assert_eq!(axis.position_at(Instant::now()), 0.0);
    }

    /// The move from where the axis rests to the scan's start is a move too: the driver
    /// refuses it (the plan cannot know where the axis is), the job fails naming it, and
    /// the axis never moved.
    #[test]
    fn the_approach_to_a_far_scan_start_is_refused_by_the_driver() {
        let (axis, sim) = grbl();
        let dir = tempfile::tempdir().unwrap();
        let text = rig_text(&sim.path(), "default_start_um = 20000.0\n");
        let rig = from_config(&config(dir.path(), &text)).unwrap();
        let d = Daemon::start_in(rig, dir);
        let mut c = d.client();
        subscribe(&mut c);
        let id = submit(&mut c, capture_job(100.0, 2, 0));
        let ev = events_until_end(&mut c, id);
        let Some(EventBody::Failed { reason, .. }) = ev.last() else {
            panic!("{ev:?}")
        };
        assert!(
            reason.starts_with("axis: move to 20000 µm refused: a move of 20000 µm from the last target 0 µm exceeds the maximum step of 5000 µm"),
            "{reason}"
        );
        assert_eq!(axis.position_at(Instant::now()), 0.0);
        // A refused move is no fault: the rig is ready.
        let hello = c.request(&Request::Hello {}).unwrap();
        assert_eq!(hello["rig_state"]["state"], "ready", "{hello}");
    }

    #[test]
    fn a_config_settle_over_the_bound_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let text = "[axis]\ndriver = \"sim\"\nsoft_min_um = 0.0\nsoft_max_um = 1000.0\n\
                    max_step_um = 100.0\nsettle_ms = 60001\n";
        let e = rigd::config::Config::from_toml_str(text, &dir.path().join("rig.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("axis.settle_ms") && e.contains("60000"), "{e}");
        // Limits typed in the wrong unit by far print short too.
        let text = "[axis]\ndriver = \"sim\"\nsoft_min_um = 1e300\nsoft_max_um = 1e299\n\
                    max_step_um = 100.0\n";
        let e = rigd::config::Config::from_toml_str(text, &dir.path().join("rig.toml"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("soft_max_um (1e299) must be above soft_min_um (1e300)") && e.len() < 200,
            "{e}"
        );
    }
}
