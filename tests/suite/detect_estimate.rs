//! Detection and centre estimation on the simulated rig: robustness of detection, accuracy
//! of the estimators against the Cramér–Rao bound, and the errors on bad input.

use image::RgbImage;
use rigd::pipeline::detect::{detect, measurement_channel, Candidate, DetectConfig};
use rigd::pipeline::estimate::{estimate, EstimateError};
use rigd::pipeline::plane::{Plane, Roi};
use rigd::pipeline::Estimator;
use rigd::sim::crb::offset_crb_um;
use rigd::sim::render::{add_noise, expected_rgb, render_frame};
use rigd::sim::{Board, CameraModel, View};

const BOARDS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/config/boards");

fn jpeg_round_trip(img: &RgbImage, quality: u8) -> RgbImage {
    let mut buf = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut buf, quality)
        .encode_image(img)
        .unwrap();
    image::load_from_memory(&buf).unwrap().to_rgb8()
}

/// Deterministic sub-pixel camera positions spread over the unit square (R2 sequence).
fn subpixel(i: usize) -> [f64; 2] {
    let f = |a: f64| (0.5 + a * (i as f64 + 1.0)).fract();
    [f(0.754_877_666_246_692_8), f(0.569_840_290_998_053_2)]
}

/// The true outer centre (image px) of every target.
fn truth(board: &Board, cam: &CameraModel, view: &View) -> Vec<[f64; 2]> {
    board
        .targets
        .iter()
        .map(|t| view.board_to_image(cam, t.centre_um))
        .collect()
}

fn nearest(c: [f64; 2], cands: &[Candidate]) -> Option<&Candidate> {
    cands.iter().min_by(|a, b| {
        let da = (a.outer_centre_px[0] - c[0]).hypot(a.outer_centre_px[1] - c[1]);
        let db = (b.outer_centre_px[0] - c[0]).hypot(b.outer_centre_px[1] - c[1]);
        da.total_cmp(&db)
    })
}

/// Every target of `board` found once, within `tol_px` of its true centre, and with the
/// right offset direction. Measured: centres within 0.18 px of the truth on the clean frames
/// (tolerance 0.3), 0.25 px after JPEG (tolerance 0.5).
fn assert_finds_all(board: &Board, cam: &CameraModel, view: &View, img: &RgbImage, tol_px: f64) {
    let det = detect(img, &DetectConfig::default());
    assert_eq!(
        det.targets.len(),
        board.targets.len(),
        "targets {:?}\nskipped {:?}",
        det.targets,
        det.skipped
    );
    for (t, c) in board.targets.iter().zip(truth(board, cam, view)) {
        let found = nearest(c, &det.targets).unwrap();
        let d = (found.outer_centre_px[0] - c[0]).hypot(found.outer_centre_px[1] - c[1]);
        assert!(d < tol_px, "target {} found {d:.2} px off", t.name);
        let ic = view.board_to_image(cam, t.inner_centre_um());
        let di = (found.inner_centre_px[0] - ic[0]).hypot(found.inner_centre_px[1] - ic[1]);
        assert!(di < tol_px, "target {} inner found {di:.2} px off", t.name);
        // Measured: rim radii within 0.16 px in every frame of these tests.
        let rim = t.outer.outer_radius_um() / cam.scale_um_per_px;
        assert!((found.outer_radii_px[1] - rim).abs() < 0.4, "{found:?}");
        assert!(found
            .roi
            .fits_in(img.width() as usize, img.height() as usize));
    }
}

#[test]
fn finds_the_twelve_paper_targets_under_vignetting_gradient_and_noise() {
    let board = Board::paper();
    let cam = CameraModel {
        vignetting: 0.45,
        light_gradient: 0.3,
        ..Default::default()
    };
    let view = View::at([0.37 * 774.0, 0.81 * 774.0]);
    let img = render_frame(&board, &cam, &view, 1.0, 11);
    assert_finds_all(&board, &cam, &view, &img, 0.3);
    let det = detect(&img, &DetectConfig::default());
    assert!(det.skipped.is_empty(), "{:?}", det.skipped);
    // Red ink on white paper: green has the contrast.
    assert_eq!(measurement_channel(&img, &det), 1);
    // A dim frame (70 % light) with the board rolled by 1°.
    let rolled = View {
        camera_um: [0.11 * 774.0, 0.64 * 774.0],
        roll_rad: 1f64.to_radians(),
        depth_um: 0.0,
    };
    let img = render_frame(&board, &cam, &rolled, 0.7, 15);
    assert_finds_all(&board, &cam, &rolled, &img, 0.3);
}

