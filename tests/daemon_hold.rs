//! Someone presses feed hold on the GRBL controller mid-job: the runner sees the stage
//! holding while it waits for the move and fails the step at once (not after the 30 s move
//! deadline), naming the stage, the hold and where it stopped; the stage is left stopped.
//! The axis is rigd's GRBL driver over a real pseudo-terminal to the GRBL emulator.

#![cfg(feature = "sim")] // the simulated rig (default feature)

mod support;

use rigd::acquisition::JobSpec;
use rigd::daemon::protocol::EventBody;
use rigd::daemon::session::SessionState;
use rigd::hw::grbl::{GrblOptions, GrblStage};
use rigd::hw::limits::TravelLimits;
use rigd::hw::{HwError, Stage, StageStatus};
use std::time::{Duration, Instant};
use support::daemon::{
    end_of, events_until_end, fast_grbl, rig_from_toml, submit, Daemon, SIM_RIG_SMALL,
};

/// The GRBL driver, with a person at the controller who presses feed hold (`!`) right
/// after the controller accepted move number `hold_on`.
struct HoldOnMove {
    inner: GrblStage,
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
            // ...feed hold: `!` is a realtime byte, the controller holds whatever line it
            // comes in.
            self.inner.send_line("!")?;
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
}

#[test]
fn a_feed_hold_mid_move_fails_the_job_at_once_naming_the_hold_and_position() {
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
        hold_on: 3,
        moves: 0,
    });
    let d = Daemon::start_in(rig, dir);
    let mut c = d.subscribed();
    // Frames at 1000, 1100, then a 40 mm move to 41100 that is held on its way.
    let job = JobSpec {
        start_um: Some(1_000.0),
        step_um: Some(100.0),
        steps: Some(2),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };
    let first = submit(&mut c, job);
    let job = JobSpec {
        start_um: Some(41_100.0),
        steps: Some(1),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };
    let id = submit(&mut c, job);
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
