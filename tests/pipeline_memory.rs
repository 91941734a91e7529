//! `ValidOptions::peak_memory_bytes` against the pipeline's measured peak heap use, and that
//! peak against a run's length (processing streams: it must not grow with the frames): a
//! counting allocator records the highest number of live bytes during a run.

mod support;

use rigd::pipeline::{Combine, Estimator, Pipeline, ProcessOptions};
use rigd::sim::render::SceneRenderer;
use rigd::sim::View;
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use support::*;

struct Counting;

static LIVE: AtomicU64 = AtomicU64::new(0);
static PEAK: AtomicU64 = AtomicU64::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = System.alloc(layout);
        if !p.is_null() {
            let live = LIVE.fetch_add(layout.size() as u64, Relaxed) + layout.size() as u64;
            PEAK.fetch_max(live, Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, p: *mut u8, layout: Layout) {
        System.dealloc(p, layout);
        LIVE.fetch_sub(layout.size() as u64, Relaxed);
    }
}

#[global_allocator]
static COUNTING: Counting = Counting;

/// Peak live bytes above those live before `f` ran, `f`'s result dropped only after.
fn peak_of<T>(f: impl FnOnce() -> T) -> u64 {
    let before = LIVE.load(Relaxed);
    PEAK.store(before, Relaxed);
    let kept = f();
    let peak = PEAK.load(Relaxed) - before;
    drop(kept);
    peak
}

// One test function: nothing else allocates in this binary while it measures. One worker
// thread: with more, how many targets are reconstructed at once depends on how the
// scheduler shares the cores with whatever else runs, and the peak with it.
#[test]
fn the_estimate_bounds_the_measured_peak_closely() {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    pool.install(measure);
    pool.install(flat_in_the_number_of_frames);
}

/// A run of 400 frames peaks where one of 50 does: nothing a frame brings is kept.
fn flat_in_the_number_of_frames() {
    let scene = SceneRenderer::new(small_board(), small_camera());
    // Back and forth over 20 places 50 µm apart, a step per frame.
    let places: Vec<(image::RgbImage, f64)> = (0..20u32)
        .map(|i| {
            let pos = 50.0 * i as f64;
            (
                frame(&scene, View::at([123.0 + pos, 456.0]), 70 + i as u64),
                pos,
            )
        })
        .collect();
    let place = |i: usize| {
        let j = i % 38;
        if j < 20 {
            j
        } else {
            38 - j
        }
    };
    let board = small_board();
    let cases = [
        (10, Combine::Interp, Estimator::Fit, false),
        (10, Combine::Splat, Estimator::Paper, false),
        (1, Combine::Mean, Estimator::Fit, false),
        (4, Combine::Interp, Estimator::Paper, true),
    ];
    for (k, combine, estimator, whole_frame) in cases {
        let opts = ProcessOptions {
            k,
            combine,
            estimator,
            whole_frame,
            ..ProcessOptions::default()
        }
        .validate()
        .unwrap();
        let run = |n: usize| {
            peak_of(|| {
                let mut p = Pipeline::new(opts.clone(), Some(board.clone()));
                for i in 0..n {
                    let (f, x) = &places[place(i)];
                    p.push(f, *x).unwrap();
                }
                p.finish().unwrap()
            })
        };
        let (short, long) = (run(50), run(400));
        let growth = long as f64 / short as f64;
        eprintln!("k={k} {combine:?} whole={whole_frame}: 50 frames {short} B, 400 frames {long} B ({growth:.3}x)");
        // Measured: 1.000x-1.009x (the 350 more listed steps: 28 kB). Before processing
        // streamed every frame's windows (28 kB a frame here) and, for the whole frame, its
        // plane (240 kB) were kept: 10 MB and 84 MB more after 400 frames.
        assert!(
            growth < 1.02,
            "k={k} {combine:?} whole={whole_frame}: {short} B after 50 frames, {long} B after 400"
        );
    }
}

fn measure() {
    let scene = SceneRenderer::new(small_board(), small_camera());
    let n = 8u32;
    let frames: Vec<(image::RgbImage, f64)> = (0..n)
        .map(|i| {
            let pos = 50.0 * i as f64;
            (
                frame(&scene, View::at([123.0 + pos, 456.0]), 40 + i as u64),
                pos,
            )
        })
        .collect();
    let size = frames[0].0.dimensions();
    let board = small_board();
    // A first run starts the thread pool: its own allocations are not a run's.
    let mut warm = Pipeline::new(ProcessOptions::default().validate().unwrap(), None);
    warm.push(&frames[0].0, 0.0).unwrap();
    drop(warm.finish());
    // (k, combine, estimator, whole_frame, how far above the measured peak the estimate may be)
    let cases = [
        // Measured on one thread: 23.9 MB (estimate 1.02x), 8.3 MB (1.09x), 9.4 MB (1.24x),
        // 0.30 MB (1.21x). (Before processing streamed: 26.0, 8.5, 9.6 and 0.30 MB.)
        (8, Combine::Interp, Estimator::Fit, true, 1.1),
        (16, Combine::Interp, Estimator::Fit, false, 1.2),
        (16, Combine::Splat, Estimator::Paper, false, 1.3),
        (1, Combine::Mean, Estimator::Fit, false, 1.35),
    ];
    for (k, combine, estimator, whole_frame, above) in cases {
        let opts = ProcessOptions {
            k,
            combine,
            estimator,
            whole_frame,
            ..ProcessOptions::default()
        }
        .validate()
        .unwrap();
        let estimate = opts.peak_memory_bytes(size, n, Some(&board));
        let measured = peak_of(|| {
            let mut p = Pipeline::new(opts.clone(), Some(board.clone()));
            for (f, x) in &frames {
                p.push(f, *x).unwrap();
            }
            p.finish().unwrap()
        });
        let ratio = estimate as f64 / measured as f64;
        eprintln!("k={k} {combine:?} {estimator:?} whole={whole_frame}: measured {measured} B, estimate {estimate} B ({ratio:.2}x)");
        assert!(
            (1.0..above).contains(&ratio),
            "k={k} {combine:?} whole={whole_frame}: estimate {estimate} B vs measured {measured} B"
        );
    }
}