#[test]
fn survives_a_jpeg_round_trip_at_quality_70() {
    let board = Board::paper();
    let cam = CameraModel::default();
    let view = View::at([0.52 * 774.0, 0.13 * 774.0]);
    let img = jpeg_round_trip(&render_frame(&board, &cam, &view, 1.0, 12), 70);
    assert_finds_all(&board, &cam, &view, &img, 0.5);
}

#[test]
fn rejects_clutter_and_skips_the_target_cut_by_the_edge() {
    let board = Board::load(format!("{BOARDS}/clutter.toml")).unwrap();
    let cam = CameraModel::default();
    let view = View::at([0.2 * 774.0, 0.4 * 774.0]);
    let img = jpeg_round_trip(&render_frame(&board, &cam, &view, 1.0, 13), 70);
    let det = detect(&img, &DetectConfig::default());
    let whole: Vec<_> = board.targets.iter().filter(|t| t.name != "cut").collect();
    assert_eq!(det.targets.len(), whole.len(), "{:?}", det.targets);
    for t in whole {
        let c = view.board_to_image(&cam, t.centre_um);
        let f = nearest(c, &det.targets).unwrap();
        // Measured: within 0.16 px.
        assert!((f.outer_centre_px[0] - c[0]).hypot(f.outer_centre_px[1] - c[1]) < 0.4);
    }
    // The cut target is reported with the reason; no clutter is.
    let cut = view.board_to_image(&cam, board.target("cut").unwrap().centre_um);
    assert_eq!(det.skipped.len(), 1, "{:?}", det.skipped);
    let s = &det.skipped[0];
    assert!(s.reason.contains("frame edge"), "{}", s.reason);
    // Measured: 0.09 px (the cut is on the left edge: y is still symmetric).
    assert!((s.centre_px[1] - cut[1]).abs() < 0.3, "{s:?} vs {cut:?}");
}

#[test]
fn finds_targets_made_of_two_rings() {
    let board = Board::load(format!("{BOARDS}/two-rings.toml")).unwrap();
    let cam = CameraModel::default();
    let view = View::at([0.6 * 774.0, 0.3 * 774.0]);
    let img = render_frame(&board, &cam, &view, 1.0, 14);
    assert_finds_all(&board, &cam, &view, &img, 0.3);
    let det = detect(&img, &DetectConfig::default());
    for c in &det.targets {
        let [hole, rim] = c.inner_radii_px;
        assert!(
            // Measured: within 0.15 px (0.18 px with other noise seeds).
            (hole - 4000.0 / 774.0).abs() < 0.4 && (rim - 7500.0 / 774.0).abs() < 0.4,
            "{c:?}"
        );
    }
    // The fit handles an inner ring too. Measured: 2.0, 0.6, 1.9 µm off (up to 4.3 µm with
    // other noise seeds).
    let plane = Plane::from_channel(&img, 1);
    for (t, c) in board.targets.iter().zip(&det.targets) {
        let e = estimate(&plane, c, Estimator::Fit, 1.0).unwrap();
        let err = (e.offset_px()[0] * 774.0 - t.offset_um[0]).abs();
        assert!(err < 6.0, "target {}: {err:.1} µm off", t.name);
    }
}

/// One noisy frame of one target's neighbourhood only (fast), as an image of that size,
/// and the true outer centre and offset in its pixel coordinates.
fn target_frame(
    board: &Board,
    cam: &CameraModel,
    idx: usize,
    view: &View,
    seed: u64,
) -> (RgbImage, [f64; 2], [f64; 2]) {
    let t = &board.targets[idx];
    let c = view.board_to_image(cam, t.centre_um);
    let half = 32.0;
    let (x0, y0) = ((c[0] - half).floor() as u32, (c[1] - half).floor() as u32);
    let n = 2 * half as u32 + 1;
    let exp = expected_rgb(board, cam, view, [x0, y0, n, n], 1.0);
    let img = RgbImage::from_raw(n, n, add_noise(&exp, n, cam, seed)).unwrap();
    let ci = view.board_to_image(cam, t.inner_centre_um());
    (
        img,
        [c[0] - x0 as f64, c[1] - y0 as f64],
        [ci[0] - c[0], ci[1] - c[1]],
    )
}

