//! Render speed: the paper's whole study (20 experiments x 31 frames of 1280x720) with the
//! default camera, and the cost of each per-frame effect, then a frame of each camera profile
//! (`ideal`, `webcam`, `stress`). `cargo bench -p rigd-sim --bench render` prints the figures
//! quoted in docs/sim.md; `... -- profiles` times the profiles only.

use rigd_sim::camera::CameraModel;
use rigd_sim::{Board, FrameRenderer};
use std::time::Instant;

/// CPU time of this process (all threads), s: the figure that does not depend on how many
/// other jobs share the machine.
fn cpu_s() -> f64 {
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage fills the struct we own.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) };
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(ru.ru_utime) + tv(ru.ru_stime)
}

fn time<T>(label: &str, frames: usize, f: impl FnOnce() -> T) -> T {
    let (t0, c0) = (Instant::now(), cpu_s());
    let out = f();
    let (s, c) = (t0.elapsed().as_secs_f64(), cpu_s() - c0);
    println!(
        "{label:<40} {frames:>4} frames  wall {s:>7.2} s ({:>6.1} ms/frame)  cpu {c:>7.2} s ({:>6.1} ms/frame)",
        1e3 * s / frames as f64,
        1e3 * c / frames as f64
    );
    out
}

fn main() {
    let threads = rayon::current_num_threads();
    println!("rayon threads: {threads}");
    if std::env::args().any(|a| a == "profiles") {
        profiles(30);
        return;
    }
    let t0 = Instant::now();
    let r = FrameRenderer::new(Board::paper(), CameraModel::default(), 1).unwrap();
    println!(
        "renderer set-up (background cache)            {:.3} s",
        t0.elapsed().as_secs_f64()
    );

    // The paper's study: 20 experiments of case 1 (1 frame), case 2 (10 frames at 100 µm)
    // and case 3 (20 frames at 50 µm): 31 frames each.
    let mut checksum = 0u64;
    time("study 20 x 31 frames (default camera)", 620, || {
        for e in 0..20u64 {
            let mut seq = e * 1000;
            let mut shot = |x: f64| {
                let img = r.render_at(seq, [x, 0.0]);
                checksum = checksum.wrapping_add(img.as_raw()[640 * 3 + 360 * 3840] as u64);
                seq += 1;
            };
            shot(0.0);
            for i in 0..10 {
                shot(i as f64 * 100.0);
            }
            for i in 0..20 {
                shot(i as f64 * 50.0);
            }
        }
    });
    println!("(checksum {checksum})");

    let n = 30;
    let view = [rigd_sim::View::at([0.0, 0.0])];
    time("expected frame only (no noise)", n, || {
        for _ in 0..n {
            r.scene().expected_frame(&view);
        }
    });
    time("static pose", n, || {
        for i in 0..n as u64 {
            r.render_at(i, [0.0, 0.0]);
        }
    });
    let blur: Vec<[f64; 2]> = (0..8).map(|k| [k as f64 * 25.0, 0.0]).collect();
    time("moving: 8 sub-exposures", n, || {
        for i in 0..n as u64 {
            r.render(i, &blur);
        }
    });
    let mj = FrameRenderer::new(
        Board::paper(),
        CameraModel {
            mjpeg_quality: Some(80),
            ..Default::default()
        },
        1,
    )
    .unwrap();
    time("static pose + MJPEG q80 4:2:2", n, || {
        for i in 0..n as u64 {
            mj.render_at(i, [0.0, 0.0]);
        }
    });
}

/// A still 1280x720 frame of each profile, and the webcam's stages.
fn profiles(n: usize) {
    for name in ["ideal", "webcam", "stress"] {
        let cam = CameraModel::profile(name).unwrap();
        let r = FrameRenderer::new(Board::paper(), cam.clone(), 1).unwrap();
        r.render_at(0, [0.0, 0.0]);
        time(&format!("{name}: still frame"), n, || {
            for i in 0..n as u64 {
                r.render_at(i, [0.0, 0.0]);
            }
        });
        if name != "webcam" {
            continue;
        }
        let view = [rigd_sim::View::at([0.0, 0.0])];
        time("webcam: expected frame only", n, || {
            for _ in 0..n {
                r.scene().expected_frame(&view);
            }
        });
        time("webcam: sensor + ISP (no transport)", n, || {
            for i in 0..n as u64 {
                r.scene().expose_lit(&view, 1.0, i, 0.0);
            }
        });
        let yuyv = FrameRenderer::new(
            Board::paper(),
            CameraModel {
                mjpeg_quality: None,
                ..cam
            },
            1,
        )
        .unwrap();
        time("webcam: YUYV instead of MJPEG", n, || {
            for i in 0..n as u64 {
                yuyv.render_at(i, [0.0, 0.0]);
            }
        });
    }
}
