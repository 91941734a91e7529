//! Issue 11's study: how well rigd measures offsets on the sim's `webcam` camera (Bayer,
//! demosaicing, sRGB, sharpening, MJPEG 4:2:0, a tilted board, barrel distortion, a rough
//! print), on random layouts it has never seen, against the raw-sensor Cramér–Rao bound.
//!
//! Each layout puts 12 targets (the paper board's shapes) at random places over the frame,
//! each with a random offset of up to 5 mm in a random direction. Each repeat starts the
//! line of sight at a random place and takes the paper's three cases (1 raw frame; 10 frames
//! at 100 µm, k = 5; 20 frames at 50 µm, k = 10). Per target and case: bias (mean error over
//! repeats), std, and the bound `offset_crb_um_raw / √N`. The suite's test runs a few
//! repeats and holds the figures to tolerances near them; the full table is
//! `cargo test --release --test webcam_accuracy -- --ignored --nocapture study_full`.

use image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigd::pipeline::{Combine, Estimator, Pipeline, ProcessOptions};
use rigd::sim::board::Target;
use rigd::sim::crb::offset_crb_um_raw;
use rigd::sim::frames::FrameRenderer;
use rigd::sim::{Board, CameraModel};

/// A case of the paper's study: frames, step, k.
#[derive(Debug, Clone, Copy)]
struct Case {
    frames: usize,
    step_um: f64,
    k: u32,
}

const CASES: [Case; 3] = [
    Case {
        frames: 1,
        step_um: 0.0,
        k: 1,
    },
    Case {
        frames: 10,
        step_um: 100.0,
        k: 5,
    },
    Case {
        frames: 20,
        step_um: 50.0,
        k: 10,
    },
];

/// A layout the estimator has never seen: 12 targets on a jittered 4 x 3 grid over the
/// frame (kept 60 px inside it), offsets up to 5 mm in any direction.
fn random_board(seed: u64, cam: &CameraModel) -> Board {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut board = Board::paper();
    let shape = board.target("F").expect("paper board has F").clone();
    let (w_um, h_um) = (
        cam.width as f64 * cam.scale_um_per_px,
        cam.height as f64 * cam.scale_um_per_px,
    );
    let margin = 60.0 * cam.scale_um_per_px;
    let (cw, ch) = ((w_um - 2.0 * margin) / 4.0, (h_um - 2.0 * margin) / 3.0);
    board.targets = (0..12)
        .map(|i| {
            let (col, row) = ((i % 4) as f64, (i / 4) as f64);
            let centre_um = [
                margin + cw * (col + rng.gen_range(0.3..0.7)),
                margin + ch * (row + rng.gen_range(0.3..0.7)),
            ];
            let (r, a) = (
                rng.gen_range(0.0..5000.0),
                rng.gen_range(0.0..std::f64::consts::TAU),
            );
            Target {
                name: format!("T{i}"),
                centre_um,
                offset_um: [r * a.cos(), r * a.sin()],
                ..shape.clone()
            }
        })
        .collect();
    board.clutter.clear();
    board
}

fn options(case: Case, estimator: Estimator) -> ProcessOptions {
    ProcessOptions {
        k: case.k,
        estimator,
        combine: if case.k > 1 {
            Combine::Interp
        } else {
            Combine::Mean
        },
        axis_dir: [-1.0, 0.0],
        ..ProcessOptions::default()
    }
}

/// One repeat's frames of one case from `start_um`, with their axis positions.
fn render(
    frames: &FrameRenderer,
    start_um: [f64; 2],
    case: Case,
    sequence: &mut u64,
) -> Vec<(RgbImage, f64)> {
    (0..case.frames)
        .map(|i| {
            *sequence += 1;
            let x_um = i as f64 * case.step_um;
            let los_um = [start_um[0] + x_um, start_um[1]];
            (frames.render_at(*sequence, los_um), x_um)
        })
        .collect()
}

/// Each target's error (measured minus nominal) on one repeat's frames, by board index.
fn measure(
    board: &Board,
    imgs: &[(RgbImage, f64)],
    case: Case,
    estimator: Estimator,
) -> Vec<Option<[f64; 2]>> {
    let opts = options(case, estimator).validate().unwrap();
    let mut pipe = Pipeline::new(opts, Some(board.clone()));
    for (img, x_um) in imgs {
        pipe.push_at(img, *x_um, None).unwrap();
    }
    let result = pipe.finish().unwrap().result;
    board
        .targets
        .iter()
        .map(|t| {
            let o = result
                .objects
                .iter()
                .find(|o| o.name.as_deref() == Some(&t.name))?;
            Some([
                o.offset_um[0] - t.offset_um[0],
                o.offset_um[1] - t.offset_um[1],
            ])
        })
        .collect()
}

/// Per target of one case: bias and std of each axis, the bound, measured count.
#[derive(Debug, Clone, Copy, Default)]
struct TargetFigures {
    bias_um: [f64; 2],
    std_um: [f64; 2],
    crb_um: [f64; 2],
    n: usize,
}

/// RMS over targets and axes of one figure.
fn rms(figs: &[TargetFigures], f: impl Fn(&TargetFigures) -> [f64; 2]) -> f64 {
    let s: f64 = figs.iter().map(|t| f(t)[0].powi(2) + f(t)[1].powi(2)).sum();
    (s / (2 * figs.len()) as f64).sqrt()
}

