//! Helpers shared by the sim integration tests: small cameras (fast to render) and a plain
//! ink-weighted centroid to see where a target landed in a frame.
#![allow(dead_code)]

use rigd_sim::camera::CameraModel;
use rigd_sim::{Board, View};

/// A 240x160 camera at the real 774 µm/px, looking at target "A" of the paper board.
pub fn small_cam() -> CameraModel {
    CameraModel {
        width: 240,
        height: 160,
        ..Default::default()
    }
}

/// The origin that puts target `name` near the centre of `cam`'s frame.
pub fn origin_centring(board: &Board, cam: &CameraModel, name: &str) -> [f64; 2] {
    let t = board.target(name).expect("target on the board");
    let s = cam.scale_um_per_px;
    [
        t.centre_um[0] - s * cam.width as f64 / 2.0 + 0.37 * s,
        t.centre_um[1] - s * cam.height as f64 / 2.0 + 0.21 * s,
    ]
}

/// A camera with every random effect off (noise-free, still, steady light).
pub fn quiet(cam: CameraModel) -> CameraModel {
    CameraModel {
        flicker_rms: 0.0,
        vibration_um: 0.0,
        read_noise_dn: 0.0,
        gain_e_per_dn: 1e12,
        vignetting: 0.0,
        light_gradient: 0.0,
        ..cam
    }
}

/// Ink-weighted centroid (green-channel darkening below `paper_dn`) of the whole frame, px.
pub fn ink_centroid(img: &image::RgbImage, paper_dn: f64) -> [f64; 2] {
    let (mut sx, mut sy, mut sw) = (0.0, 0.0, 0.0);
    for (x, y, p) in img.enumerate_pixels() {
        let w = (paper_dn - p.0[1] as f64).max(0.0);
        sx += w * x as f64;
        sy += w * y as f64;
        sw += w;
    }
    [sx / sw, sy / sw]
}

/// Where target `name`'s outer centre lands in the image with the line of sight at `los_um`.
pub fn predicted_px(
    board: &Board,
    cam: &CameraModel,
    origin: [f64; 2],
    los_um: [f64; 2],
    name: &str,
) -> [f64; 2] {
    let t = board.target(name).unwrap();
    View::at([origin[0] + los_um[0], origin[1] + los_um[1]]).board_to_image(cam, t.centre_um)
}

/// Pixels of a frame whose green value lies strictly between ink and paper (edge pixels).
pub fn edge_pixels(img: &image::RgbImage, ink_dn: f64, paper_dn: f64) -> usize {
    let (lo, hi) = (ink_dn + 4.0, paper_dn - 4.0);
    img.pixels()
        .filter(|p| {
            let g = p.0[1] as f64;
            g > lo && g < hi
        })
        .count()
}

/// Pixels of row `y` whose green value lies strictly between ink and paper.
pub fn row_edge_pixels(img: &image::RgbImage, y: u32, ink_dn: f64, paper_dn: f64) -> usize {
    let (lo, hi) = (ink_dn + 4.0, paper_dn - 4.0);
    (0..img.width())
        .filter(|&x| {
            let g = img.get_pixel(x, y).0[1] as f64;
            g > lo && g < hi
        })
        .count()
}

/// Pixels of row `y` at full ink (green within 8 DN of the ink level).
pub fn row_ink_pixels(img: &image::RgbImage, y: u32, ink_dn: f64) -> usize {
    (0..img.width())
        .filter(|&x| (img.get_pixel(x, y).0[1] as f64) < ink_dn + 8.0)
        .count()
}