struct Stats {
    bias_um: [f64; 2],
    std_um: [f64; 2],
    /// RMS of the fit's own one-sigma figure.
    reported_um: [f64; 2],
}

fn offset_stats(
    board: &Board,
    cam: &CameraModel,
    idx: usize,
    frames: usize,
    est: Estimator,
) -> Stats {
    let s = cam.scale_um_per_px;
    let mut errs = Vec::new();
    let mut rep = [0.0; 2];
    for i in 0..frames {
        let p = subpixel(i + 100 * idx);
        let view = View::at([p[0] * s, p[1] * s]);
        let (img, _, off) = target_frame(board, cam, idx, &view, 1000 + i as u64);
        let det = detect(&img, &DetectConfig::default());
        assert_eq!(det.targets.len(), 1, "frame {i}: {:?}", det.skipped);
        let plane = Plane::from_channel(&img, measurement_channel(&img, &det));
        let e = estimate(&plane, &det.targets[0], est, 1.0).unwrap();
        let o = e.offset_px();
        errs.push([(o[0] - off[0]) * s, (o[1] - off[1]) * s]);
        if let Some(c) = e.offset_cov_px2 {
            rep[0] += c[0][0] * s * s;
            rep[1] += c[1][1] * s * s;
        }
    }
    let n = errs.len() as f64;
    let mean = |k: usize| errs.iter().map(|e| e[k]).sum::<f64>() / n;
    let bias_um = [mean(0), mean(1)];
    let std_um = [0, 1].map(|k| {
        (errs
            .iter()
            .map(|e| (e[k] - bias_um[k]).powi(2))
            .sum::<f64>()
            / (n - 1.0))
            .sqrt()
    });
    Stats {
        bias_um,
        std_um,
        reported_um: rep.map(|v| (v / n).sqrt()),
    }
}

/// The bound averaged (in variance) over a few sub-pixel positions.
fn crb(board: &Board, cam: &CameraModel, idx: usize) -> [f64; 2] {
    let s = cam.scale_um_per_px;
    let mut v = [0.0; 2];
    for i in 0..3 {
        let p = subpixel(7 * i + 3);
        let b = offset_crb_um(board, cam, idx, View::at([p[0] * s, p[1] * s]));
        v[0] += b[0] * b[0] / 3.0;
        v[1] += b[1] * b[1] / 3.0;
    }
    v.map(f64::sqrt)
}

#[test]
fn fit_is_unbiased_and_near_the_cramer_rao_bound() {
    let board = Board::paper();
    let cam = CameraModel::default();
    // A (horizontal 100 µm) and Fv (vertical 5000 µm).
    for idx in [6, 5] {
        let bound = crb(&board, &cam, idx);
        let st = offset_stats(&board, &cam, idx, 40, Estimator::Fit);
        eprintln!(
            "target {}: fit bias {:.2?} µm, std {:.2?} µm, reported {:.2?} µm, CRB {:.2?} µm",
            board.targets[idx].name, st.bias_um, st.std_um, st.reported_um, bound
        );
        // Measured: bias A +0.51, -0.56 µm, Fv +1.17, +0.08 µm (the standard error of a
        // 40-frame mean is ~0.5 µm); std 0.8-1.1x the bound.
        for k in 0..2 {
            assert!(st.bias_um[k].abs() < 2.5, "bias {:?}", st.bias_um);
            assert!(
                st.std_um[k] < 1.5 * bound[k],
                "std {:?} vs CRB {:?}",
                st.std_um,
                bound
            );
            // The fit's own uncertainty is honest.
            let r = st.reported_um[k] / st.std_um[k];
            assert!(
                r > 0.6 && r < 1.6,
                "reported {:?} vs std {:?}",
                st.reported_um,
                st.std_um
            );
        }
    }
}

