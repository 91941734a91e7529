//! Pipeline speed (docs/performance.md): `cargo bench --bench pipeline`.
//!
//! - `frame/first`: frame 0 of a job, 1280x720: detect every target and measure it.
//! - `frame/next`: a later frame: measure the targets where registration predicts them.
//! - `job/20x50um_k10`: a 20-frame k = 10 job from a PNG folder, end to end (read, decode,
//!   detect, register, reconstruct and measure the 12 targets) on one thread, the way
//!   `rigctl process` does it without `--out`: buffers reused, later frames decoded down to
//!   the last row the pipeline reads, no images made. (`rigctl process` also decodes on
//!   every core: its whole-process figure is in docs/performance.md.)
//! - `whole_frame/interp_k10_20` and `whole_frame/splat_k10_20`: the whole-frame k = 10
//!   reconstruction of 20 frames.
//!
//! Peak memory: `RIGD_PEAK_RSS=interp cargo bench --bench pipeline` (or `=splat`) runs the
//! whole-frame reconstruction once in this fresh process and prints its time and VmHWM.
//! `RIGD_WRITE_FOLDER=DIR cargo bench --bench pipeline` writes the job's folder (for
//! benches/opencv_baseline.py) and exits.

#[path = "support/paper_job.rs"]
mod paper_job;

use criterion::{criterion_group, Criterion};
use paper_job::{frames, write_folder, STEP_UM};
use rigd::pipeline::reconstruct::{self, View};
use rigd::pipeline::{plane::Plane, Combine, Estimator, Pipeline, ProcessOptions, ValidOptions};
use std::hint::black_box;
use std::time::Instant;

fn opts(k: u32, combine: Combine, estimator: Estimator) -> ValidOptions {
    ProcessOptions {
        k,
        combine,
        estimator,
        ..ProcessOptions::default()
    }
    .validate()
    .unwrap()
}

fn bench_frames(c: &mut Criterion) {
    let f = frames(2);
    let mut g = c.benchmark_group("frame");
    for est in [Estimator::Paper, Estimator::Fit] {
        g.bench_function(format!("first/{est:?}"), |b| {
            b.iter(|| {
                let mut p = Pipeline::new(opts(1, Combine::Mean, est), None);
                black_box(p.push(&f[0], 0.0).unwrap());
            })
        });
        let mut p = Pipeline::new(opts(1, Combine::Mean, est), None);
        p.push(&f[0], 0.0).unwrap();
        g.bench_function(format!("next/{est:?}"), |b| {
            b.iter(|| {
                // Same pipeline, growing by one frame per iteration: the per-frame cost.
                black_box(p.push(&f[1], STEP_UM).unwrap());
            })
        });
    }
    g.finish();
}

/// Write the benchmark's folder: 20 frames of the paper's board at 50 µm steps.
fn bench_job(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    write_folder(dir.path());
    let mut g = c.benchmark_group("job");
    g.sample_size(10);
    for est in [Estimator::Paper, Estimator::Fit] {
        g.bench_function(format!("20x50um_k10/{est:?}"), |b| {
            b.iter(|| {
                let folder = rigd::folder::open(dir.path(), None).unwrap();
                let mut p = Pipeline::new(opts(10, Combine::Interp, est), None);
                p.keep_images(false);
                let mut reader = rigd::folder::FrameReader::default();
                let mut buf = None;
                for (path, &x) in folder.frames.iter().zip(&folder.positions_um) {
                    let rows = p.rows_needed(24).unwrap_or(u32::MAX);
                    let (f, rows) = reader.read_rows(path, buf.take(), rows).unwrap();
                    let f = match p.push_rows(&f, rows, x).unwrap() {
                        Some(_) => f,
                        None => {
                            let f = reader.read(path, Some(f)).unwrap();
                            p.push(&f, x).unwrap();
                            f
                        }
                    };
                    buf = Some(f);
                }
                black_box(p.finish().unwrap())
            })
        });
    }
    g.finish();
}

fn planes(n: usize) -> Vec<Plane> {
    frames(n)
        .iter()
        .map(|f| Plane::from_channel(f, 1))
        .collect()
}

fn shifts(n: usize, k: usize) -> Vec<[i64; 2]> {
    (0..n)
        .map(|i| reconstruct::fine_shift([-STEP_UM * i as f64 / 774.0, 0.0], k))
        .collect()
}

fn bench_whole_frame(c: &mut Criterion) {
    let p = planes(20);
    let views: Vec<View> = p
        .iter()
        .map(|p| View::new(&p.data, p.width, p.height))
        .collect();
    let s = shifts(20, 10);
    let mut g = c.benchmark_group("whole_frame");
    g.sample_size(10);
    g.bench_function("interp_k10_20", |b| {
        b.iter(|| black_box(reconstruct::interp(&views, &s, 10)))
    });
    g.bench_function("splat_k10_20", |b| {
        b.iter(|| black_box(reconstruct::splat(&views, &s, 10)))
    });
    g.finish();
}

/// VmHWM (peak resident set) of this process, in MB.
fn peak_rss_mb() -> f64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    s.lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map(|kb| kb / 1024.0)
        .unwrap_or(f64::NAN)
}

/// One whole-frame reconstruction in this fresh process: its time and the peak RSS.
fn peak_memory(method: &str) {
    let p = planes(20);
    let before = peak_rss_mb();
    let views: Vec<View> = p
        .iter()
        .map(|p| View::new(&p.data, p.width, p.height))
        .collect();
    let s = shifts(20, 10);
    let t = Instant::now();
    let fine = if method == "splat" {
        reconstruct::splat(&views, &s, 10)
    } else {
        reconstruct::interp(&views, &s, 10)
    };
    let el = t.elapsed().as_secs_f64();
    println!(
        "whole-frame {method} k=10, 20 frames 1280x720 -> {}x{}: {el:.3} s, peak RSS {:.0} MB (before: {before:.0} MB)",
        fine.width,
        fine.height,
        peak_rss_mb()
    );
}

criterion_group!(benches, bench_frames, bench_job, bench_whole_frame);

fn main() {
    if let Ok(m) = std::env::var("RIGD_PEAK_RSS") {
        peak_memory(&m);
        return;
    }
    if let Some(dir) = std::env::var_os("RIGD_WRITE_FOLDER") {
        write_folder(std::path::Path::new(&dir));
        return;
    }
    benches();
    Criterion::default().configure_from_args().final_summary();
}
