//! Someone presses feed hold on the GRBL controller mid-job. With `[daemon] on_feed_hold =
//! "pause"` (the default) the job pauses where the stage held (`paused`, cause `feed_hold`),
//! and `resume` sends cycle start, re-issues the held move and goes on: the frame is taken
//! at its planned position. With `"fail"` the runner fails the step at once (not after the
//! 30 s move deadline), naming the stage, the hold and where it stopped; the stage is left
//! stopped. The axis is rigd's GRBL driver over a real pseudo-terminal to the GRBL emulator.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{
    end_of, events_until_end, fast_grbl, rig_from_toml, submit, Daemon, SIM_RIG_SMALL,
};
use rigd::acquisition::{HoldPolicy, JobSpec};
use rigd::daemon::protocol::{EventBody, Request};
use rigd::hw::grbl::{GrblOptions, GrblStage};
use rigd::hw::limits::TravelLimits;
use rigd::hw::{HwError, Stage, StageStatus};
use rigd::session::SessionState;
use std::time::{Duration, Instant};

/// The GRBL driver, with a person at the controller who presses feed hold (`!`) right
/// after the controller accepted move number `hold_on`.
struct HoldOnMove {
    inner: GrblStage,
    faults: rigd_sim::serve::Faults,
    hold_on: u32,
    moves: u32,
}

impl Stage for HoldOnMove {
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn move_rel(&mut self, delta_um: f64) -> Result<(), HwError> {
        self.inner.move_rel(delta_um)
    }
    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError> {
        self.inner.move_abs(target_um)?;
        self.moves += 1;
        if self.moves == self.hold_on {
            // Well into the move: the driver's feed is the axis' 50 mm/s, so the 40 mm move
            // lasts 0.8 s and this lands ~4-5 mm in...
            std::thread::sleep(Duration::from_millis(100));
            // ...feed hold, pressed on the controller.
            self.faults.update(|f| f.feed_hold = true);
        }
        Ok(())
    }
    fn wait_settled(&mut self, timeout: Duration) -> Result<f64, HwError> {
        self.inner.wait_settled(timeout)
    }
    fn position_um(&mut self) -> Result<f64, HwError> {
        self.inner.position_um()
    }
    fn stop(&mut self) -> Result<(), HwError> {
        self.inner.stop()
    }
    fn home(&mut self) -> Result<(), HwError> {
        self.inner.home()
    }
    fn status(&mut self) -> Result<StageStatus, HwError> {
        self.inner.status()
    }
    fn resume(&mut self) -> Result<(), HwError> {
        self.inner.resume()
    }
}

/// A daemon whose axis is held on its third move (a 40 mm move from 1100 to 41100 µm),
/// with `on_feed_hold` as given; returns it, the emulated axis and the emulator (whose pty
/// is the driver's port: kept as long as the daemon).
fn held_daemon(
    policy: HoldPolicy,
) -> (
    Daemon,
    std::sync::Arc<rigd_sim::motion::Axis>,
    rigd_sim::grbl::GrblSim,
) {
    let (axis, grbl) = fast_grbl();
    let mut opts = GrblOptions::new(
        grbl.path().to_str().unwrap(),
        TravelLimits::new(0.0, 100_000.0, 100_000.0).unwrap(),
    );
    // The emulator moves G1 at the F word: feed at the axis' top speed, as a rig's config would.
    opts.feed_um_s = 50_000.0;
    let grbl_stage = GrblStage::connect("axis", opts).unwrap();
    // A camera from the config's sim section; the axis is replaced by the GRBL one.
    let dir = tempfile::tempdir().unwrap();
    let mut rig = rig_from_toml(dir.path(), SIM_RIG_SMALL);
    rig.axis = Box::new(HoldOnMove {
        inner: grbl_stage,
        faults: grbl.faults().clone(),
        hold_on: 3,
        moves: 0,
    });
    let d = Daemon::start_with(rig, dir, |s| s.on_feed_hold = policy);
    (d, axis, grbl)
}

/// Frames at 1000 and 1100 (job one), then one at 41100 (job two) whose move is held.
fn submit_both(c: &mut rigd::cli::client::Client) -> (u64, u64) {
    let job = JobSpec {
        start_um: Some(1_000.0),
        step_um: Some(100.0),
        steps: Some(2),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };
    let first = submit(c, job);
    let job = JobSpec {
        start_um: Some(41_100.0),
        steps: Some(1),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };
    (first, submit(c, job))
}

