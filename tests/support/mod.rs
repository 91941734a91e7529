//! Shared by the integration tests: scenes rendered with rigd_sim, only where targets are;
//! controller emulators for the driver tests in [`emulated`].
#![allow(dead_code)]

pub mod emulated;

use image::RgbImage;
use rigd::sim::render::{add_noise, expected_rgb, View};
use rigd::sim::{Board, CameraModel};
use std::path::Path;

/// SplitMix64: a tiny seeded generator for the tests' random starts and jitter.
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f64 {
        let u = self.uniform().max(1e-300);
        let v = self.uniform();
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }
}

/// Render a frame: every target's neighbourhood from the renderer (noise included), the
/// rest plain paper under the camera's illumination (nothing there to measure).
pub fn render_rois(
    board: &Board,
    cam: &CameraModel,
    view: &View,
    light: f64,
    seed: u64,
) -> RgbImage {
    let (w, h) = (cam.width, cam.height);
    let mut img = RgbImage::from_fn(w, h, |u, v| {
        let lum = cam.white_dn * light * cam.illumination(u as f64, v as f64);
        image::Rgb(
            board
                .paper_rgb
                .map(|p| (lum * p).round().clamp(0.0, 255.0) as u8),
        )
    });
    for (i, t) in board.targets.iter().enumerate() {
        let c = view.board_to_image(cam, t.centre_um);
        let r = t.outer.outer_radius_um() / cam.scale_um_per_px + 5.0 * cam.psf_sigma_px + 3.0;
        let x0 = (c[0] - r).floor().max(0.0) as u32;
        let y0 = (c[1] - r).floor().max(0.0) as u32;
        let x1 = ((c[0] + r).ceil() as u32 + 1).min(w);
        let y1 = ((c[1] + r).ceil() as u32 + 1).min(h);
        if x1 <= x0 || y1 <= y0 {
            continue;
        }
        let roi = [x0, y0, x1 - x0, y1 - y0];
        let exp = expected_rgb(board, cam, view, roi, light);
        let px = add_noise(
            &exp,
            roi[2],
            cam,
            seed.wrapping_mul(131).wrapping_add(i as u64),
        );
        for yy in 0..roi[3] {
            for xx in 0..roi[2] {
                let k = ((yy * roi[2] + xx) * 3) as usize;
                img.put_pixel(x0 + xx, y0 + yy, image::Rgb([px[k], px[k + 1], px[k + 2]]));
            }
        }
    }
    img
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
    let mut steps = String::from("index,position_um,note\n");
    for i in 0..n {
        let view = View::at([start_um[0] + step_um * i as f64, start_um[1]]);
        let img = render_rois(board, cam, &view, 1.0, seed + i as u64);
        img.save(dir.join("frames").join(format!("{i:04}.png")))
            .unwrap();
        steps.push_str(&format!("{i},{},sim\n", step_um * i as f64));
    }
    std::fs::write(dir.join("steps.csv"), steps).unwrap();
}
