//! The `ideal` camera (the default) renders bit for bit what a renderer without the webcam
//! effects renders: checksums of frames computed at commit 357eef4, compared here.

mod common;
use common::*;
use rigd_sim::camera::{CameraModel, ChromaSubsampling};
use rigd_sim::render::{expected_rgb, View};
use rigd_sim::{Board, FrameRenderer};

/// FNV-1a, 64-bit: a checksum with no dependency.
fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}

fn frames_checksums(cam: CameraModel) -> Vec<u64> {
    let board = Board::paper();
    let origin = origin_centring(&board, &cam, "A");
    let r = FrameRenderer::new(board, cam, 11)
        .unwrap()
        .with_origin(origin);
    let mut out = vec![
        fnv(r.render_at(0, [0.0, 0.0]).as_raw()),
        fnv(r.render_at(7, [123.4, -56.7]).as_raw()),
    ];
    let moving: Vec<[f64; 2]> = (0..8).map(|k| [k as f64 * 40.0, 3.0]).collect();
    out.push(fnv(r.render(3, &moving).as_raw()));
    out
}

fn expected_checksum(cam: &CameraModel) -> u64 {
    let board = Board::paper();
    let view = View {
        camera_um: [1500.0, 800.0],
        roll_rad: 0.01,
        depth_um: 0.0,
    };
    let e = expected_rgb(&board, cam, &view, [0, 0, cam.width, cam.height], 1.0);
    let bytes: Vec<u8> = e.iter().flat_map(|v| v.to_le_bytes()).collect();
    fnv(&bytes)
}

fn print_or_compare(label: &str, got: &[u64], want: &[u64]) {
    eprintln!("{label}: {got:?}");
    assert_eq!(got, want, "{label}: the ideal camera's frames changed");
}

#[test]
fn the_ideal_camera_renders_as_before() {
    let small = small_cam();
    let mjpeg = CameraModel {
        mjpeg_quality: Some(80),
        ..small.clone()
    };
    let m420 = CameraModel {
        mjpeg_chroma: ChromaSubsampling::Yuv420,
        ..mjpeg.clone()
    };
    let mut got = frames_checksums(small.clone());
    got.extend(frames_checksums(mjpeg));
    got.extend(frames_checksums(m420));
    got.push(expected_checksum(&small));
    print_or_compare(
        "small raw, mjpeg 4:2:2, 4:2:0, expected",
        &got,
        &[
            17091301075724835666,
            13993852524449386604,
            14956491701849697443,
            6999257763804364,
            16783911398898152407,
            9385589960129724004,
            4844980148115849155,
            2918813986140527132,
            14664127798741558690,
            15550858173825659433,
        ],
    );
}

#[test]
fn the_ideal_camera_renders_full_frames_as_before() {
    let cam = CameraModel::default();
    let board = Board::paper();
    let r = FrameRenderer::new(board, cam.clone(), 1).unwrap();
    let got = vec![
        fnv(r.render_at(0, [0.0, 0.0]).as_raw()),
        fnv(r.render_at(5, [250.0, 0.0]).as_raw()),
        expected_checksum(&cam),
    ];
    print_or_compare(
        "full frame",
        &got,
        &[
            4402349043180363053,
            1839995572417679844,
            18231243525569180832,
        ],
    );
}

#[test]
fn the_ideal_crb_is_as_before() {
    let cam = CameraModel::default();
    let board = Board::paper();
    let view = View::at([0.3 * 774.0, 0.6 * 774.0]);
    let b = rigd_sim::crb::offset_crb_um(&board, &cam, 6, view);
    eprintln!("crb {b:?}");
    // To 1e-12, not to the bit: the Fisher information is one matrix product, whose
    // summation order may follow the CPU's vector width.
    let want = [3.4373871673459604, 3.43779072400179];
    for (g, w) in b.iter().zip(want) {
        assert!(
            (g / w - 1.0).abs() < 1e-12,
            "crb {b:?}, want {want:?}: the ideal camera's frames changed"
        );
    }
}