#[test]
fn a_feed_hold_mid_move_pauses_the_job_and_resume_takes_the_frame_where_planned() {
    let (d, axis, _grbl) = held_daemon(HoldPolicy::Pause);
    let mut c = d.subscribed();
    let (first, id) = submit_both(&mut c);
    let end = end_of(&mut c, first);
    assert!(matches!(end, EventBody::Finished { .. }), "{end:?}");
    let mut ev = Vec::new();
    let (next_index, at_um, reason) = loop {
        let e = c.next_event().unwrap();
        if e.job_id != id {
            continue;
        }
        ev.push(e.body.clone());
        match e.body {
            EventBody::Paused {
                next_index,
                at_um,
                cause,
                reason,
            } => {
                assert_eq!(cause, "feed_hold");
                break (next_index, at_um.unwrap(), reason);
            }
            b => assert!(!b.is_terminal(), "ended before pausing: {ev:?}"),
        }
    };
    assert_eq!(next_index, 0);
    assert!(
        at_um > 1_500.0 && at_um < 41_100.0,
        "held mid-move: {reason}"
    );
    assert!(
        reason.starts_with("axis: feed hold at ") && reason.contains("during the move to 41100 µm"),
        "{reason}"
    );
    // Held where it paused, and the job says so.
    assert!(!axis.is_moving(Instant::now()));
    assert!((axis.position_at(Instant::now()) - at_um).abs() < 1.0);
    let mut other = d.client();
    let st = other
        .request(&Request::Status { job_id: Some(id) })
        .unwrap();
    assert_eq!(st["state"], "paused", "{st}");
    other.request(&Request::Resume { job_id: id }).unwrap();
    ev.extend(events_until_end(&mut c, id));
    assert!(
        matches!(ev.last(), Some(EventBody::Finished { .. })),
        "{ev:?}"
    );
    assert!(ev.contains(&EventBody::Resumed { next_index: 0 }), "{ev:?}");
    let s = d.session(&ev);
    assert_eq!(s.manifest.state, SessionState::Finished);
    assert_eq!(s.steps.len(), 1);
    assert_eq!(s.steps[0].position_um, 41_100.0);
    assert!(
        (s.steps[0].axis_um - 41_100.0).abs() < 1.0,
        "{:?}",
        s.steps[0]
    );
}

#[test]
fn a_feed_hold_mid_move_fails_the_job_at_once_naming_the_hold_and_position() {
    let (d, axis, _grbl) = held_daemon(HoldPolicy::Fail);
    let mut c = d.subscribed();
    let (first, id) = submit_both(&mut c);
    let end = end_of(&mut c, first);
    assert!(matches!(end, EventBody::Finished { .. }), "{end:?}");
    let ev = events_until_end(&mut c, id);
    let Some(EventBody::Failed { reason, .. }) = ev.last() else {
        panic!("the held job ended otherwise: {ev:?}")
    };
    // "axis: feed hold at 5482.0 µm during the move to 41100 µm (…); axis stopped at …"
    let prefix = "axis: feed hold at ";
    assert!(reason.starts_with(prefix), "{reason}");
    let held_um: f64 = reason[prefix.len()..]
        .split(" µm")
        .next()
        .unwrap()
        .parse()
        .unwrap_or_else(|e| panic!("{reason}: {e}"));
    assert!(
        held_um > 1_500.0 && held_um < 41_100.0,
        "held mid-move: {reason}"
    );
    assert!(reason.contains("during the move to 41100 µm"), "{reason}");
    assert!(reason.contains("; axis stopped at"), "{reason}");
    // The controller is stopped where it held, not moving, and not resumed to the target.
    let true_um = axis.position_at(Instant::now());
    assert!(!axis.is_moving(Instant::now()));
    assert!((true_um - held_um).abs() < 1.0, "{true_um} vs {reason}");
    let s = d.session(&ev);
    assert_eq!(s.manifest.state, SessionState::Failed);
    assert_eq!(s.manifest.reason.as_deref(), Some(reason.as_str()));
    assert!(s.steps.is_empty(), "no frame of the held step");
}
