//! No target in view is dropped silently. Over frames of the sim's `ideal`,
//! soft-lens dim, `webcam` and `stress` cameras at random board placements, every board
//! target whose centre is in the frame is either detected or listed in `skipped` near it.

use rigd::pipeline::detect::{detect, DetectConfig};
use rigd::pipeline::layout::unseen_targets;
use rigd::pipeline::{process_frames, Combine, ProcessOptions};
use rigd::sim::frames::FrameRenderer;
use rigd::sim::{Board, CameraModel};

/// Counts over frames × targets in view.
#[derive(Debug, Default, Clone, Copy, PartialEq)]
struct Counts {
    measured: usize,
    skipped: usize,
    silent: usize,
}

/// Deterministic board placements (an R2 sequence): the paper board moved by up to ±250 mm
/// across and ±150 mm down, so that some targets leave the frame or are cut by its edge.
fn origin(i: u64) -> [f64; 2] {
    let f = |a: f64| (0.5 + a * (i as f64 + 1.0)).fract() * 2.0 - 1.0;
    [
        f(0.754_877_666_246_692_8) * 250_000.0,
        f(0.569_840_290_998_053_2) * 150_000.0,
    ]
}

/// Detect in `frames` frames of `cam` (seed `seed`, the board placed anew each frame) and
/// count each target in view as found, skipped or silently dropped: by the detection alone,
/// and with the board's unseen targets added to its `skipped` (one render and one detection
/// serve both).
fn count(cam: &CameraModel, frames: u64, seed: u64, light: f64) -> [Counts; 2] {
    let board = Board::paper();
    let mut c = [Counts::default(); 2];
    for i in 0..frames {
        let r = FrameRenderer::new(board.clone(), cam.clone(), seed + i)
            .unwrap()
            .with_origin(origin(seed * 31 + i));
        let mut img = r.render_at(i, [0.0, 0.0]);
        if light < 1.0 {
            // Dim light: the whole frame darker (as a shorter exposure would make it).
            img.pixels_mut()
                .for_each(|p| p.0 = p.0.map(|v| (v as f64 * light).round() as u8));
        }
        let view = r.views(i, &[[0.0, 0.0]])[0];
        let det = detect(&img, &DetectConfig::default());
        let found: Vec<[f64; 2]> = det.targets.iter().map(|t| t.outer_centre_px).collect();
        let reported: Vec<[f64; 2]> = det.skipped.iter().map(|s| s.centre_px).collect();
        let size = (cam.width, cam.height);
        let unseen = unseen_targets(&found, &reported, &board, cam.scale_um_per_px, size);
        let with_board: Vec<[f64; 2]> = (reported.iter().copied())
            .chain(unseen.iter().map(|s| s.centre_px))
            .collect();
        for (counts, skipped) in c.iter_mut().zip([reported, with_board]) {
            tally(counts, cam, &board, view, &found, &skipped);
        }
    }
    c
}

/// Counts each board target in view (projected through `view`) as found, skipped or
/// silently dropped.
fn tally(
    c: &mut Counts,
    cam: &CameraModel,
    board: &Board,
    view: rigd::sim::render::View,
    found: &[[f64; 2]],
    skipped: &[[f64; 2]],
) {
    for t in &board.targets {
        let p = view.project(cam, 1, t.centre_um);
        let (w, h) = (cam.width as f64, cam.height as f64);
        if p[0] < 0.0 || p[1] < 0.0 || p[0] > w - 1.0 || p[1] > h - 1.0 {
            continue;
        }
        let rim_px = t.outer.outer_radius_um() / cam.scale_um_per_px;
        let near = |q: &[f64; 2]| (q[0] - p[0]).hypot(q[1] - p[1]) < rim_px;
        if found.iter().any(near) {
            c.measured += 1;
        } else if skipped.iter().any(near) {
            c.skipped += 1;
        } else {
            c.silent += 1;
        }
    }
}

/// The ideal camera behind a softer lens (blur σ 1.2 px).
fn soft() -> CameraModel {
    CameraModel {
        psf_sigma_px: 1.2,
        ..CameraModel::default()
    }
}

fn profile(name: &str) -> CameraModel {
    CameraModel::profile(name).unwrap()
}

