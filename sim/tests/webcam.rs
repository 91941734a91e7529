//! The webcam effects, each measured on rendered frames (or on the model that draws them):
//! profiles, tilt, distortion, lateral colour, Bayer + crosstalk + demosaicing, gamma,
//! sharpening, 4:2:0 / YUYV chroma, flicker bands, auto-exposure wander, lens-shading
//! correction, rough edges, uneven ink, the leadscrew, the webcam Cramér–Rao bound.

mod common;
use common::*;
use image::RgbImage;
use rigd_sim::board::{Clutter, ClutterShape};
use rigd_sim::camera::{CameraModel, Cfa, ChromaSubsampling, Demosaic, Gamma, Uncompressed};
use rigd_sim::frames::{mjpeg_round_trip, subsample_chroma, FrameEffects};
use rigd_sim::motion::{Axis, AxisParams, Leadscrew};
use rigd_sim::render::expected_rgb;
use rigd_sim::{Board, FrameRenderer, SceneRenderer, SimRigConfig, View};
use std::time::Instant;

/// A board with nothing on it but `clutter`, neutral paper and ink (every channel sees it).
fn bare_board(clutter: Vec<Clutter>) -> Board {
    let mut b = Board::paper();
    b.targets.clear();
    b.clutter = clutter;
    b.paper_rgb = [0.9; 3];
    b.ink_rgb = [0.1; 3];
    b
}

fn disk(centre_um: [f64; 2], radius_um: f64) -> Clutter {
    Clutter {
        centre_um,
        shape: ClutterShape::Disk { radius_um },
    }
}

/// The view that puts board point `p_um` at image offset `off_px` from the frame centre
/// (ideal lens).
fn view_putting(cam: &CameraModel, p_um: [f64; 2], off_px: [f64; 2]) -> View {
    let s = cam.scale_um_per_px;
    View::at([
        p_um[0] - s * (cam.width as f64 / 2.0 + off_px[0]),
        p_um[1] - s * (cam.height as f64 / 2.0 + off_px[1]),
    ])
}

