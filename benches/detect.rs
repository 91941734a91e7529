//! Per-frame detection and measurement on a simulated 1280x720 frame of the paper's board.
//! `cargo bench --bench detect`; figures in docs/method.md.

use criterion::{criterion_group, Criterion};
use rigd::pipeline::detect::{detect, measurement_channel, DetectConfig};
use rigd::pipeline::estimate::{estimate, estimate_targets};
use rigd::pipeline::plane::Plane;
use rigd::pipeline::{Estimator, Response};
use rigd::sim::render::render_frame;
use rigd::sim::{Board, CameraModel, View};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let board = Board::paper();
    let cam = CameraModel::default();
    let img = render_frame(&board, &cam, &View::at([300.0, 500.0]), 1.0, 1);
    let cfg = DetectConfig::default();
    let det = detect(&img, &cfg);
    assert_eq!(
        det.targets.len(),
        12,
        "the bench frame shows all twelve targets"
    );

    c.bench_function("detect 1280x720", |b| {
        b.iter(|| detect(black_box(&img), &cfg))
    });
    for (name, est) in [("fit", Estimator::Fit), ("paper", Estimator::Paper)] {
        c.bench_function(
            &format!("detect + measure 12 targets ({name}, ROI path)"),
            |b| {
                b.iter(|| {
                    let det = detect(black_box(&img), &cfg);
                    let ch = measurement_channel(&img, &det);
                    let r = estimate_targets(&img, &det, (ch, Response::Linear), est);
                    assert!(r.iter().all(|r| r.is_ok()));
                    r
                })
            },
        );
    }
    let plane = Plane::from_channel(&img, 1);
    let g = &det.targets[0];
    c.bench_function("fit one target", |b| {
        b.iter(|| estimate(black_box(&plane), g, Estimator::Fit, 1.0).unwrap())
    });
    c.bench_function("paper one target", |b| {
        b.iter(|| estimate(black_box(&plane), g, Estimator::Paper, 1.0).unwrap())
    });
}

/// CPU seconds (user + system, all threads) this process has used.
fn cpu_s() -> f64 {
    // SAFETY: getrusage writes into the zeroed struct we pass and reads nothing else.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 * 1e-6;
    t(u.ru_utime) + t(u.ru_stime)
}

/// CPU time per frame as well as criterion's wall time: on a machine shared with other
/// jobs the wall time includes waiting for a core, the CPU time does not.
fn cpu_report() {
    let board = Board::paper();
    let cam = CameraModel::default();
    let img = render_frame(&board, &cam, &View::at([300.0, 500.0]), 1.0, 1);
    let cfg = DetectConfig::default();
    let n = 300;
    let t0 = cpu_s();
    for _ in 0..n {
        black_box(detect(black_box(&img), &cfg));
    }
    let t1 = cpu_s();
    for _ in 0..n {
        let det = detect(black_box(&img), &cfg);
        let ch = measurement_channel(&img, &det);
        black_box(estimate_targets(
            &img,
            &det,
            (ch, Response::Linear),
            Estimator::Fit,
        ));
    }
    let t2 = cpu_s();
    println!(
        "CPU time per 1280x720 frame (all threads): detect {:.2} ms, detect + fit 12 targets {:.2} ms",
        (t1 - t0) / n as f64 * 1e3,
        (t2 - t1) / n as f64 * 1e3
    );
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(3));
    targets = bench
}

fn main() {
    benches();
    cpu_report();
    Criterion::default().configure_from_args().final_summary();
}
