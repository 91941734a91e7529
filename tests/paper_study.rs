//! The paper's study on the simulated rig: the paper, reproduced.
//!
//! Each experiment starts the camera at a random sub-pixel position and renders the paper's
//! three cases: one raw frame; 10 frames at 100 µm steps (k = 5); 20 frames at 50 µm steps
//! (k = 10). The camera moves +x, so the scene moves -x. Every frame has its own noise,
//! a 2 µm RMS vibration of the line of sight and 0.5 % illumination flicker. With the
//! `paper` estimator (thresholded centroids) and the paper's reconstruction, averaging must
//! cut the RMS std of the offsets of targets A-F by at least 7x (case 2) and 15x (case 3),
//! about half of what the simulated rig gives (the paper measured 2.9x and 4.0x on its real
//! rig, whose averaged std is dominated by effects the simulation leaves out).
//!
//! `paper_study_subset` runs 5 experiments in the default suite; the full study (20
//! experiments, both estimators, tables and figures written under target/) is
//! `cargo test --release --test paper_study -- --ignored --nocapture`.

mod support;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigd::pipeline::stats::{study_stats, CaseRuns, StudyStats};
use rigd::pipeline::{process_frames, Combine, Estimator, ProcessOptions, Registration};
use rigd::sim::frames::FrameRenderer;
use rigd::sim::render::View;
use rigd::sim::{Board, CameraModel};

const NAMES: [&str; 6] = ["A", "B", "C", "D", "E", "F"];

struct Case {
    name: &'static str,
    frames: usize,
    step_um: f64,
    k: u32,
}

const CASES: [Case; 3] = [
    Case {
        name: "case 1",
        frames: 1,
        step_um: 0.0,
        k: 1,
    },
    Case {
        name: "case 2",
        frames: 10,
        step_um: 100.0,
        k: 5,
    },
    Case {
        name: "case 3",
        frames: 20,
        step_um: 50.0,
        k: 10,
    },
];

/// The frames and commanded positions of one case of one experiment. Frame `sequence + i`
/// draws its own flicker, vibration and noise (`FrameEffects`).
fn render_case(
    frames: &FrameRenderer,
    start_um: [f64; 2],
    case: &Case,
    sequence: &mut u64,
) -> (Vec<image::RgbImage>, Vec<f64>) {
    (0..case.frames)
        .map(|i| {
            let pos = case.step_um * i as f64;
            *sequence += 1;
            let img = frames.render_at(*sequence, [start_um[0] + pos, start_um[1]]);
            (img, pos)
        })
        .unzip()
}

/// Which way each case is combined, for one estimator.
fn options(case: &Case, estimator: Estimator, reconstruct: bool) -> ProcessOptions {
    ProcessOptions {
        k: if reconstruct { case.k } else { 1 },
        estimator,
        combine: if reconstruct && case.frames > 1 {
            Combine::Interp
        } else {
            Combine::Mean
        },
        registration: Registration::Image,
        ..ProcessOptions::default()
    }
}

/// Run `experiments` experiments; one study per (estimator, reconstruct) method given.
fn run_study(
    experiments: usize,
    cam: &CameraModel,
    methods: &[(Estimator, bool)],
) -> Vec<StudyStats> {
    let board = Board::paper();
    let frames = FrameRenderer::new(board.clone(), cam.clone(), 2015).expect("a valid camera");
    let mut rng = ChaCha8Rng::seed_from_u64(2015);
    let mut sequence = 0;
    let mut runs: Vec<Vec<CaseRuns>> = methods
        .iter()
        .map(|_| {
            CASES
                .iter()
                .map(|c| CaseRuns {
                    name: c.name.into(),
                    frames: c.frames,
                    step_um: c.step_um,
                    k: c.k,
                    runs: Vec::new(),
                })
                .collect()
        })
        .collect();
    for _ in 0..experiments {
        // A random sub-pixel start: the sampling phase of every target differs per experiment.
        let start = [
            cam.scale_um_per_px * rng.gen::<f64>(),
            cam.scale_um_per_px * rng.gen::<f64>(),
        ];
        for (ci, case) in CASES.iter().enumerate() {
            let (imgs, pos) = render_case(&frames, start, case, &mut sequence);
            for (mi, &(est, rec)) in methods.iter().enumerate() {
                let done =
                    process_frames(&imgs, &pos, &options(case, est, rec), Some(board.clone()))
                        .unwrap_or_else(|e| panic!("{} {est:?}: {e}", case.name));
                let mut r = runs[mi][ci].clone();
                r.runs.push(done.result.objects);
                runs[mi][ci] = r;
            }
        }
    }
    runs.iter()
        .map(|c| study_stats(c, &NAMES, cam.scale_um_per_px))
        .collect()
}

fn gains(st: &StudyStats) -> (f64, f64) {
    let r: Vec<f64> = st.cases.iter().map(|c| c.rms_std_um).collect();
    (r[0] / r[1], r[0] / r[2])
}