/// Ink coverage moments of one channel of an expected image (RGB f32) in the box
/// `[x0, y0, x1, y1]`: (weight, mean x, mean y, var x, var y).
fn moments(rgb: &[f32], width: u32, ch: usize, paper: f64, bx: [u32; 4]) -> [f64; 5] {
    let (mut s, mut sx, mut sy, mut sxx, mut syy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for y in bx[1]..bx[3] {
        for x in bx[0]..bx[2] {
            let v = rgb[((y * width + x) * 3) as usize + ch] as f64;
            let w = paper - v;
            let (xf, yf) = (x as f64, y as f64);
            s += w;
            sx += w * xf;
            sy += w * yf;
            sxx += w * xf * xf;
            syy += w * yf * yf;
        }
    }
    let (mx, my) = (sx / s, sy / s);
    [s, mx, my, sxx / s - mx * mx, syy / s - my * my]
}

fn quiet_flat(cam: CameraModel) -> CameraModel {
    CameraModel {
        psf_sigma_px: 0.7,
        ..quiet(cam)
    }
}

#[test]
fn profiles_are_named_and_a_table_overrides_its_profile() {
    assert_eq!(
        CameraModel::profile("ideal").unwrap(),
        CameraModel::default()
    );
    for name in rigd_sim::camera::PROFILES {
        let cam = CameraModel::profile(name).unwrap();
        cam.validate().unwrap();
        // Written out and read back, a profile's camera is the same camera.
        let text = toml::to_string(&cam).unwrap();
        assert_eq!(toml::from_str::<CameraModel>(&text).unwrap(), cam, "{name}");
    }
    let webcam = CameraModel::profile("webcam").unwrap();
    assert_eq!(webcam.cfa, Cfa::Rggb);
    assert_eq!(webcam.mjpeg_chroma, ChromaSubsampling::Yuv420);
    let c: CameraModel =
        toml::from_str("profile = \"webcam\"\nmjpeg_quality = 70\nwidth = 320").unwrap();
    assert_eq!(
        c,
        CameraModel {
            mjpeg_quality: Some(70),
            width: 320,
            ..webcam.clone()
        }
    );
    let stress = CameraModel::profile("stress").unwrap();
    assert_eq!(
        (stress.mjpeg_quality, stress.tilt_y_deg, stress.psf_sigma_px),
        (Some(50), 3.0, 1.2)
    );
    // Without a profile the table starts from the ideal camera.
    let c: CameraModel = toml::from_str("width = 320").unwrap();
    assert_eq!(c.cfa, Cfa::None);
    let e = toml::from_str::<CameraModel>("profile = \"phone\"")
        .unwrap_err()
        .to_string();
    assert!(e.contains("profile") && e.contains("phone"), "{e}");
    let e = toml::from_str::<CameraModel>("profile = \"webcam\"\nwidht = 3")
        .unwrap_err()
        .to_string();
    assert!(e.contains("unknown field `widht`"), "{e}");
    // The sim rig's config selects it as `[camera] profile`.
    let rig = SimRigConfig::parse("[camera]\nprofile = \"webcam\"\n", "test").unwrap();
    assert_eq!(rig.camera, webcam);
    let rig = SimRigConfig::profile("webcam").unwrap();
    assert_eq!((rig.camera, rig.leadscrew), (webcam, Leadscrew::webcam()));
    let bad = CameraModel {
        distortion_k1: -0.9,
        ..CameraModel::default()
    };
    assert_eq!(bad.validate().unwrap_err().field, "distortion_k1");
}

#[test]
fn tilt_changes_the_local_scale_across_the_frame() {
    // Tilt about y by 2°: the right side recedes. A disk 13 px across, seen 500 px left and
    // right of the centre: the local scale is f/Z ∝ (1 − tanθ·x/f) vertically and its square
    // horizontally (x the image position).
    let cam = CameraModel {
        width: 1280,
        height: 96,
        tilt_y_deg: 2.0,
        ..quiet_flat(CameraModel::default())
    };
    let board = bare_board(vec![disk([100_000.0, 100_000.0], 10_000.0)]);
    let sigma2 = cam.psf_sigma_px.powi(2) + 1.0 / 12.0;
    let paper = 0.9 * cam.white_dn;
    let size_at = |x_off: f64| {
        let view = view_putting(&cam, [100_000.0, 100_000.0], [x_off, 0.0]);
        let c = view.project(&cam, 1, [100_000.0, 100_000.0]);
        let roi = [(c[0] - 25.0) as u32, 20, 50, 56];
        let img = expected_rgb(&board, &cam, &view, roi, 1.0);
        let m = moments(&img, 50, 1, paper, [0, 0, 50, 56]);
        // Semi-axes of the ellipse: var = a²/4 + blur; and where it sits (from the centre).
        [
            2.0 * (m[3] - sigma2).sqrt(),
            2.0 * (m[4] - sigma2).sqrt(),
            c[0] - 639.5,
        ]
    };
    let t = 2f64.to_radians().tan();
    let (l, r) = (size_at(-500.0), size_at(500.0));
    // The disk's image centre sits where the projection puts it: about ±500 px.
    let k = |x: f64| 1.0 - t * x / cam.focal_length_px;
    let (xl, xr) = (l[2], r[2]);
    let want_v = k(xr) / k(xl);
    let want_h = want_v * want_v;
    let (got_h, got_v) = (r[0] / l[0], r[1] / l[1]);
    eprintln!("tilt 2°: width ratio right/left {got_h:.4} (want {want_h:.4}), height {got_v:.4} (want {want_v:.4})");
    assert!((got_h - want_h).abs() < 0.003, "{got_h} vs {want_h}");
    assert!((got_v - want_v).abs() < 0.003, "{got_v} vs {want_v}");
    // A few percent: "local µm/px varies by a few percent across the frame".
    assert!(want_v < 0.97 && want_h < 0.94);
}

#[test]
fn a_tilted_circle_is_an_ellipse_centred_off_its_projected_centre() {
    let cam = CameraModel {
        width: 1000,
        height: 240,
        tilt_y_deg: 3.0,
        ..quiet_flat(CameraModel::default())
    };
    let centre = [200_000.0, 100_000.0];
    let r_um = 40_000.0;
    let board = bare_board(vec![disk(centre, r_um)]);
    let view = view_putting(&cam, centre, [300.0, 0.0]);
    let projected = view.project(&cam, 1, centre);
    // The image of the circle: the exact ellipse's centre is halfway between its extremes.
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    for k in 0..7200 {
        let a = k as f64 / 7200.0 * std::f64::consts::TAU;
        let p = view.project(
            &cam,
            1,
            [centre[0] + r_um * a.cos(), centre[1] + r_um * a.sin()],
        );
        for i in 0..2 {
            lo[i] = lo[i].min(p[i]);
            hi[i] = hi[i].max(p[i]);
        }
    }
    let ellipse = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
    let roi = [(lo[0] - 8.0) as u32, (lo[1] - 8.0) as u32, 0, 0];
    let (w, h) = ((hi[0] - lo[0] + 16.0) as u32, (hi[1] - lo[1] + 16.0) as u32);
    let img = expected_rgb(&board, &cam, &view, [roi[0], roi[1], w, h], 1.0);
    let m = moments(&img, w, 1, 0.9 * cam.white_dn, [0, 0, w, h]);
    let centroid = [roi[0] as f64 + m[1], roi[1] as f64 + m[2]];
    let shift = ellipse[0] - projected[0];
    eprintln!(
        "3° tilt, r 52 px: projected centre {projected:?}, ellipse centre {ellipse:?}, rendered centroid {centroid:?}"
    );
    assert!(
        (centroid[0] - ellipse[0]).abs() < 0.005 && (centroid[1] - ellipse[1]).abs() < 0.005,
        "centroid {centroid:?} vs ellipse {ellipse:?}"
    );
    // The ellipse's centre lies towards the near side of the projected centre (the near half
    // of the circle images larger), by ≈ tanθ·r²/f = 0.14 px here (≈ 110 µm on the board).
    assert!(shift < -0.08 && shift > -0.3, "shift {shift} px");
    assert!((ellipse[1] - projected[1]).abs() < 0.01);
}

#[test]
fn distortion_moves_points_by_the_brown_model() {
    let (k1, k2) = (-0.05, 0.01);
    let cam = CameraModel {
        width: 1280,
        height: 720,
        distortion_k1: k1,
        distortion_k2: k2,
        ..quiet_flat(CameraModel::default())
    };
    let p = [300_000.0, 200_000.0];
    let board = bare_board(vec![disk(p, 1_500.0)]);
    let f = cam.focal_length_px;
    let pp = [639.5, 359.5];
    for off in [[500.0, 300.0], [-250.0, 100.0], [600.0, -340.0]] {
        let view = view_putting(&cam, p, off);
        let r2 = (off[0] * off[0] + off[1] * off[1]) / (f * f);
        let g = 1.0 + k1 * r2 + k2 * r2 * r2;
        let want = [pp[0] + off[0] * g, pp[1] + off[1] * g];
        let got = view.project(&cam, 1, p);
        assert!((got[0] - want[0]).abs() < 1e-9 && (got[1] - want[1]).abs() < 1e-9);
        // The rendered dot sits there too.
        let (x0, y0) = ((want[0] - 8.0) as u32, (want[1] - 8.0) as u32);
        let img = expected_rgb(&board, &cam, &view, [x0, y0, 17, 17], 1.0);
        let m = moments(&img, 17, 1, 0.9 * cam.white_dn, [0, 0, 17, 17]);
        let c = [x0 as f64 + m[1], y0 as f64 + m[2]];
        let radial = (off[0].hypot(off[1])) * (g - 1.0);
        eprintln!(
            "offset {off:?}: Brown displacement {radial:.3} px, dot at {c:?} (model {want:?})"
        );
        assert!(
            (c[0] - want[0]).abs() < 0.01 && (c[1] - want[1]).abs() < 0.01,
            "{c:?} vs {want:?}"
        );
    }
}

#[test]
fn lateral_colour_magnifies_red_and_shrinks_blue() {
    let cam = CameraModel {
        width: 1280,
        height: 120,
        lateral_colour_r: 1e-3,
        lateral_colour_b: -1e-3,
        ..quiet_flat(CameraModel::default())
    };
    let p = [300_000.0, 200_000.0];
    let board = bare_board(vec![disk(p, 3_000.0)]);
    let view = view_putting(&cam, p, [600.0, 0.0]);
    let img = expected_rgb(&board, &cam, &view, [1220, 50, 30, 20], 1.0);
    let x = |ch| 1220.0 + moments(&img, 30, ch, 0.9 * cam.white_dn, [0, 0, 30, 20])[1];
    let (r, g, b) = (x(0), x(1), x(2));
    eprintln!("lateral colour ±1e-3 at 600 px: R {r:.3}, G {g:.3}, B {b:.3}");
    assert!((g - 1239.5).abs() < 0.01, "{g}");
    assert!(
        (r - g - 0.6).abs() < 0.01 && (g - b - 0.6).abs() < 0.01,
        "{r} {g} {b}"
    );
}

/// A frame of `board` through `cam` (one view, frame 0).
fn frame(board: &Board, cam: &CameraModel, view: View) -> RgbImage {
    let r = FrameRenderer::new(board.clone(), cam.clone(), 3).unwrap();
    let v = view.camera_um;
    r.render_at(0, v)
}

#[test]
fn bayer_crosstalk_desaturates_and_demosaicing_colours_edges() {
    let base = CameraModel {
        width: 96,
        height: 64,
        cfa: Cfa::Rggb,
        ..quiet_flat(CameraModel::default())
    };
    // Red ink filling the frame: each channel mixes in `crosstalk` of the others.
    let mut red = Board::paper();
    red.targets.clear();
    red.clutter = vec![Clutter {
        centre_um: [0.0, 0.0],
        shape: ClutterShape::Rect {
            width_um: 1e6,
            height_um: 1e6,
        },
    }];
    let c = 0.1;
    let cam = CameraModel {
        crosstalk: c,
        ..base.clone()
    };
    let img = frame(&red, &cam, View::at([-37_000.0, -25_000.0]));
    let ink = red.ink_rgb.map(|v| v * cam.white_dn);
    let sum: f64 = ink.iter().sum();
    let px = img.get_pixel(48, 32).0;
    for ch in 0..3 {
        let want = (1.0 - 3.0 * c) * ink[ch] + c * sum;
        assert!(
            (px[ch] as f64 - want).abs() < 0.8,
            "channel {ch}: {} vs {want}",
            px[ch]
        );
    }
    // A neutral vertical edge: no colour without a mosaic; false colour with one, less with
    // the edge-aware demosaicing.
    let mut edge = bare_board(vec![Clutter {
        centre_um: [-500_000.0 + 0.3 * 774.0, 0.0],
        shape: ClutterShape::Rect {
            width_um: 1e6,
            height_um: 1e6,
        },
    }]);
    edge.ink_rgb = [0.1; 3];
    let false_colour = |cam: &CameraModel| {
        let img = frame(&edge, cam, View::at([-48.0 * 774.0, -32.0 * 774.0]));
        img.pixels()
            .map(|p| (p.0[0] as f64 - p.0[1] as f64).abs() + (p.0[2] as f64 - p.0[1] as f64).abs())
            .sum::<f64>()
    };
    let none = false_colour(&CameraModel {
        cfa: Cfa::None,
        gamma: Gamma::Srgb,
        ..base.clone()
    });
    let bilinear = false_colour(&base);
    let aware = false_colour(&CameraModel {
        demosaic: Demosaic::EdgeAware,
        ..base.clone()
    });
    eprintln!(
        "false colour (sum |R−G|+|B−G|): none {none}, bilinear {bilinear}, edge-aware {aware}"
    );
    assert!(none < 1.0, "{none}");
    assert!(bilinear > 500.0, "{bilinear}");
    assert!(aware < 0.5 * bilinear, "{aware} vs {bilinear}");
}

#[test]
fn gamma_follows_the_srgb_curve_and_lens_shading_is_partly_corrected() {
    let board = bare_board(Vec::new());
    let cam = CameraModel {
        width: 64,
        height: 48,
        gamma: Gamma::Srgb,
        ..quiet_flat(CameraModel::default())
    };
    let img = frame(&board, &cam, View::at([0.0, 0.0]));
    let lin = 0.9 * cam.white_dn / 255.0;
    let want = 255.0 * (1.055 * f64::powf(lin, 1.0 / 2.4) - 0.055);
    let got = img.get_pixel(32, 24).0[1] as f64;
    assert!((got - want).abs() <= 0.6, "{got} vs sRGB {want}");
    // Vignetting 0.4, the camera undoing half of it: the corner keeps (1 − 0.4r²)/(1 − 0.2r²).
    let cam = CameraModel {
        width: 64,
        height: 48,
        vignetting: 0.4,
        vignetting_correction: 0.5,
        ..quiet_flat(CameraModel::default())
    };
    let img = frame(&board, &cam, View::at([0.0, 0.0]));
    let r2 = cam.radius2(0.0, 0.0);
    let centre = 0.9 * cam.white_dn;
    let want = centre * (1.0 - 0.4 * r2) / (1.0 - 0.2 * r2);
    let got = img.get_pixel(0, 0).0[1] as f64;
    assert!((got - want).abs() <= 0.6, "corner {got} vs {want}");
    assert!(got > centre * (1.0 - 0.4 * r2) + 20.0);
}

#[test]
fn sharpening_overshoots_at_edges() {
    let mut board = bare_board(vec![Clutter {
        centre_um: [-500_000.0, 0.0],
        shape: ClutterShape::Rect {
            width_um: 1e6,
            height_um: 1e6,
        },
    }]);
    board.ink_rgb = [0.3; 3];
    let (amount, sigma_s) = (0.8, 1.5);
    let profile = |amount: f64| {
        let cam = CameraModel {
            width: 64,
            height: 16,
            sharpen_amount: amount,
            sharpen_sigma_px: sigma_s,
            ..quiet_flat(CameraModel::default())
        };
        // The edge (board x = 0) at image x = 31.8.
        let img = frame(&board, &cam, View::at([-32.3 * 774.0, -8.0 * 774.0]));
        (0..64)
            .map(|x| img.get_pixel(x, 8).0[1] as f64)
            .collect::<Vec<_>>()
    };
    let (paper, ink) = (0.9 * 235.0, 0.3 * 235.0);
    let plain = profile(0.0);
    let sharp = profile(amount);
    // The unsharp mask of a blurred step: (1 + a)·Φ(x/σe) − a·Φ(x/σt), σe the edge's blur
    // (lens and pixel), σt² = σe² + σs².
    let phi = |x: f64| 0.5 * libm::erfc(-x / std::f64::consts::SQRT_2);
    let se = (0.49f64 + 1.0 / 12.0).sqrt();
    let st = (se * se + sigma_s * sigma_s).sqrt();
    let want: Vec<f64> = (0..64)
        .map(|k| {
            let x = k as f64 - 31.8;
            ink + (paper - ink) * ((1.0 + amount) * phi(x / se) - amount * phi(x / st))
        })
        .collect();
    let hi = |p: &[f64]| p.iter().cloned().fold(0.0, f64::max);
    let lo = |p: &[f64]| p.iter().cloned().fold(255.0, f64::min);
    eprintln!(
        "edge paper {paper} ink {ink}: plain {}..{}, sharpened {}..{} (model {:.1}..{:.1})",
        lo(&plain),
        hi(&plain),
        lo(&sharp),
        hi(&sharp),
        lo(&want),
        hi(&want)
    );
    assert!(hi(&plain) <= paper + 1.0 && lo(&plain) >= ink - 1.0);
    // Halos of ~10 % of the 141 DN step on both sides, where the model puts them.
    assert!(
        hi(&sharp) > paper + 10.0 && lo(&sharp) < ink - 10.0,
        "{sharp:?}"
    );
    for (k, (g, w)) in sharp.iter().zip(&want).enumerate() {
        assert!((g - w).abs() < 2.5, "x = {k}: {g} vs model {w:.1}");
    }
}

/// Chroma (Cr, JFIF) of a pixel.
fn cr(p: &image::Rgb<u8>) -> f64 {
    let [r, g, b] = p.0.map(f64::from);
    0.5 * r - 0.418_688 * g - 0.081_312 * b
}

fn luma(p: &image::Rgb<u8>) -> f64 {
    let [r, g, b] = p.0.map(f64::from);
    0.299 * r + 0.587 * g + 0.114 * b
}

#[test]
fn four_two_zero_spreads_a_red_line_over_two_pixels_and_yuyv_over_two_columns() {
    // A 1-px red line, vertical at x = 9, horizontal at y = 9, on grey.
    let img = RgbImage::from_fn(32, 32, |x, y| {
        if x == 9 || y == 9 {
            image::Rgb([200, 60, 60])
        } else {
            image::Rgb([128, 128, 128])
        }
    });
    let grey_cr = cr(&image::Rgb([128, 128, 128]));
    // Chroma along row 20 (crossing the vertical line) and column 20 (the horizontal one).
    let spread = |out: &RgbImage| {
        let along_x: Vec<f64> = (6..13)
            .map(|x| cr(out.get_pixel(x, 20)) - grey_cr)
            .collect();
        let along_y: Vec<f64> = (6..13)
            .map(|y| cr(out.get_pixel(20, y)) - grey_cr)
            .collect();
        let width = |v: &[f64]| {
            let peak = v.iter().cloned().fold(0.0, f64::max);
            v.iter().filter(|&&c| c > 0.3 * peak).count()
        };
        (width(&along_x), width(&along_y))
    };
    let full = mjpeg_round_trip(&img, 100, ChromaSubsampling::Yuv444);
    let q420 = mjpeg_round_trip(&img, 100, ChromaSubsampling::Yuv420);
    let mut yuyv = img.clone();
    subsample_chroma(&mut yuyv, ChromaSubsampling::Yuv422);
    eprintln!(
        "chroma width (px across, px down): 4:4:4 {:?}, 4:2:0 {:?}, YUYV {:?}",
        spread(&full),
        spread(&q420),
        spread(&yuyv)
    );
    assert_eq!(spread(&full), (1, 1));
    assert_eq!(spread(&q420), (2, 2));
    assert_eq!(spread(&yuyv), (2, 1));
    // Luma keeps its full resolution: the pixel beside the line stays grey.
    for out in [&q420, &yuyv] {
        assert!((luma(out.get_pixel(8, 20)) - 128.0).abs() < 3.0);
        assert!((luma(out.get_pixel(9, 20)) - luma(img.get_pixel(9, 20))).abs() < 3.0);
    }
    // And a webcam frame with MJPEG off goes out as YUYV.
    let cam = CameraModel {
        width: 32,
        height: 32,
        uncompressed: Uncompressed::Yuyv,
        ..quiet_flat(CameraModel::default())
    };
    let f = frame(&Board::paper(), &cam, View::at([0.0, 0.0]));
    assert_eq!(f.dimensions(), (32, 32));
}

/// Least-squares fit of `y ≈ m + a·cos(w·i) + b·sin(w·i)`: amplitude relative to m, and
/// phase φ of `cos(w·i + φ)`.
fn sinusoid(y: &[f64], w: f64) -> (f64, f64) {
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = nalgebra::Vector3::<f64>::zeros();
    for (i, v) in y.iter().enumerate() {
        let r = nalgebra::Vector3::new(1.0, (w * i as f64).cos(), (w * i as f64).sin());
        ata += r * r.transpose();
        atb += r * *v;
    }
    let x = ata.lu().solve(&atb).unwrap();
    (x[1].hypot(x[2]) / x[0], (-x[2]).atan2(x[1]))
}

#[test]
fn flicker_bands_modulate_the_rows_at_the_mains_period() {
    let cam = CameraModel {
        width: 16,
        height: 720,
        flicker_band_depth: 0.2,
        exposure_ms: 8.0,
        row_time_us: 30.0,
        flicker_hz: 100.0,
        ..quiet_flat(CameraModel::default())
    };
    let r = FrameRenderer::new(bare_board(Vec::new()), cam.clone(), 4).unwrap();
    let rows = |seq: u64| {
        let img = r.render_at(seq, [0.0, 0.0]);
        (0..720)
            .map(|y| {
                (0..16)
                    .map(|x| img.get_pixel(x, y).0[1] as f64)
                    .sum::<f64>()
                    / 16.0
            })
            .collect::<Vec<f64>>()
    };
    // Period: 1 / (100 Hz · 30 µs) = 333 rows; depth 0.2 · sinc(100 Hz · 8 ms) = 0.047.
    let w = std::f64::consts::TAU * 100.0 * 30e-6;
    let x = std::f64::consts::PI * 0.8;
    let want = 0.2 * x.sin() / x;
    let (a0, p0) = sinusoid(&rows(0), w);
    let (a1, p1) = sinusoid(&rows(1), w);
    let (off, _) = sinusoid(&rows(0), 1.5 * w);
    eprintln!("flicker bands: amplitude {a0:.4} / {a1:.4} (want {want:.4}), off-period {off:.4}, phases {p0:.3} {p1:.3}");
    assert!(
        (a0 / want - 1.0).abs() < 0.02 && (a1 / want - 1.0).abs() < 0.02,
        "{a0} {a1} vs {want}"
    );
    assert!(off < 0.3 * want, "{off}");
    // The bands roll: 100 Hz x 33.3 ms = 3⅓ cycles per frame, so the next frame's bands are
    // a third of a cycle on.
    let d = (p1 - p0).rem_euclid(std::f64::consts::TAU);
    let third = std::f64::consts::TAU / 3.0;
    assert!((d - third).abs() < 0.01, "phase step {d} vs {third}");
    // No bands at an exposure of whole flicker periods (what anti-flicker settings pick).
    let cam10 = CameraModel {
        exposure_ms: 10.0,
        ..cam
    };
    let r10 = FrameRenderer::new(bare_board(Vec::new()), cam10, 4).unwrap();
    let img = r10.render_at(0, [0.0, 0.0]);
    let flat: Vec<f64> = (0..720).map(|y| img.get_pixel(0, y).0[1] as f64).collect();
    assert!(sinusoid(&flat, w).0 < 0.003);
}

#[test]
fn auto_exposure_wanders_within_its_bounds() {
    let cam = CameraModel {
        ae_wander_rms: 0.003,
        ae_gain_range: 0.3,
        ..CameraModel::default()
    };
    let g: Vec<f64> = (0..3000)
        .map(|i| FrameEffects::draw(&cam, 9, i).ae_gain)
        .collect();
    assert_eq!(g[0], 1.0);
    let steps: Vec<f64> = g.windows(2).map(|w| w[1] - w[0]).collect();
    let rms = (steps.iter().map(|d| d * d).sum::<f64>() / steps.len() as f64).sqrt();
    let spread = g.iter().cloned().fold(0.0, f64::max) - g.iter().cloned().fold(9.0, f64::min);
    eprintln!("AE: step RMS {rms:.5} (want 0.003), range over 3000 frames {spread:.3}");
    assert!((rms / 0.003 - 1.0).abs() < 0.08, "{rms}");
    assert!(spread > 0.05, "a random walk wanders: {spread}");
    // Tight bounds: it reflects off them and never leaves.
    let tight = CameraModel {
        ae_gain_range: 0.01,
        ..cam.clone()
    };
    let g: Vec<f64> = (0..3000)
        .map(|i| FrameEffects::draw(&tight, 9, i).ae_gain)
        .collect();
    assert!(g.iter().all(|&v| (0.99..=1.01).contains(&v)));
    assert!(g.iter().any(|&v| v > 1.009) && g.iter().any(|&v| v < 0.991));
    // The frame's brightness follows the gain.
    let qc = CameraModel {
        width: 32,
        height: 24,
        ..quiet_flat(cam)
    };
    let r = FrameRenderer::new(bare_board(Vec::new()), qc.clone(), 9).unwrap();
    let mean = |i: u64| {
        let img = r.render_at(i, [0.0, 0.0]);
        img.pixels().map(|p| p.0[1] as f64).sum::<f64>() / (32.0 * 24.0)
    };
    let (m0, m500) = (mean(0), mean(500));
    let g500 = FrameEffects::draw(&qc, 9, 500).ae_gain;
    assert!(
        (m500 / m0 - g500).abs() < 0.004,
        "{m500}/{m0} vs gain {g500}"
    );
}

#[test]
fn rough_edges_follow_the_seeded_radius_error() {
    // Exaggerated so one frame measures it: 150 µm RMS (0.19 px), 5 mm correlation.
    let cam = CameraModel {
        width: 96,
        height: 96,
        edge_roughness_um: 150.0,
        edge_roughness_corr_um: 5_000.0,
        ..quiet_flat(CameraModel::default())
    };
    let board = Board::paper();
    let ti = board.targets.iter().position(|t| t.name == "A").unwrap();
    let t = &board.targets[ti];
    let view = view_putting(&cam, t.centre_um, [0.3, 0.2]);
    let img = expected_rgb(&board, &cam, &view, [0, 0, 96, 96], 1.0);
    let c = view.board_to_image(&cam, t.centre_um);
    let (pg, ig) = (
        board.paper_rgb[1] * cam.white_dn,
        board.ink_rgb[1] * cam.white_dn,
    );
    let cov = |x: f64, y: f64| {
        // Bilinear sample of the green coverage.
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let at = |xi: f64, yi: f64| {
            (pg - img[((yi as usize) * 96 + xi as usize) * 3 + 1] as f64) / (pg - ig)
        };
        at(x0, y0) * (1.0 - fx) * (1.0 - fy)
            + at(x0 + 1.0, y0) * fx * (1.0 - fy)
            + at(x0, y0 + 1.0) * (1.0 - fx) * fy
            + at(x0 + 1.0, y0 + 1.0) * fx * fy
    };
    let s = cam.scale_um_per_px;
    let rim = t.outer.outer_radius_um();
    let edge = rigd_sim::print::RoughEdge::new(&cam, ti, 1, rim).unwrap();
    let (r0, r1) = (15_000.0 / s, 21_000.0 / s);
    let (mut meas, mut model) = (Vec::new(), Vec::new());
    for k in 0..72 {
        let a = k as f64 / 72.0 * std::f64::consts::TAU;
        let (dx, dy) = (a.cos(), a.sin());
        // ∫ coverage dr from mid-ring to paper = edge radius − r0 (for any symmetric blur).
        let n = 600;
        let dr = (r1 - r0) / n as f64;
        let integral: f64 = (0..n)
            .map(|i| {
                let r = r0 + (i as f64 + 0.5) * dr;
                cov(c[0] + r * dx, c[1] + r * dy) * dr
            })
            .sum();
        meas.push((r0 + integral) * s - rim);
        model.push(edge.at(dx, dy));
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (mm, md) = (mean(&meas), mean(&model));
    let cov_md: f64 = meas
        .iter()
        .zip(&model)
        .map(|(a, b)| (a - mm) * (b - md))
        .sum();
    let var = |v: &[f64], m: f64| v.iter().map(|a| (a - m).powi(2)).sum::<f64>();
    let corr = cov_md / (var(&meas, mm) * var(&model, md)).sqrt();
    let rms = |v: &[f64], m: f64| (var(v, m) / v.len() as f64).sqrt();
    eprintln!(
        "rough rim: measured RMS {:.1} µm, model {:.1} µm, correlation {corr:.3}",
        rms(&meas, mm),
        rms(&model, md)
    );
    assert!(corr > 0.9, "{corr}");
    assert!((rms(&meas, mm) / rms(&model, md) - 1.0).abs() < 0.2);
}

#[test]
fn uneven_ink_scales_the_ink_density() {
    let cam = CameraModel {
        width: 96,
        height: 96,
        ink_density_rms: 0.1,
        ink_density_corr_um: 3_000.0,
        ..quiet_flat(CameraModel::default())
    };
    let board = Board::paper();
    let t = board.target("A").unwrap();
    let view = view_putting(&cam, t.inner_centre_um(), [0.0, 0.0]);
    let img = expected_rgb(&board, &cam, &view, [0, 0, 96, 96], 1.0);
    let field = rigd_sim::print::InkDensity::new(&cam).unwrap();
    let s = cam.scale_um_per_px;
    let (pg, ig) = (board.paper_rgb[1], board.ink_rgb[1]);
    // The lens blurs the inked density: a pixel all inked sees ε averaged over its area and
    // the PSF (by quadrature on a grid 1/8 px apart).
    let sigma = cam.psf_sigma_px;
    let phi = |x: f64| 0.5 * libm::erfc(-x / (std::f64::consts::SQRT_2 * sigma));
    let weights: Vec<(f64, f64)> = (-48..=48)
        .map(|i| i as f64 / 8.0)
        .map(|t| (t, (phi(t + 0.5) - phi(t - 0.5)) / 8.0))
        .collect();
    let blurred = |p: [f64; 2]| -> f64 {
        let mut sum = 0.0;
        for &(ty, wy) in &weights {
            for &(tx, wx) in &weights {
                sum += wx * wy * field.at([p[0] + tx * s, p[1] + ty * s]);
            }
        }
        sum
    };
    let mut eps = Vec::new();
    // Pixels well inside the inner disk (radius 6 mm = 7.8 px) are all ink.
    for y in 46..50u32 {
        for x in 46..50u32 {
            let p = [
                view.camera_um[0] + (x as f64 + 0.5) * s,
                view.camera_um[1] + (y as f64 + 0.5) * s,
            ];
            let e = blurred(p);
            let want = cam.white_dn * (pg - (pg - ig) * (1.0 + e));
            let got = img[((y * 96 + x) * 3 + 1) as usize] as f64;
            assert!((got - want).abs() < 2e-3, "({x}, {y}): {got} vs {want}");
            eps.push(e);
        }
    }
    let spread = eps.iter().cloned().fold(-1.0, f64::max) - eps.iter().cloned().fold(1.0, f64::min);
    assert!(
        spread > 0.01,
        "the density varies across the disk: {spread}"
    );
}

#[test]
fn the_leadscrew_error_has_its_period_and_amplitude() {
    let screw = Leadscrew {
        error_um: 3.0,
        pitch_mm: 2.0,
        phase_deg: 30.0,
    };
    let axis = Axis::new(AxisParams {
        position_error_rms_um: 0.0,
        ..AxisParams::default()
    })
    .with_leadscrew(screw);
    let xs: Vec<f64> = (0..400).map(|i| i as f64 * 25.0).collect();
    let err: Vec<f64> = xs
        .iter()
        .map(|&x| {
            axis.set_position(x);
            axis.position_at(Instant::now()) - x
        })
        .collect();
    // The best-fitting period among 1.5..2.5 mm, and its amplitude.
    let fit = |pitch_um: f64| {
        let w = std::f64::consts::TAU * 25.0 / pitch_um;
        let (c, s): (f64, f64) = err.iter().enumerate().fold((0.0, 0.0), |(c, s), (i, e)| {
            (c + e * (w * i as f64).cos(), s + e * (w * i as f64).sin())
        });
        2.0 * c.hypot(s) / err.len() as f64
    };
    let best = (1500..=2500)
        .step_by(10)
        .max_by(|&a, &b| fit(a as f64).total_cmp(&fit(b as f64)))
        .unwrap();
    let amp = fit(2000.0);
    eprintln!("leadscrew: period {best} µm, amplitude {amp:.3} µm");
    assert!((best as i64 - 2000).abs() <= 20, "{best}");
    assert!((amp - 3.0).abs() < 0.01, "{amp}");
    // The controller does not see it.
    assert_eq!(axis.reported_um(Instant::now()), *xs.last().unwrap());
}

#[test]
fn webcam_and_stress_frames_are_deterministic() {
    for name in ["webcam", "stress"] {
        let cam = CameraModel {
            width: 160,
            height: 120,
            ..CameraModel::profile(name).unwrap()
        };
        let board = Board::paper();
        let origin = origin_centring(&board, &cam, "A");
        let a = FrameRenderer::new(board.clone(), cam.clone(), 5)
            .unwrap()
            .with_origin(origin);
        let b = FrameRenderer::new(board.clone(), cam.clone(), 5)
            .unwrap()
            .with_origin(origin);
        let f0 = a.render_at(2, [10.0, 0.0]);
        assert_eq!(f0, b.render_at(2, [10.0, 0.0]), "{name}");
        assert_ne!(f0, a.render_at(3, [10.0, 0.0]), "{name}");
        // The target is there: dark green in the middle, paper around.
        let g = |x, y| f0.get_pixel(x, y).0[1] as f64;
        assert!(
            g(5, 5) > g(80, 60) + 40.0 || g(5, 5) > 90.0,
            "{name}: {} {}",
            g(5, 5),
            g(80, 60)
        );
    }
}

#[test]
fn a_webcam_scene_renderer_matches_the_direct_render() {
    let cam = CameraModel {
        width: 200,
        height: 150,
        ..CameraModel::profile("webcam").unwrap()
    };
    let board = Board::paper();
    let origin = origin_centring(&board, &cam, "A");
    let view = View::at(origin);
    let direct = expected_rgb(&board, &cam, &view, [0, 0, 200, 150], 1.0);
    let fast = SceneRenderer::new(board, cam).expected_frame(&[view]);
    let worst = direct
        .iter()
        .zip(&fast)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(worst < 1e-3, "{worst}");
}

#[test]
fn the_webcam_cramer_rao_bound_comes_from_the_raw_mosaic() {
    let board = Board::paper();
    let view = View::at([0.3 * 774.0, 0.6 * 774.0]);
    let ideal = CameraModel::default();
    let webcam = CameraModel::profile("webcam").unwrap();
    let green = rigd_sim::crb::offset_crb_um(&board, &ideal, 6, view);
    let raw_ideal = rigd_sim::crb::offset_crb_um_raw(&board, &ideal, 6, view);
    let rgb_ideal = rigd_sim::crb::offset_crb_um_channels(&board, &ideal, 6, view, &[0, 1, 2]);
    let raw_webcam = rigd_sim::crb::offset_crb_um_raw(&board, &webcam, 6, view);
    eprintln!(
        "CRB target A, one frame: ideal green {green:?}, ideal RGB {rgb_ideal:?}, ideal raw {raw_ideal:?}, webcam raw mosaic {raw_webcam:?} µm"
    );
    // The ideal camera's raw samples are its RGB (finer quantisation only).
    assert!(raw_ideal[0] <= rgb_ideal[0] && raw_ideal[0] > 0.95 * rgb_ideal[0]);
    // A webcam's mosaic samples one channel per pixel, at half the conversion gain, through a
    // softer lens: 7.06 µm per axis for one frame (deterministic; 5 % either way).
    let near = |v: f64, want: f64| (v / want - 1.0).abs() < 0.05;
    assert!(
        near(raw_webcam[0], 7.06) && near(raw_webcam[1], 7.06),
        "{raw_webcam:?}"
    );
    assert!(near(raw_ideal[0], 2.45), "{raw_ideal:?}");
}
