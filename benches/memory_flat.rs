//! Peak memory of one run against its length (docs/performance.md, "Memory against a run's
//! length"): `cargo bench --bench memory_flat`.
//!
//! A counting global allocator records the highest number of live heap bytes while one
//! pipeline takes N frames of the paper's board (1280x720, 12 targets) rendered by the
//! simulator, and finishes; the frames themselves (rendered once, before) are not counted.
//! The scan goes back and forth over 40 rendered positions 50 µm apart (a long run on a
//! board of finite size), one step per frame, registered from the image as the daemon does.
//!
//! `RIGD_MEMORY_FRAMES=100,1000,10000` (the default) sets the run lengths,
//! `RIGD_MEMORY_CASES=interp-fit,splat-paper,mean-fit,whole-interp` (the default: all) the
//! processing: k = 10 with the named combine and estimator (`whole-interp`: the whole-frame
//! reconstruction as well, on at most 1000 frames unless asked for by name alone).
//! `RIGD_MEMORY_VERBOSE=1` prints every target's offset and sigma at full precision (to
//! compare the results of two builds).

use rigd::pipeline::{Combine, Estimator, Pipeline, ProcessOptions};
use rigd::sim::render::{render_frame, View};
use rigd::sim::{Board, CameraModel};
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Instant;

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

const STEP_UM: f64 = 50.0;
const POSITIONS: usize = 40;

/// Frame `i` of the back-and-forth scan: its rendered position's index.
fn place(i: usize) -> usize {
    let period = 2 * (POSITIONS - 1);
    let j = i % period;
    if j < POSITIONS {
        j
    } else {
        period - j
    }
}

struct Case {
    name: &'static str,
    combine: Combine,
    estimator: Estimator,
    whole_frame: bool,
}

const CASES: [Case; 4] = [
    Case {
        name: "interp-fit",
        combine: Combine::Interp,
        estimator: Estimator::Fit,
        whole_frame: false,
    },
    Case {
        name: "splat-paper",
        combine: Combine::Splat,
        estimator: Estimator::Paper,
        whole_frame: false,
    },
    Case {
        name: "mean-fit",
        combine: Combine::Mean,
        estimator: Estimator::Fit,
        whole_frame: false,
    },
    Case {
        name: "whole-interp",
        combine: Combine::Interp,
        estimator: Estimator::Paper,
        whole_frame: true,
    },
];

fn main() {
    // `cargo bench` passes `--bench`; nothing else is taken from the command line.
    let lengths: Vec<usize> = std::env::var("RIGD_MEMORY_FRAMES")
        .unwrap_or_else(|_| "100,1000,10000".into())
        .split(',')
        .map(|s| s.trim().parse().expect("RIGD_MEMORY_FRAMES: frame counts"))
        .collect();
    let asked = std::env::var("RIGD_MEMORY_CASES").ok();
    let board = Board::paper();
    let cam = CameraModel::default();
    let frames: Vec<image::RgbImage> = (0..POSITIONS)
        .map(|i| {
            let view = View::at([237.0 + STEP_UM * i as f64, 411.0]);
            render_frame(&board, &cam, &view, 1.0, 100 + i as u64)
        })
        .collect();
    println!("case          frames   peak heap   time    first target's offset_um");
    for case in &CASES {
        if asked
            .as_ref()
            .is_some_and(|a| !a.split(',').any(|c| c == case.name))
        {
            continue;
        }
        let opts = ProcessOptions {
            k: 10,
            combine: case.combine,
            estimator: case.estimator,
            whole_frame: case.whole_frame,
            ..ProcessOptions::default()
        }
        .validate()
        .unwrap();
        for &n in &lengths {
            if case.whole_frame && n > 1000 && asked.is_none() {
                continue;
            }
            let before = LIVE.load(Relaxed);
            PEAK.store(before, Relaxed);
            let t = Instant::now();
            let mut p = Pipeline::new(opts.clone(), Some(board.clone()));
            for i in 0..n {
                let at = place(i);
                p.push(&frames[at], STEP_UM * at as f64).unwrap();
            }
            let done = p.finish().unwrap();
            let peak = PEAK.load(Relaxed) - before;
            let o = &done.result.objects[0];
            println!(
                "{:<12} {n:>7} {:>8.1} MB {:>6.1} s  [{:.2}, {:.2}]",
                case.name,
                peak as f64 / 1e6,
                t.elapsed().as_secs_f64(),
                o.offset_um[0],
                o.offset_um[1]
            );
            if std::env::var_os("RIGD_MEMORY_VERBOSE").is_some() {
                for o in &done.result.objects {
                    println!("    {:?} {:?} {:?}", o.name, o.offset_um, o.sigma_um);
                }
            }
        }
    }
}