#[test]
fn paper_estimator_is_pixel_quantised() {
    let board = Board::paper();
    let cam = CameraModel::default();
    let st = offset_stats(&board, &cam, 6, 40, Estimator::Paper);
    let fit = offset_stats(&board, &cam, 6, 10, Estimator::Fit);
    eprintln!(
        "paper estimator on target A: bias {:.1?} µm, std {:.1?} µm",
        st.bias_um, st.std_um
    );
    // Measured: std 114, 117 µm against the fit's 2.0, 4.3 µm (10 frames): 56x and 27x.
    for k in 0..2 {
        assert!(
            st.std_um[k] > 12.0 * fit.std_um[k],
            "paper {:?} vs fit {:?}",
            st.std_um,
            fit.std_um
        );
    }
}

#[test]
fn bad_input_gives_errors_that_name_the_problem() {
    let board = Board::paper();
    let cam = CameraModel::default();
    let (img, _, _) = target_frame(&board, &cam, 0, &View::default(), 1);
    let det = detect(&img, &DetectConfig::default());
    let g = det.targets[0].clone();
    let plane = Plane::from_channel(&img, 1);
    // The window leaves the plane.
    let small = plane.crop(Roi {
        x: 0,
        y: 0,
        w: 30,
        h: 30,
    });
    for est in [Estimator::Fit, Estimator::Paper] {
        let e = estimate(&small, &g, est, 1.0).unwrap_err();
        assert!(matches!(e, EstimateError::RoiOutside { .. }), "{e}");
        assert!(e.to_string().contains("outside the 30x30 plane"), "{e}");
    }
    // Blank paper: no ink.
    let mut blank = plane.clone();
    blank.data.iter_mut().for_each(|v| *v = 200.0);
    for est in [Estimator::Fit, Estimator::Paper] {
        let e = estimate(&blank, &g, est, 1.0).unwrap_err();
        assert!(matches!(e, EstimateError::NoInk { .. }), "{e}");
    }
    // Nonsense guess.
    let mut bad = g.clone();
    bad.outer_radii_px = [20.0, 10.0];
    let e = estimate(&plane, &bad, Estimator::Fit, 1.0).unwrap_err();
    assert!(e.to_string().contains("hole < rim"), "{e}");
    bad = g.clone();
    bad.outer_centre_px[0] = f64::NAN;
    assert!(matches!(
        estimate(&plane, &bad, Estimator::Fit, 1.0),
        Err(EstimateError::BadGuess(_))
    ));
    // A blank frame has no targets and no skipped regions.
    let det = detect(
        &RgbImage::from_pixel(64, 48, image::Rgb([200, 200, 190])),
        &DetectConfig::default(),
    );
    assert!(det.targets.is_empty() && det.skipped.is_empty());
}

/// The figures in docs/method.md: every target of the paper's board, raw and after an
/// MJPEG-like JPEG round trip. `cargo test --release --test suite detect_estimate:: -- --ignored
/// --nocapture study`.
#[test]
#[ignore = "a study (minutes): its figures are in docs/method.md"]
fn study_accuracy_of_every_target() {
    let board = Board::paper();
    let cam = CameraModel::default();
    let s = cam.scale_um_per_px;
    let frames = 100;
    println!("| target | CRB x, y (µm) | fit bias x, y | fit std x, y | fit σ reported | fit std, JPEG q70 | paper bias x, y | paper std x, y |");
    println!("|---|---|---|---|---|---|---|---|");
    for idx in 0..board.targets.len() {
        let bound = crb(&board, &cam, idx);
        // [fit, fit after JPEG, paper] errors, and the fit's reported variance.
        let mut errs: [Vec<[f64; 2]>; 3] = Default::default();
        let mut rep = 0.0;
        for i in 0..frames {
            let p = subpixel(i + 1000 * idx);
            let view = View::at([p[0] * s, p[1] * s]);
            let (img, _, off) = target_frame(&board, &cam, idx, &view, 5000 + i as u64);
            let jpeg = jpeg_round_trip(&img, 70);
            for (slot, (im, est)) in [
                (&img, Estimator::Fit),
                (&jpeg, Estimator::Fit),
                (&img, Estimator::Paper),
            ]
            .into_iter()
            .enumerate()
            {
                let det = detect(im, &DetectConfig::default());
                assert_eq!(det.targets.len(), 1);
                let plane = Plane::from_channel(im, measurement_channel(im, &det));
                let e = estimate(&plane, &det.targets[0], est, 1.0).unwrap();
                let o = e.offset_px();
                errs[slot].push([(o[0] - off[0]) * s, (o[1] - off[1]) * s]);
                if slot == 0 {
                    let c = e.offset_cov_px2.unwrap();
                    rep += (c[0][0] + c[1][1]) / 2.0 * s * s;
                }
            }
        }
        let ms = |e: &[[f64; 2]]| {
            let n = e.len() as f64;
            let m = [0, 1].map(|k| e.iter().map(|v| v[k]).sum::<f64>() / n);
            let sd = [0, 1]
                .map(|k| (e.iter().map(|v| (v[k] - m[k]).powi(2)).sum::<f64>() / (n - 1.0)).sqrt());
            (m, sd)
        };
        let (fb, fs) = ms(&errs[0]);
        let (_, js) = ms(&errs[1]);
        let (pb, ps) = ms(&errs[2]);
        println!(
            "| {} | {:.2}, {:.2} | {:+.2}, {:+.2} | {:.2}, {:.2} | {:.2} | {:.2}, {:.2} | {:+.0}, {:+.0} | {:.0}, {:.0} |",
            board.targets[idx].name,
            bound[0], bound[1], fb[0], fb[1], fs[0], fs[1], (rep / frames as f64).sqrt(), js[0], js[1], pb[0], pb[1], ps[0], ps[1]
        );
    }
}

