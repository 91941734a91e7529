//! The live view over the daemon's real socket, on the simulated rig (GRBL emulator on a
//! pty, frame-clock camera) showing a small board: `snap` after the stage moved, `preview`'s
//! rate and its frames during a job, a subscriber that never reads, bad options, the focus
//! figure against the renderer's blur, and `rigctl snap` / `rigctl view`.
//! (Latency and the job's step interval are timed in `benches/preview_latency.rs`.)

#![cfg(feature = "sim")]

use crate::support::daemon::{assert_finished, run_job, Daemon};
use base64::Engine as _;
use rigd::acquisition::JobSpec;
use rigd::cli::client::Client;
use rigd::daemon::live_view::render;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::daemon::protocol::{SnapReply, ViewFrame};
use rigd::rig::{simulated, SimSettings};
use rigd::sim::render::{SceneRenderer, View};
use rigd::sim::CameraModel;
use std::io::{Read, Write};
use std::time::{Duration, SystemTime};

/// 300x200 frames of the small board (targets H and V), every 10 ms.
fn camera() -> CameraModel {
    CameraModel {
        width: 300,
        height: 200,
        supersample: 2,
        frame_period_ms: 10.0,
        exposure_ms: 2.0,
        motion_samples: 2,
        vibration_um: 0.0,
        ..CameraModel::default()
    }
}

fn start() -> Daemon {
    let dir = tempfile::tempdir().unwrap();
    let board = dir.path().join("small.toml");
    std::fs::write(&board, crate::support::SMALL_BOARD).unwrap();
    let rig = simulated(&SimSettings {
        camera: camera(),
        board_file: Some(board),
        ..SimSettings::default()
    })
    .unwrap();
    Daemon::start_in(rig, dir)
}

/// A one-frame capture job at `x_um`: it leaves the axis there.
fn move_to(c: &mut Client, x_um: f64) {
    let job = JobSpec {
        start_um: Some(x_um),
        steps: Some(1),
        step_um: Some(0.0),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };
    assert_finished(&run_job(c, job).1);
}

fn snap(c: &mut Client) -> SnapReply {
    let v = c
        .request(&Request::Snap {
            scale: None,
            crop: None,
        })
        .unwrap();
    serde_json::from_value(v).unwrap()
}

fn centre(f: &ViewFrame, name: &str) -> [f64; 2] {
    f.targets
        .iter()
        .find(|t| t.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("no target {name} in {:?}", f.targets))
        .centre_px
}

fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

#[test]
fn snap_is_a_fresh_frame_at_the_stage_s_position_after_a_move() {
    let d = start();
    let mut c = d.subscribed();
    move_to(&mut c, 20_000.0);
    let asked = unix_now();
    let a = snap(&mut c);
    assert_eq!((a.job_id, a.frame.index), (None, None));
    assert!(a.frame.t_unix_s >= asked, "exposed before the request");
    let axis = a.frame.stage_um.axis_um.unwrap();
    assert!((axis - 20_000.0).abs() < 0.01, "axis at {axis}");
    assert!(a.frame.stage_um.piezo_um.is_some());
    assert_eq!((a.frame.width, a.frame.height), (300, 200));
    let png = base64::engine::general_purpose::STANDARD
        .decode(&a.frame.png_base64)
        .unwrap();
    let img = image::load_from_memory(&png).unwrap();
    assert_eq!((img.width(), img.height()), (300, 200));
    // H at board x 62 mm, the frame's left edge at the camera: (62000 - 20000) / 774 px.
    let h = centre(&a.frame, "H");
    assert!((h[0] - 42_000.0 / 774.0).abs() < 1.0, "H at {h:?}");
    let t = &a.frame.targets[0];
    assert!(t.focus.unwrap() > 0.0 && t.error.is_none(), "{t:?}");
    assert!((t.centre_um[0] - t.centre_px[0] * 774.0).abs() < 1e-6);

    move_to(&mut c, 30_000.0);
    let b = snap(&mut c);
    assert!((b.frame.stage_um.axis_um.unwrap() - 30_000.0).abs() < 0.01);
    // The board moved 10 mm the other way in the frame: 12.92 px.
    let dx = centre(&b.frame, "H")[0] - h[0];
    assert!((dx + 10_000.0 / 774.0).abs() < 0.2, "moved {dx} px");
    assert!(b.frame.sequence > a.frame.sequence);
}

