//! Someone presses feed hold on the GRBL controller mid-job: the runner sees the stage
//! holding while it waits for the move and fails the step at once (not after the 30 s move
//! deadline), naming the stage, the hold and where it stopped; the stage is left stopped.
//! The axis is rigd's GRBL driver over a real pseudo-terminal to the GRBL emulator.

use rigd::cli::client::Client;
use rigd::config::Config;
use rigd::daemon::hwrig::rig_from_config;
use rigd::daemon::protocol::{EventBody, JobSpec, Request};
use rigd::daemon::server::Background;
use rigd::daemon::session::{Session, SessionState};
use rigd::daemon::DaemonSettings;
use rigd::hw::grbl::{GrblOptions, GrblStage};
use rigd::hw::limits::TravelLimits;
use rigd::hw::{HwError, Stage, StageStatus};
use rigd::sim::grbl::{GrblSim, GrblSimOptions};
use rigd::sim::motion::{Axis, AxisParams};
use std::sync::Arc;
use std::time::{Duration, Instant};

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

/// A camera from the config's sim section; the axis is replaced by the GRBL one.
const CAMERA: &str = r#"
[axis]
driver = "sim"
soft_min_um = 0.0
soft_max_um = 100000.0
max_step_um = 100000.0
[camera]
driver = "sim"
[camera.sim]
width = 48
height = 32
supersample = 2
frame_period_ms = 2.0
exposure_ms = 1.0
"#;

#[test]
fn a_feed_hold_mid_move_fails_the_job_at_once_naming_the_hold_and_position() {
    let axis = Arc::new(Axis::new(AxisParams {
        max_speed_um_s: 50_000.0,
        accel_um_s2: 2_000_000.0,
        position_error_rms_um: 0.0,
        ..AxisParams::default()
    }));
    let grbl = GrblSim::spawn(Arc::clone(&axis), GrblSimOptions::default(), None).unwrap();
    let mut opts = GrblOptions::new(
        grbl.path().to_str().unwrap(),
        TravelLimits::new(0.0, 100_000.0, 100_000.0).unwrap(),
    );
    // The emulator moves G1 at the F word: feed at the axis' top speed, as a rig's config would.
    opts.feed_um_s = 50_000.0;
    let grbl_stage = GrblStage::connect("axis", opts).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::from_toml_str(CAMERA, &dir.path().join("rig.toml")).unwrap();
    let mut rig = rig_from_config(&cfg).unwrap();
    rig.axis = Box::new(HoldOnMove {
        inner: grbl_stage,
        hold_on: 3,
        moves: 0,
    });
    let data = dir.path().join("data");
    let settings = DaemonSettings {
        socket: dir.path().join("rigd.sock"),
        group: None,
        data_root: data.clone(),
    };
    let bg = Background::start(settings, rig).unwrap();
    let mut c = Client::connect(&bg.socket).unwrap();
    c.request(&Request::Subscribe { job_id: None }).unwrap();
    // Frames at 1000, 1100, then a 40 mm move to 41100 that is held on its way.
    let job = JobSpec {
        start_um: Some(1_000.0),
        step_um: Some(100.0),
        steps: Some(2),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };
    let first = c.request(&Request::Submit { job }).unwrap()["job_id"]
        .as_u64()
        .unwrap();
    let job = JobSpec {
        start_um: Some(41_100.0),
        steps: Some(1),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };
    let id = c.request(&Request::Submit { job }).unwrap()["job_id"]
        .as_u64()
        .unwrap();
    let mut session = None;
    let reason = loop {
        let e = c.next_event().unwrap();
        if e.job_id == first && e.body.is_terminal() {
            assert!(matches!(e.body, EventBody::Finished { .. }), "{:?}", e.body);
        }
        if e.job_id != id {
            continue;
        }
        match e.body {
            EventBody::Started { session: s, .. } => session = Some(s),
            EventBody::Failed { reason, .. } => break reason,
            b if b.is_terminal() => panic!("the held job ended otherwise: {b:?}"),
            _ => {}
        }
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
    let s = Session::open(&data.join(session.unwrap())).unwrap();
    assert_eq!(s.manifest.state, SessionState::Failed);
    assert_eq!(s.manifest.reason.as_deref(), Some(reason.as_str()));
    assert!(s.steps.is_empty(), "no frame of the held step");
}
