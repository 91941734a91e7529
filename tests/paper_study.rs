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
//! `paper_study_subset` runs 5 experiments in the default suite and holds them within 25 %
//! of README.md's figures; the full study (20 experiments, both estimators, tables and
//! figures written under target/) is
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

/// README.md's figures on the `ideal` camera, µm for raw / 10 @ 100 µm / 20 @ 50 µm: the
/// `paper` estimator's RMS std (the full study below) and the fit's (`rigctl demo --camera
/// ideal`, which combines by `mean`).
const README_PAPER_RMS_STD_UM: [f64; 3] = [93.0, 6.2, 3.5];
const README_FIT_RMS_STD_UM: [f64; 3] = [2.4, 0.8, 0.6];

/// `got` within 25 % of README's `want`, per case.
fn near_readme(what: &str, got: &[f64], want: [f64; 3]) {
    for (c, (&g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g / w - 1.0).abs() <= 0.25,
            "{what}, case {}: RMS std {g:.2} µm, README.md says {w} (within 25 %)",
            c + 1
        );
    }
}

#[test]
fn paper_study_subset() {
    // Coarser area integration (4x4 instead of 8x8 sub-samples on edge pixels) keeps the
    // default suite quick; the full study uses the camera's defaults.
    let cam = CameraModel {
        supersample: 4,
        ..CameraModel::default()
    };
    let studies = run_study(
        5,
        &cam,
        &[(Estimator::Paper, true), (Estimator::Fit, false)],
    );
    let (st, fit) = (&studies[0], &studies[1]);
    println!("{}", rigd::report::study_tables(st));
    println!("{}", rigd::report::study_tables(fit));
    for c in st.cases.iter().chain(&fit.cases) {
        for t in &c.targets {
            assert_eq!(
                t.n, 5,
                "{} {}: every run measures every target",
                c.name, t.name
            );
        }
    }
    // Seed 2015, measured: the paper's estimator 100.3 / 5.0 / 3.2 µm (gains 19.9x and
    // 31.4x), the fit 2.4 / 0.9 / 0.6 µm; largest |bias| averaged: the centroids' 31.2
    // and 34.4 µm (their systematic, docs/paper-tables.md), the fit's 0.6 µm. Five
    // experiments estimate README's 20: each figure within 25 % of README's.
    let rms = |s: &StudyStats| s.cases.iter().map(|c| c.rms_std_um).collect::<Vec<f64>>();
    near_readme("paper", &rms(st), README_PAPER_RMS_STD_UM);
    near_readme("fit", &rms(fit), README_FIT_RMS_STD_UM);
    let (g2, g3) = gains(st);
    assert!(
        g2 >= 15.0 && g3 >= 25.0,
        "averaging improves the std {g2:.2}x and {g3:.2}x (seeded: 19.9x, 31.4x)"
    );
    // The averaged cases measure the offsets they should, within the ~30 µm systematic of
    // thresholded centroids; the fit within README's 2.0 µm (over 20 repeats).
    for (s, most) in [(st, 40.0), (fit, 2.0)] {
        for c in &s.cases[1..] {
            for t in &c.targets {
                assert!(
                    t.bias_um.abs() < most,
                    "{} {}: bias {:.1} µm, want < {most}",
                    c.name,
                    t.name,
                    t.bias_um
                );
            }
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