#[test]
fn snap_takes_scale_and_crop_and_bad_options_are_named() {
    let d = start();
    let mut c = d.client();
    let v = c
        .request(&Request::Snap {
            scale: Some(0.5),
            crop: Some([20, 40, 200, 120]),
        })
        .unwrap();
    let s: SnapReply = serde_json::from_value(v).unwrap();
    assert_eq!(
        (s.frame.width, s.frame.height, s.frame.crop),
        (100, 60, [20, 40, 200, 120])
    );
    // Targets stay in whole-frame coordinates whatever the crop.
    assert!((centre(&s.frame, "H")[1] - 77_000.0 / 774.0).abs() < 1.0);
    let e = c
        .request(&Request::Snap {
            scale: None,
            crop: Some([200, 0, 200, 10]),
        })
        .unwrap_err();
    assert!(
        e.to_string().contains(
            "`crop` [200, 0, 200, 10] (x, y, width, height) must lie inside the 300x200 frame"
        ),
        "{e}"
    );
    for fps in [0.0, 61.0] {
        let e = c
            .request(&Request::Preview {
                max_fps: fps,
                scale: None,
                crop: None,
            })
            .unwrap_err();
        assert!(
            e.to_string().contains("`max_fps` must be from 0.01 to 60"),
            "{e}"
        );
    }
    let stop = c.request(&Request::PreviewStop {}).unwrap();
    assert_eq!(stop["stopped"], false);
    // Unknown fields are refused as on every request; the connection keeps serving.
    let mut raw = std::os::unix::net::UnixStream::connect(&d.bg.socket).unwrap();
    raw.write_all(b"{\"kind\":\"preview\",\"max_fps\":5,\"fps\":3}\n")
        .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(&raw), &mut line).unwrap();
    assert!(
        line.contains("bad_request") && line.contains("fps"),
        "{line}"
    );
}

/// Preview events until `n` have come.
fn previews(c: &mut Client, n: usize) -> Vec<(u64, ViewFrame)> {
    let mut v = Vec::new();
    while v.len() < n {
        let e = c.next_event().unwrap();
        if let EventBody::Preview(f) = e.body {
            v.push((e.job_id, *f));
        }
    }
    v
}

#[test]
fn preview_keeps_to_the_client_s_rate_and_stops() {
    let d = start();
    let mut c = d.client();
    let r = c
        .request(&Request::Preview {
            max_fps: 8.0,
            scale: Some(0.5),
            crop: None,
        })
        .unwrap();
    assert_eq!(
        (r["max_fps"].as_f64(), r["scale"].as_f64()),
        (Some(8.0), Some(0.5))
    );
    let got = previews(&mut c, 6);
    for w in got.windows(2) {
        let gap = w[1].1.t_unix_s - w[0].1.t_unix_s;
        // At most 8 a second: exposures at least 1/8 s apart (the sim's clock: 10 ms frames).
        assert!(gap >= 0.125 - 1e-6, "frames {gap} s apart");
    }
    for (job, f) in &got {
        assert_eq!((*job, f.width, f.height, f.targets.len()), (0, 150, 100, 2));
        assert!(f.stage_um.axis_um.is_some());
    }
    // A new preview replaces the old one; stop ends it.
    c.request(&Request::Preview {
        max_fps: 20.0,
        scale: None,
        crop: Some([0, 0, 100, 100]),
    })
    .unwrap();
    let r = c.request(&Request::PreviewStop {}).unwrap();
    assert_eq!(r["stopped"], true);
}

#[test]
fn preview_during_a_job_shows_the_job_s_frames_at_their_positions() {
    let d = start();
    let mut c = d.subscribed();
    c.request(&Request::Preview {
        max_fps: 60.0,
        scale: Some(0.25),
        crop: None,
    })
    .unwrap();
    let job = JobSpec {
        start_um: Some(10_000.0),
        steps: Some(12),
        step_um: Some(1_000.0),
        settle_ms: 30,
        process: false,
        ..JobSpec::default()
    };
    let (id, events) = run_job(&mut c, job);
    assert_finished(&events);
    let steps: Vec<(u32, f64)> = events
        .iter()
        .filter_map(|e| match e {
            EventBody::Step { index, axis_um, .. } => Some((*index, *axis_um)),
            _ => None,
        })
        .collect();
    // The job's preview events come with its own (`job_id` the job's).
    let seen: Vec<&ViewFrame> = events
        .iter()
        .filter_map(|e| match e {
            EventBody::Preview(f) => Some(&**f),
            _ => None,
        })
        .collect();
    let _ = id;
    assert!(!seen.is_empty(), "no preview of the job's frames");
    for f in seen {
        let i = f.index.expect("a job frame's index");
        let (_, axis) = steps[i as usize];
        assert_eq!(f.stage_um.axis_um, Some(axis), "frame {i}");
    }
}