/// The path a reconstruction takes: a detection on the camera frame, scaled to a k-times
/// finer grid, measured there with `px_per_camera_px = k`.
#[test]
fn a_scaled_guess_measures_a_finer_grid() {
    // k = 6 also exercises the fit's pixel stride on fine grids.
    for k in [3.0, 6.0] {
        scaled_guess_on_finer_grid(k);
    }
}

fn scaled_guess_on_finer_grid(k: f64) {
    let board = Board::paper();
    let cam = CameraModel::default();
    let fine = CameraModel {
        scale_um_per_px: cam.scale_um_per_px / k,
        psf_sigma_px: cam.psf_sigma_px * k,
        width: cam.width * k as u32,
        height: cam.height * k as u32,
        supersample: 3,
        ..cam.clone()
    };
    let view = View::at([0.41 * 774.0, 0.27 * 774.0]);
    let (img, _, off) = target_frame(&board, &cam, 3, &view, 21);
    let det = detect(&img, &DetectConfig::default());
    let c = &det.targets[0];
    // The coarse frame's origin in the full frame, to place the fine window.
    let t = &board.targets[3];
    let centre = view.board_to_image(&cam, t.centre_um);
    let x0 = (centre[0] - 32.0).floor();
    let y0 = (centre[1] - 32.0).floor();
    let full = c.translated([x0, y0]).scaled(k);
    let (fx0, fy0) = ((k * (x0 + 0.5) - 0.5) as u32, (k * (y0 + 0.5) - 0.5) as u32);
    let n = (65.0 * k) as u32;
    let exp = expected_rgb(&board, &fine, &view, [fx0, fy0, n, n], 1.0);
    let fimg = RgbImage::from_raw(n, n, add_noise(&exp, n, &fine, 22)).unwrap();
    let plane = Plane::from_channel(&fimg, 1);
    let guess = full.translated([-(fx0 as f64), -(fy0 as f64)]);
    let e = estimate(&plane, &guess, Estimator::Fit, k).unwrap();
    let rim_um = e.outer_radius_px / k * cam.scale_um_per_px;
    // Measured: -0.7 µm (k = 3), +0.2 µm (k = 6); up to 1.1 µm with other noise seeds.
    assert!((rim_um - 17000.0).abs() < 3.0, "rim {rim_um} µm");
    for (a, (&got, &want)) in e.offset_px().iter().zip(&off).enumerate() {
        let err_um = (got / k - want) * cam.scale_um_per_px;
        eprintln!("k = {k}, axis {a}: offset error {err_um:+.2} µm");
        // Measured: -1.89, -1.55 µm (k = 3), +0.41, +2.59 µm (k = 6); up to 2.7 µm with
        // other noise seeds.
        assert!(err_um.abs() < 5.0, "k = {k}, axis {a}: {err_um:.2} µm");
    }
}