fn figures(errors: &[Vec<Option<[f64; 2]>>], crb_um: &[[f64; 2]]) -> Vec<TargetFigures> {
    (0..crb_um.len())
        .map(|t| {
            let e: Vec<[f64; 2]> = errors.iter().filter_map(|r| r[t]).collect();
            let n = e.len();
            let mut fig = TargetFigures {
                crb_um: crb_um[t],
                n,
                ..Default::default()
            };
            for a in 0..2 {
                let mean = e.iter().map(|v| v[a]).sum::<f64>() / n as f64;
                let var = e.iter().map(|v| (v[a] - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
                fig.bias_um[a] = mean;
                fig.std_um[a] = var.sqrt();
            }
            fig
        })
        .collect()
}

/// The bound per target for one frame (its position in the frame fixes the local scale,
/// blur and light), averaged in variance over two sub-pixel phases.
fn crb_per_frame(frames: &FrameRenderer, starts: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let board = frames.scene().board().clone();
    let cam = frames.camera().clone();
    (0..board.targets.len())
        .map(|t| {
            let mut v = [0.0; 2];
            for (i, &s) in starts.iter().enumerate() {
                let view = frames.views(i as u64, &[s])[0];
                let b = offset_crb_um_raw(&board, &cam, t, view);
                (0..2).for_each(|a| v[a] += b[a].powi(2) / starts.len() as f64);
            }
            v.map(f64::sqrt)
        })
        .collect()
}

/// One study: `repeats` of every case with each estimator, on layout `seed`.
struct Study {
    fit: Vec<Vec<TargetFigures>>,
    paper: Vec<Vec<TargetFigures>>,
}

fn study(seed: u64, repeats: usize) -> Study {
    let cam = CameraModel::profile("webcam").unwrap();
    let board = random_board(seed, &cam);
    let frames = FrameRenderer::new(board.clone(), cam, seed).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed);
    let starts: Vec<[f64; 2]> = (0..repeats)
        .map(|_| [rng.gen_range(0.0..774.0), rng.gen_range(0.0..774.0)])
        .collect();
    let crb = crb_per_frame(&frames, &starts[..2.min(repeats)]);
    let mut out = Study {
        fit: vec![],
        paper: vec![],
    };
    let mut seq = 0;
    for case in CASES {
        let crb_case: Vec<[f64; 2]> = crb
            .iter()
            .map(|b| b.map(|v| v / (case.frames as f64).sqrt()))
            .collect();
        let (mut fit, mut paper) = (vec![], vec![]);
        for &start in &starts {
            let imgs = render(&frames, start, case, &mut seq);
            fit.push(measure(&board, &imgs, case, Estimator::Fit));
            paper.push(measure(&board, &imgs, case, Estimator::Paper));
        }
        out.fit.push(figures(&fit, &crb_case));
        out.paper.push(figures(&paper, &crb_case));
    }
    out
}

fn print(s: &Study) {
    println!(
        "| case | fit RMS std | CRB (raw) | ratio | fit RMS bias | max bias | paper RMS std |"
    );
    println!("|---|---|---|---|---|---|---|");
    for (i, case) in CASES.iter().enumerate() {
        let (f, p) = (&s.fit[i], &s.paper[i]);
        let max_bias = f
            .iter()
            .flat_map(|t| t.bias_um.map(f64::abs))
            .fold(0.0, f64::max);
        let (std, crb) = (rms(f, |t| t.std_um), rms(f, |t| t.crb_um));
        println!(
            "| {} x {} µm, k {} | {std:.2} | {crb:.2} | {:.2} | {:.1} | {max_bias:.1} | {:.1} |",
            case.frames,
            case.step_um,
            case.k,
            std / crb,
            rms(f, |t| t.bias_um),
            rms(p, |t| t.std_um),
        );
    }
}

/// The suite's check, 3 repeats of one layout. What it holds today, uncalibrated (one
/// global scale; measured at 4 repeats: fit std 1.3–1.7x the raw-sensor bound, the paper's
/// estimator 5–9x the fit's std, RMS bias 45–49 µm and up to 135 µm on 5 mm offsets): every
/// target measured in every repeat; the fit's scatter near the bound and well below the
/// paper's estimator's; the bias dominated by the local scale the global one ignores (the
/// tilt and the distortion), which calibration from the stage is for (docs/calibration.md).
#[test]
fn webcam_offsets_are_precise_but_biased_without_calibration() {
    let s = study(11, 3);
    print(&s);
    for (i, case) in CASES.iter().enumerate() {
        let f = &s.fit[i];
        assert!(
            f.iter().all(|t| t.n == 3),
            "{case:?}: a target was lost: {f:?}"
        );
        let (std, crb) = (rms(f, |t| t.std_um), rms(f, |t| t.crb_um));
        let paper = rms(&s.paper[i], |t| t.std_um);
        assert!(
            std < 2.5 * crb,
            "{case:?}: fit std {std:.2} vs bound {crb:.2}"
        );
        assert!(
            paper > 3.5 * std,
            "{case:?}: paper {paper:.1} vs fit {std:.2}"
        );
        let bias = rms(f, |t| t.bias_um);
        assert!(
            (25.0..80.0).contains(&bias),
            "{case:?}: RMS bias {bias:.1} µm"
        );
    }
}

#[test]
#[ignore = "the full study: cargo test --release --test webcam_accuracy -- --ignored --nocapture"]
fn study_full() {
    for seed in [11, 12, 13] {
        println!("layout {seed}, 20 repeats");
        print(&study(seed, 20));
    }
}
