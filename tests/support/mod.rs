//! Shared by the integration tests: a small board and camera, frames and `rigctl process`
//! folders rendered with the simulator's `SceneRenderer`; controller emulators for the
//! driver tests in [`emulated`]; the daemon, its clients and sessions in [`daemon`].
#![allow(dead_code)]

pub mod adversary;
pub mod daemon;
pub mod emulated;
pub mod firmware;
pub mod instances;
pub mod schema;
pub mod skip;
pub mod web;

use image::RgbImage;
use rigd::sim::render::{SceneRenderer, View};
use rigd::sim::{Board, CameraModel};
use std::path::Path;

/// One noisy frame of `scene`'s board with the camera at `view` (light 1, no flicker or
/// vibration: `rigd::sim::frames::FrameRenderer` adds those).
pub fn frame(scene: &SceneRenderer, view: View, seed: u64) -> RgbImage {
    let cam = scene.camera();
    RgbImage::from_raw(cam.width, cam.height, scene.expose(&[view], 1.0, seed))
        .expect("a frame-sized buffer")
}

/// A small board for quick tests: one horizontal and one vertical target.
pub const SMALL_BOARD: &str = r#"
name = "small"
[defaults]
outer = { kind = "ring", inner_radius_um = 13000.0, outer_radius_um = 17000.0 }
inner = { kind = "disk", radius_um = 6000.0 }
[[targets]]
name = "H"
centre_um = [62000.0, 77000.0]
offset_um = [2000.0, 0.0]
[[targets]]
name = "V"
centre_um = [170000.0, 77000.0]
offset_um = [0.0, 3000.0]
"#;

pub fn small_board() -> Board {
    Board::parse(SMALL_BOARD, "small.toml").unwrap()
}

pub fn small_camera() -> CameraModel {
    CameraModel {
        width: 300,
        height: 200,
        ..CameraModel::default()
    }
}

/// Write a `rigctl process` folder: `n` frames with the camera stepping `step_um` in +x
/// from `start_um`, `steps.csv` with the commanded positions.
pub fn write_folder(
    dir: &Path,
    board: &Board,
    cam: &CameraModel,
    start_um: [f64; 2],
    step_um: f64,
    n: usize,
    seed: u64,
) {
    std::fs::create_dir_all(dir.join("frames")).unwrap();
    let scene = SceneRenderer::new(board.clone(), cam.clone());
    let mut steps = String::from("index,position_um,note\n");
    for i in 0..n {
        let view = View::at([start_um[0] + step_um * i as f64, start_um[1]]);
        let img = frame(&scene, view, seed + i as u64);
        img.save(dir.join("frames").join(format!("{i:04}.png")))
            .unwrap();
        steps.push_str(&format!("{i},{},sim\n", step_um * i as f64));
    }
    std::fs::write(dir.join("steps.csv"), steps).unwrap();
}
