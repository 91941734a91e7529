//! Per-frame effects: determinism, flicker, vibration, MJPEG, all on a small camera.

mod common;
use common::*;
use rigd_sim::camera::{CameraModel, ChromaSubsampling};
use rigd_sim::{Board, FrameRenderer};

fn renderer(cam: CameraModel, seed: u64) -> FrameRenderer {
    let board = Board::paper();
    let origin = origin_centring(&board, &cam, "A");
    FrameRenderer::new(board, cam, seed)
        .unwrap()
        .with_origin(origin)
}

fn mean_green(img: &image::RgbImage) -> f64 {
    img.pixels().map(|p| p.0[1] as f64).sum::<f64>() / (img.width() * img.height()) as f64
}

#[test]
fn same_seed_same_frame_whatever_the_order() {
    let a = renderer(small_cam(), 42);
    let b = renderer(small_cam(), 42);
    let forward: Vec<_> = (0..3).map(|i| a.render_at(i, [10.0, 0.0])).collect();
    let backward: Vec<_> = (0..3).rev().map(|i| b.render_at(i, [10.0, 0.0])).collect();
    for i in 0..3 {
        assert_eq!(forward[i], backward[2 - i], "frame {i}");
    }
    // Successive frames differ (fresh noise), and another seed gives other frames.
    assert_ne!(forward[0], forward[1]);
    assert_ne!(
        forward[0],
        renderer(small_cam(), 43).render_at(0, [10.0, 0.0])
    );
}

#[test]
fn flicker_changes_the_brightness_frame_to_frame() {
    let steady = renderer(quiet(small_cam()), 1);
    let flicker = renderer(
        CameraModel {
            flicker_rms: 0.05,
            ..quiet(small_cam())
        },
        1,
    );
    let s: Vec<f64> = (0..6)
        .map(|i| mean_green(&steady.render_at(i, [0.0; 2])))
        .collect();
    let f: Vec<f64> = (0..6)
        .map(|i| mean_green(&flicker.render_at(i, [0.0; 2])))
        .collect();
    // Without flicker or noise every frame is identical; with 5 % flicker the mean level
    // moves by DN from frame to frame, by the gain drawn for that frame.
    assert!(s.windows(2).all(|w| w[0] == w[1]), "{s:?}");
    let spread =
        f.iter().cloned().fold(f64::MIN, f64::max) - f.iter().cloned().fold(f64::MAX, f64::min);
    assert!(spread > 2.0, "flicker spread {spread} DN: {f:?}");
    for (i, m) in f.iter().enumerate() {
        let fx = rigd_sim::frames::FrameEffects::draw(flicker.camera(), 1, i as u64);
        assert!(
            (m / s[0] - fx.light).abs() < 0.01,
            "frame {i}: {m} vs {} x {}",
            s[0],
            fx.light
        );
    }
}

#[test]
fn vibration_moves_the_scene_by_the_drawn_jitter() {
    let board = Board::paper();
    let cam = CameraModel {
        vibration_um: 300.0,
        ..quiet(small_cam())
    };
    let still = renderer(quiet(small_cam()), 5);
    let shaky = renderer(cam.clone(), 5);
    let paper = board.paper_rgb[1] * cam.white_dn;
    let c0 = ink_centroid(&still.render_at(0, [0.0; 2]), paper);
    for i in 0..3u64 {
        let fx = rigd_sim::frames::FrameEffects::draw(&cam, 5, i);
        let c = ink_centroid(&shaky.render_at(i, [0.0; 2]), paper);
        // The camera moved by +jitter, so the scene moved by -jitter in the image.
        for a in 0..2 {
            let want = -fx.jitter_um[a] / cam.scale_um_per_px;
            assert!(
                (c[a] - c0[a] - want).abs() < 0.02,
                "frame {i} axis {a}: moved {} px, jitter says {want}",
                c[a] - c0[a]
            );
        }
        assert!(fx.jitter_um[0].abs() + fx.jitter_um[1].abs() > 1.0);
    }
}

#[test]
fn mjpeg_round_trip_changes_the_frame_within_reason() {
    let raw = renderer(small_cam(), 9).render_at(0, [0.0; 2]);
    let cam = CameraModel {
        mjpeg_quality: Some(60),
        ..small_cam()
    };
    let jpg = renderer(cam.clone(), 9).render_at(0, [0.0; 2]);
    let diffs: Vec<u8> = raw
        .as_raw()
        .iter()
        .zip(jpg.as_raw())
        .map(|(a, b)| a.abs_diff(*b))
        .collect();
    let mean = diffs.iter().map(|&d| d as f64).sum::<f64>() / diffs.len() as f64;
    assert!(mean > 0.3 && mean < 6.0, "mean |raw - mjpeg| = {mean} DN");
    // Higher quality is closer to the raw frame.
    let q95 = renderer(
        CameraModel {
            mjpeg_quality: Some(95),
            ..cam.clone()
        },
        9,
    )
    .render_at(0, [0.0; 2]);
    let mean95 = raw
        .as_raw()
        .iter()
        .zip(q95.as_raw())
        .map(|(a, b)| a.abs_diff(*b) as f64)
        .sum::<f64>()
        / diffs.len() as f64;
    assert!(mean95 < mean, "q95 {mean95} vs q60 {mean}");
    // 4:2:0 loses more colour than 4:4:4 at the same quality.
    let chroma_err = |c: ChromaSubsampling| {
        let img = renderer(
            CameraModel {
                mjpeg_chroma: c,
                mjpeg_quality: Some(90),
                ..quiet(small_cam())
            },
            9,
        )
        .render_at(0, [0.0; 2]);
        let reference = renderer(quiet(small_cam()), 9).render_at(0, [0.0; 2]);
        img.pixels()
            .zip(reference.pixels())
            .map(|(a, b)| (a.0[0] as f64 - a.0[1] as f64 - (b.0[0] as f64 - b.0[1] as f64)).abs())
            .sum::<f64>()
    };
    let e444 = chroma_err(ChromaSubsampling::Yuv444);
    let e422 = chroma_err(ChromaSubsampling::Yuv422);
    let e420 = chroma_err(ChromaSubsampling::Yuv420);
    assert!(
        e444 < e422 && e422 < e420 && e420 > 1.2 * e444,
        "colour error 4:4:4 {e444}, 4:2:2 {e422}, 4:2:0 {e420}"
    );
}

#[test]
fn noise_has_the_configured_level() {
    let cam = CameraModel {
        read_noise_dn: 3.0,
        ..quiet(small_cam())
    };
    let quiet_frame = renderer(quiet(small_cam()), 3).render_at(0, [0.0; 2]);
    let noisy = renderer(cam, 3).render_at(0, [0.0; 2]);
    let d: Vec<f64> = quiet_frame
        .as_raw()
        .iter()
        .zip(noisy.as_raw())
        .map(|(a, b)| *b as f64 - *a as f64)
        .collect();
    let rms = (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
    // 3 DN read noise, plus rounding (both frames are quantised).
    assert!((rms - 3.0).abs() < 0.15, "rms {rms}");
}