#[test]
fn a_subscriber_that_never_reads_holds_one_frame_and_the_job_runs_through() {
    let d = start();
    let mut lazy = std::os::unix::net::UnixStream::connect(&d.bg.socket).unwrap();
    lazy.write_all(b"{\"kind\":\"preview\",\"max_fps\":60}\n")
        .unwrap();
    let mut c = d.subscribed();
    let job = JobSpec {
        start_um: Some(10_000.0),
        steps: Some(40),
        step_um: Some(500.0),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };
    let (_, events) = run_job(&mut c, job);
    assert_finished(&events);
    assert_eq!(
        events
            .iter()
            .filter(|e| matches!(e, EventBody::Step { .. }))
            .count(),
        40
    );
    // What waited for the lazy client: the kernel's socket buffers, one line in the
    // daemon's queue and one being written; never the job's 40 frames.
    // Stop its preview, then read up to the stop's reply: what is before it had waited.
    lazy.write_all(b"{\"kind\":\"preview_stop\",\"id\":\"stop\"}\n")
        .unwrap();
    lazy.set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut got = Vec::new();
    let mut buf = vec![0u8; 1 << 16];
    while !got.ends_with(b"}}\n")
        || !String::from_utf8_lossy(&got[got.len().saturating_sub(200)..]).contains("\"stop\"")
    {
        let n = lazy.read(&mut buf).unwrap();
        assert!(n > 0, "the daemon closed the lazy client");
        got.extend_from_slice(&buf[..n]);
    }
    let lines: Vec<&[u8]> = got
        .split(|&b| b == b'\n')
        .filter(|l| !l.is_empty())
        .collect();
    let longest = lines.iter().map(|l| l.len()).max().unwrap();
    let kernel: usize = ["wmem_default", "rmem_default"]
        .iter()
        .map(|f| {
            std::fs::read_to_string(format!("/proc/sys/net/core/{f}"))
                .map_or(212_992, |s| s.trim().parse().unwrap())
        })
        .sum();
    assert!(
        longest > 50_000,
        "frames of {longest} bytes: too small to tell"
    );
    let backlog = 40 * longest;
    assert!(
        got.len() < kernel + 3 * longest + 300 * 1024 && got.len() < backlog / 2,
        "{} bytes waited ({} lines of up to {longest}; kernel buffers {kernel})",
        got.len(),
        lines.len()
    );
}

#[test]
fn the_focus_figure_falls_as_the_sim_blurs() {
    let board = crate::support::small_board();
    let info = rig_info_of(&board);
    let mut last = [f64::INFINITY; 2];
    for sigma in [0.5, 1.0, 1.6, 2.4] {
        let cam = CameraModel {
            psf_sigma_px: sigma,
            ..camera()
        };
        let scene = SceneRenderer::new(board.clone(), cam);
        let img = crate::support::frame(&scene, View::at([20_000.0, 0.0]), 7);
        let t = render::targets(&img, &info);
        assert_eq!(t.len(), 2, "σ {sigma}");
        for (i, t) in t.iter().enumerate() {
            let f = t.focus.unwrap();
            assert!(f < last[i] * 0.97, "σ {sigma}: {f} not below {}", last[i]);
            last[i] = f;
        }
    }
}

/// A rig description for the small board and the test camera.
fn rig_info_of(board: &rigd::board::Board) -> rigd::rig::RigInfo {
    let mut info: rigd::rig::RigInfo = serde_json::from_value(serde_json::json!({
        "mode": "sim", "axis_limits_um": [0.0, 250000.0], "piezo_limits_um": null,
        "default_start_um": 1000.0, "scale_um_per_px": 774.0, "axis_dir": [-1.0, 0.0],
        "frame_size": [300, 200], "board": null, "config": null
    }))
    .unwrap();
    info.board = Some(board.clone());
    info
}

#[test]
fn rigctl_snap_and_view_write_the_png_and_show_the_targets() {
    let d = start();
    let dir = tempfile::tempdir().unwrap();
    let rigctl = env!("CARGO_BIN_EXE_rigctl");
    let snap = dir.path().join("snap.png");
    let out = std::process::Command::new(rigctl)
        .args(["snap", "--socket"])
        .arg(&d.bg.socket)
        .arg("--out")
        .arg(&snap)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text} {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.starts_with("a fresh frame: 300x200 at "), "{text}");
    assert!(
        text.contains("axis 0.0 µm") && text.contains("  H "),
        "{text}"
    );
    assert_eq!(image::open(&snap).unwrap().width(), 300);

    let preview = dir.path().join("view.png");
    let out = std::process::Command::new(rigctl)
        .args(["view", "--frames", "3", "--fps", "20", "--socket"])
        .arg(&d.bg.socket)
        .arg("--out")
        .arg(&preview)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text} {}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Not a terminal: plain lines, no escapes; three frames of two targets.
    assert!(!text.contains('\x1b'), "{text:?}");
    assert_eq!(
        text.lines().filter(|l| l.starts_with("frame ")).count(),
        3,
        "{text}"
    );
    assert_eq!(
        text.lines().filter(|l| l.contains("focus ")).count(),
        6,
        "{text}"
    );
    assert_eq!(image::open(&preview).unwrap().width(), 150);
    // No temporary left beside it.
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names.len(), 2, "{names:?}");
}