/// Every target in view over 20 frames of `cam` (seed `seed`, `light` times the light), the
/// board placed anew in each, is measured or skipped, and at least 98 % are measured: by the
/// detection alone and with the board's unseen targets.
fn none_dropped(name: &str, cam: &CameraModel, light: f64, seed: u64) {
    for (with_board, c) in [false, true].into_iter().zip(count(cam, 20, seed, light)) {
        eprintln!("{name} (seed {seed}, board {with_board}): {c:?}");
        assert_eq!(c.silent, 0, "{name} seed {seed}: {c:?}");
        let in_view = c.measured + c.skipped + c.silent;
        assert!(
            in_view >= 150,
            "{name} seed {seed}: few targets in view: {c:?}"
        );
        assert!(
            c.measured as f64 >= 0.98 * in_view as f64,
            "{name} seed {seed}: {c:?}"
        );
    }
}

// The cases (counts in docs/method.md, "No target dropped silently"), one test per camera
// so that they run in parallel. Measured: ideal, soft and webcam 220 of 220 (seed 7) and
// 220 of 224 (seed 101, 3-4 cut by the edge and skipped); stress 220 of 222 and 220 of 224,
// the rest cut by the edge and skipped. A fixed redness threshold of 0.4 finds no target at
// all on the webcam and stress frames (210-218 dropped silently).

#[test]
fn no_target_in_view_is_dropped_silently_ideal() {
    none_dropped("ideal", &CameraModel::default(), 1.0, 7);
}

#[test]
fn no_target_in_view_is_dropped_silently_behind_a_soft_lens_in_dim_light() {
    none_dropped("ideal, blur 1.2 px", &soft(), 1.0, 101);
    none_dropped("ideal, blur 1.2 px, dim", &soft(), 0.5, 7);
    none_dropped("ideal, blur 1.2 px, dim", &soft(), 0.5, 101);
}

#[test]
fn no_target_in_view_is_dropped_silently_webcam() {
    for seed in [7, 101] {
        none_dropped("webcam", &profile("webcam"), 1.0, seed);
    }
}

#[test]
fn no_target_in_view_is_dropped_silently_stress() {
    for seed in [7, 101] {
        none_dropped("stress", &profile("stress"), 1.0, seed);
    }
}

/// The pipeline's result with a board, on stress frames: every board target in view in
/// frame 0 is an object or a `skipped` entry. Measured: 16 `skipped` entries over the 6
/// placements (cut by the edge, ROIs leaving the frame, the board check's); no
/// target in view missing from the result.
#[test]
fn the_pipeline_result_accounts_for_every_target_in_view_on_stress_frames() {
    let cam = profile("stress");
    let board = Board::paper();
    let mut skipped_total = 0;
    for placement in 0..6u64 {
        let r = FrameRenderer::new(board.clone(), cam.clone(), 40 + placement)
            .unwrap()
            .with_origin(origin(placement * 7 + 3));
        let frames: Vec<_> = (0..3)
            .map(|i| r.render_at(i, [i as f64 * 80.0, 0.0]))
            .collect();
        let pos = [0.0, 80.0, 160.0];
        let opts = ProcessOptions {
            combine: Combine::Mean,
            scale_um_per_px: cam.scale_um_per_px,
            ..ProcessOptions::default()
        };
        let res = process_frames(&frames, &pos, &opts, Some(board.clone()))
            .unwrap()
            .result;
        let view = r.views(0, &[[0.0, 0.0]])[0];
        skipped_total += res.skipped.len();
        for t in &board.targets {
            let p = view.project(&cam, 1, t.centre_um);
            if p[0] < 0.0
                || p[1] < 0.0
                || p[0] > cam.width as f64 - 1.0
                || p[1] > cam.height as f64 - 1.0
            {
                continue;
            }
            let rim_px = t.outer.outer_radius_um() / cam.scale_um_per_px;
            let near = |q: [f64; 2]| (q[0] - p[0]).hypot(q[1] - p[1]) < rim_px;
            assert!(
                res.objects.iter().any(|o| near(o.centre_px))
                    || res.skipped.iter().any(|s| near(s.centre_px)),
                "placement {placement}: target {} at {p:?} is neither measured nor skipped: {:?}",
                t.name,
                res.skipped
            );
        }
    }
    eprintln!("skipped entries over 6 placements: {skipped_total}");
    assert!(
        skipped_total >= 6,
        "the stress frames skipped too little to test: {skipped_total}"
    );
}