#[test]
fn paper_study_subset() {
    // Coarser area integration (4x4 instead of 8x8 sub-samples on edge pixels) keeps the
    // default suite quick; the full study uses the camera's defaults.
    let cam = CameraModel {
        supersample: 4,
        ..CameraModel::default()
    };
    let st = &run_study(5, &cam, &[(Estimator::Paper, true)])[0];
    println!("{}", rigd::report::study_tables(st));
    for c in &st.cases {
        for t in &c.targets {
            assert_eq!(
                t.n, 5,
                "{} {}: every run measures every target",
                c.name, t.name
            );
        }
    }
    // Seed 2015, measured: gains 14.5x and 34.4x; averaged RMS std 7.2 and 3.0 µm; largest
    // |bias| 30 and 28 µm (the centroids' systematic, docs/paper-tables.md). Seeds 1-5 give
    // gains 9.4-16x and 15-38x, RMS std 5.8-7.6 and 3.0-4.6 µm, |bias| <= 31 µm: the bounds
    // below hold for any of them and are about 2x the seeded figures.
    let (g2, g3) = gains(st);
    assert!(
        g2 >= 7.0,
        "case 2 improves the std {g2:.2}x, want >= 7x (seeded: 14.5x)"
    );
    assert!(
        g3 >= 15.0,
        "case 3 improves the std {g3:.2}x, want >= 15x (seeded: 34.4x)"
    );
    let rms: Vec<f64> = st.cases.iter().map(|c| c.rms_std_um).collect();
    assert!(
        rms[1] < 15.0,
        "case 2 RMS std {:.1} µm, want < 15 (seeded: 7.2)",
        rms[1]
    );
    assert!(
        rms[2] < 7.0,
        "case 3 RMS std {:.1} µm, want < 7 (seeded: 3.0)",
        rms[2]
    );
    // The averaged cases measure the offsets they should, within twice the ~30 µm
    // systematic of thresholded centroids.
    for c in &st.cases[1..] {
        for t in &c.targets {
            assert!(
                t.bias_um.abs() < 60.0,
                "{} {}: bias {:.1} µm, want < 60 (seeded: <= 30)",
                c.name,
                t.name,
                t.bias_um
            );
        }
    }
}

#[test]
#[ignore = "the full study: 20 experiments x 31 frames, two estimators; run with --release"]
fn paper_study_full() {
    let methods = [
        (Estimator::Paper, true),
        (Estimator::Fit, false),
        (Estimator::Fit, true),
    ];
    let studies = run_study(20, &CameraModel::default(), &methods);
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("paper-study");
    std::fs::create_dir_all(&out).unwrap();
    let labels = ["paper-interp", "fit-mean", "fit-interp"];
    for (st, label) in studies.iter().zip(labels) {
        let text = rigd::report::study_tables(st);
        println!("== {label}\n{text}");
        std::fs::write(out.join(format!("{label}.txt")), &text).unwrap();
        std::fs::write(
            out.join(format!("{label}.json")),
            rigd::report::study_json(st),
        )
        .unwrap();
        // The same charts `rigctl report` writes for a session (src/figures.rs).
        for c in 0..3 {
            let png = rigd::figures::figure4(st, c).png().unwrap();
            std::fs::write(out.join(format!("{label}-figure4-case{}.png", c + 1)), png).unwrap();
        }
        let png = rigd::figures::figure5(st).png().unwrap();
        std::fs::write(out.join(format!("{label}-figure5.png")), png).unwrap();
    }
    // The Cramér–Rao bound of one frame for each target, at a typical start: in the
    // measurement channel alone, and in all three (the pipeline measures in the channels
    // weighted by their ink contrast).
    let board = Board::paper();
    let cam = CameraModel::default();
    let mut crb = String::from(
        "Cramér–Rao bound, one frame (µm, along the offset): green alone, all three channels\n",
    );
    for n in NAMES {
        let i = board.targets.iter().position(|t| t.name == n).unwrap();
        let view = View::at([387.0, 387.0]);
        let b = rigd::sim::crb::offset_crb_um(&board, &cam, i, view);
        let all = rigd::sim::crb::offset_crb_um_channels(&board, &cam, i, view, &[0, 1, 2]);
        crb.push_str(&format!("{n}: {:.2}, {:.2}\n", b[0], all[0]));
    }
    println!("{crb}");
    std::fs::write(out.join("crb.txt"), crb).unwrap();
    println!("written to {}", out.display());
    // docs/paper-tables.md: 15.0x and 26.8x with seed 2015 (16.7x and 32x in green alone);
    // about half of each.
    let (g2, g3) = gains(&studies[0]);
    assert!(
        g2 >= 8.0 && g3 >= 15.0,
        "paper estimator gains {g2:.2}x, {g3:.2}x, want >= 8x and >= 15x"
    );
}
