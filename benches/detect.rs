//! Per-frame detection and measurement on a simulated 1280x720 frame of the paper's board.
//! `cargo bench --bench detect`; figures in docs/method.md.

use criterion::{criterion_group, criterion_main, Criterion};
use rigd::pipeline::detect::{detect, measurement_channel, DetectConfig};
use rigd::pipeline::estimate::{estimate, estimate_targets};
use rigd::pipeline::plane::Plane;
use rigd::pipeline::Estimator;
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
                    let r = estimate_targets(&img, &det, ch, est);
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

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(3));
    targets = bench
}
criterion_main!(benches);
