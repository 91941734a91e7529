//! The pipeline's combine and registration modes on a small simulated scan.

use crate::support::*;
use rigd::pipeline::{
    process_frames, Combine, Estimator, ProcessOptions, Registration, ValidOptions,
};
use rigd::sim::render::SceneRenderer;
use rigd::sim::View;

const STEP_UM: f64 = 50.0;

fn scan(n: usize) -> (Vec<image::RgbImage>, Vec<f64>) {
    let scene = SceneRenderer::new(small_board(), small_camera());
    (0..n)
        .map(|i| {
            let pos = STEP_UM * i as f64;
            let view = View::at([123.0 + pos, 456.0]);
            (frame(&scene, view, 40 + i as u64), pos)
        })
        .unzip()
}

#[test]
fn every_mode_measures_the_nominal_offsets() {
    let (frames, pos) = scan(8);
    let board = small_board();
    for combine in [Combine::Interp, Combine::Splat, Combine::Mean] {
        for registration in [Registration::Image, Registration::Positions] {
            let opts = ProcessOptions {
                k: 4,
                combine,
                registration,
                estimator: Estimator::Fit,
                whole_frame: combine == Combine::Splat,
                ..ProcessOptions::default()
            };
            let done = process_frames(&frames, &pos, &opts, Some(board.clone())).unwrap();
            let r = &done.result;
            assert_eq!(r.objects.len(), 2);
            for o in &r.objects {
                let nominal = o.nominal_um.expect("matched to the board");
                // Measured: |error| <= 2.2 µm in every mode (seeds 40, 100-400: <= 2.25).
                for a in 0..2 {
                    assert!(
                        (o.offset_um[a] - nominal[a]).abs() < 5.0,
                        "{combine:?}/{registration:?} {:?}: {:?} vs {nominal:?}",
                        o.name,
                        o.offset_um
                    );
                }
                let k = if combine == Combine::Mean { 1.0 } else { 4.0 };
                assert_eq!(o.effective_pixel_um, 774.0 / k);
                assert!(o.sigma_um.is_some(), "the fit gives an uncertainty");
            }
            // Image and positions agree to a few µm on every step (measured: <= 3.4 µm).
            for s in &r.steps {
                assert!(s.residual_um[0].hypot(s.residual_um[1]) < 7.0, "{s:?}");
            }
            let n_images = done.images.len();
            match combine {
                Combine::Mean => assert_eq!(n_images, 0),
                Combine::Interp => assert_eq!(n_images, 2),
                Combine::Splat => {
                    assert_eq!(n_images, 3);
                    let w = done
                        .images
                        .iter()
                        .find(|i| i.name == "whole-frame")
                        .unwrap();
                    assert_eq!(w.image.dimensions(), (300 * 4, 200 * 4));
                }
            }
        }
    }
}

#[test]
fn a_stale_frame_shows_in_the_step_residuals() {
    let (mut frames, pos) = scan(4);
    // Frame 2 is a repeat of frame 1: the axis moved, the picture did not.
    frames[2] = frames[1].clone();
    let opts = ProcessOptions {
        estimator: Estimator::Fit,
        ..ProcessOptions::default()
    };
    let r = process_frames(&frames, &pos, &opts, None).unwrap().result;
    // Measured: 0.12 µm off on both steps (up to 2.5 µm with other noise seeds).
    assert!(r.steps[1].residual_um[0].abs() < 5.0, "{:?}", r.steps[1]);
    assert!(
        (r.steps[2].residual_um[0] - STEP_UM).abs() < 5.0,
        "a missed 50 µm step reads as +50 µm: {:?}",
        r.steps[2]
    );
}

#[test]
fn frame_of_another_size_and_bad_options_are_errors() {
    let (frames, _) = scan(1);
    let mut p = rigd::pipeline::Pipeline::new(ValidOptions::default(), None);
    p.push(&frames[0], 0.0).unwrap();
    let e = p
        .push(&image::RgbImage::new(10, 10), 50.0)
        .unwrap_err()
        .to_string();
    assert!(e.contains("frame 1") && e.contains("size"), "{e}");
    let bad = ProcessOptions {
        k: 0,
        ..ProcessOptions::default()
    };
    let Err(e) = process_frames(&frames, &[0.0], &bad, None) else {
        panic!("k = 0 accepted")
    };
    assert_eq!(e.to_string(), "`k` must be 1..=32, got 0");
    let none = rigd::pipeline::Pipeline::new(ValidOptions::default(), None);
    assert!(none.finish().is_err(), "no frames");
}
