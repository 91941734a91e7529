//! `rigctl reprocess` against cores (docs/performance.md, "Reprocessing sessions"):
//! `cargo bench --bench reprocess_scaling`.
//!
//! Writes N sessions (default 100) of 10 small frames each (300x200, the tests' two-target
//! board, rendered by rigd-sim; a 10-frame scan 154.8 µm apart, recorded at k = 5, fit,
//! image registration) through the daemon's own session writer, then reprocesses all of
//! them with the library call `rigctl reprocess` makes, on 1 and on 2 rayon threads (each
//! run's pipeline shares the pool), with `--k 5` (settings `k5`: result.json, settings.json
//! and the reconstructions written into each session, rows added to an index), and prints
//! sessions per second. `RIGD_REPROCESS_SESSIONS=N` and `RIGD_REPROCESS_THREADS=1,2,4` change
//! the load.

use rigd::acquisition::plan::plan;
use rigd::acquisition::{JobSpec, Processing};
use rigd::offline::reprocess::{reprocess, IndexTarget, Reprocess};
use rigd::offline::Overrides;
use rigd::rig::{RigInfo, RigMode};
use rigd::session::{unix_s, SessionState, SessionWriter, StepRow};
use rigd::sim::render::{SceneRenderer, View};
use rigd::sim::{Board, CameraModel};
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime};

const BOARD: &str = r#"
name = "small"
[defaults]
outer = { kind = "ring", inner_radius_um = 13000.0, outer_radius_um = 17000.0 }
inner = { kind = "disk", radius_um = 6000.0 }
[[targets]]
name = "H"
centre_um = [62000.0, 77000.0]
offset_um = [2000.0, 0.0]
[[targets]]
name = "V"
centre_um = [170000.0, 77000.0]
offset_um = [0.0, 3000.0]
"#;
const FRAMES: u32 = 10;
const STEP_UM: f64 = 154.8;

fn rig(board: &Board, cam: &CameraModel) -> RigInfo {
    RigInfo {
        mode: RigMode::Sim,
        axis_limits_um: [0.0, 250_000.0],
        piezo_limits_um: None,
        axis_max_step_um: None,
        piezo_max_step_um: None,
        axis_settle_ms: None,
        piezo_settle_ms: None,
        default_start_um: 310.0,
        scale_um_per_px: cam.scale_um_per_px,
        axis_dir: [-1.0, 0.0],
        piezo_dir: None,
        frame_size: (cam.width, cam.height),
        response: Default::default(),
        ink_prior: None,
        interferometer: false,
        axis_machine: None,
        board: Some(board.clone()),
        config: serde_json::Value::Null,
        job_defaults: Processing::default(),
        grab_timeout_ms: 5000,
    }
}

/// Write `n` sessions under `root`, each a 10-frame scan of its own noise.
fn write_sessions(root: &Path, n: usize) -> Vec<PathBuf> {
    let board = Board::parse(BOARD, "small.toml").unwrap();
    let cam = CameraModel {
        width: 300,
        height: 200,
        ..CameraModel::default()
    };
    let scene = SceneRenderer::new(board.clone(), cam.clone());
    let info = rig(&board, &cam);
    let job = JobSpec {
        step_um: Some(STEP_UM),
        steps: Some(FRAMES),
        k: Some(5),
        ..JobSpec::default()
    }
    .with_defaults(&Processing::default());
    let p = plan(&job, &info, root, 0).unwrap();
    (0..n)
        .map(|s| {
            let mut w =
                SessionWriter::create(root, s as u64 + 1, &job, &p, &info, (None, None)).unwrap();
            for (i, &pos) in p.runs[0].positions_um.iter().enumerate() {
                let view = View::at([pos, 150.0]);
                let px = scene.expose(&[view], 1.0, (s * 1000 + i) as u64);
                let img = image::RgbImage::from_raw(cam.width, cam.height, px).unwrap();
                let row = StepRow {
                    index: i as u32,
                    position_um: pos,
                    run: 0,
                    case: "scan".into(),
                    repeat: 0,
                    axis_um: pos,
                    interferometer_um: None,
                    t_unix_s: unix_s(SystemTime::now()),
                    sequence: i as u64,
                    move_ms: 0.0,
                    settle_ms: 0.0,
                    grab_ms: 0.0,
                    piezo_commanded_um: None,
                    piezo_um: None,
                };
                w.record(row, &img).unwrap();
            }
            let dir = w.dir().to_path_buf();
            w.close(SessionState::Finished, None, None).unwrap();
            dir
        })
        .collect()
}

fn env_list(name: &str, default: &str) -> Vec<usize> {
    std::env::var(name)
        .unwrap_or_else(|_| default.into())
        .split(',')
        .map(|s| s.trim().parse().expect("a number"))
        .collect()
}

fn main() {
    // `cargo bench` passes `--bench`; a filter argument is ignored (one measurement).
    let n = env_list("RIGD_REPROCESS_SESSIONS", "100")[0];
    let threads = env_list("RIGD_REPROCESS_THREADS", "1,2");
    let root = tempfile::tempdir().unwrap();
    let t = Instant::now();
    let sessions = write_sessions(root.path(), n);
    println!(
        "wrote {n} sessions of {FRAMES} frames (300x200) in {:.1} s",
        t.elapsed().as_secs_f64()
    );
    for &th in &threads {
        let how = Reprocess {
            overrides: Overrides {
                k: Some(5),
                ..Overrides::default()
            },
            board: None,
            calibration: None,
            no_calibration: false,
            threads: th,
            index: IndexTarget::File(root.path().join(format!("index-{th}.sqlite"))),
        };
        let t = Instant::now();
        let done = reprocess(&sessions, &how, &|_| {}).unwrap();
        let s = t.elapsed().as_secs_f64();
        let failed = done.iter().filter(|d| d.outcome.is_err()).count();
        assert_eq!(failed, 0, "{:?}", done.iter().find(|d| d.outcome.is_err()));
        println!(
            "reprocess_scaling/{n}x{FRAMES}/threads={th}: {s:.2} s, {:.1} sessions/s",
            n as f64 / s
        );
    }
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("load average: {}", load.trim());
}
