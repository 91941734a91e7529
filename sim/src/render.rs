//! The renderer: board + camera model + where the camera is -> what the sensor sees.
//!
//! Pixels integrate area: a pixel that straddles an edge is sampled on a fine sub-grid
//! (`CameraModel::supersample` per side) of the Gaussian-blurred edge profile, so a
//! sub-pixel move of the camera changes the image the way it does on a real sensor.
//! Pixels far from every edge are exactly ink or exactly paper. Image coordinates put pixel
//! centres at integers (OpenCV's convention): pixel (u, v) covers [u-0.5, u+0.5] x [v-0.5, v+0.5].

use crate::board::{Board, ClutterShape, Shape};
use crate::camera::CameraModel;
use image::RgbImage;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

/// Where the camera looks: the board point (µm) seen at the top-left corner of pixel (0, 0)
/// when the roll is zero, and a roll of the board about the image centre.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct View {
    pub camera_um: [f64; 2],
    pub roll_rad: f64,
}

impl View {
    pub fn at(camera_um: [f64; 2]) -> View {
        View {
            camera_um,
            roll_rad: 0.0,
        }
    }

    /// Image coordinates (pixel centres at integers) of a board point.
    pub fn board_to_image(&self, cam: &CameraModel, p_um: [f64; 2]) -> [f64; 2] {
        let s = cam.scale_um_per_px;
        let (cx, cy) = (cam.width as f64 / 2.0, cam.height as f64 / 2.0);
        // p = camera + s*c + s*R(roll)*(q - c), with q = image point + 0.5.
        let dx = (p_um[0] - self.camera_um[0]) / s - cx;
        let dy = (p_um[1] - self.camera_um[1]) / s - cy;
        let (sn, cs) = self.roll_rad.sin_cos();
        let qx = cs * dx + sn * dy + cx;
        let qy = -sn * dx + cs * dy + cy;
        [qx - 0.5, qy - 0.5]
    }
}

/// A circle edge in image coordinates: ink inside `radius_px` of `centre`.
#[derive(Debug, Clone, Copy)]
struct Disk {
    centre: [f64; 2],
    radius_px: f64,
    /// +1 adds ink, -1 removes it (the hole of a ring).
    sign: f64,
}

/// A filled rectangle (clutter), axis-aligned in the image.
#[derive(Debug, Clone, Copy)]
struct Rect {
    centre: [f64; 2],
    half: [f64; 2],
}

/// Everything inked on the board, in image coordinates for one view.
struct Ink {
    disks: Vec<Disk>,
    rects: Vec<Rect>,
}

fn shape_disks(out: &mut Vec<Disk>, centre: [f64; 2], shape: &Shape, s: f64) {
    match *shape {
        Shape::Disk { radius_um } => out.push(Disk {
            centre,
            radius_px: radius_um / s,
            sign: 1.0,
        }),
        Shape::Ring {
            inner_radius_um,
            outer_radius_um,
        } => {
            out.push(Disk {
                centre,
                radius_px: outer_radius_um / s,
                sign: 1.0,
            });
            out.push(Disk {
                centre,
                radius_px: inner_radius_um / s,
                sign: -1.0,
            });
        }
    }
}

impl Ink {
    fn new(board: &Board, cam: &CameraModel, view: &View) -> Ink {
        let s = cam.scale_um_per_px;
        let mut disks = Vec::new();
        let mut rects = Vec::new();
        for t in &board.targets {
            shape_disks(
                &mut disks,
                view.board_to_image(cam, t.centre_um),
                &t.outer,
                s,
            );
            shape_disks(
                &mut disks,
                view.board_to_image(cam, t.inner_centre_um()),
                &t.inner,
                s,
            );
        }
        for c in &board.clutter {
            let centre = view.board_to_image(cam, c.centre_um);
            match c.shape {
                ClutterShape::Disk { radius_um } => disks.push(Disk {
                    centre,
                    radius_px: radius_um / s,
                    sign: 1.0,
                }),
                ClutterShape::Rect {
                    width_um,
                    height_um,
                } => rects.push(Rect {
                    centre,
                    half: [width_um / s / 2.0, height_um / s / 2.0],
                }),
            }
        }
        Ink { disks, rects }
    }
}

/// Blurred coverage of a half-plane edge at signed distance `d` (positive outside).
#[inline]
fn edge(d: f64, inv_sqrt2_sigma: f64) -> f64 {
    0.5 * libm::erfc(d * inv_sqrt2_sigma)
}

/// Ink coverage (0..1) of pixel (u, v), area-integrated.
fn pixel_coverage(
    ink: &Ink,
    near: &[usize],
    near_rects: &[usize],
    u: f64,
    v: f64,
    cam: &CameraModel,
) -> f64 {
    let sigma = cam.psf_sigma_px.max(1e-3);
    let k = 1.0 / (std::f64::consts::SQRT_2 * sigma);
    // Beyond this distance from an edge the blurred, pixel-integrated profile is flat.
    let band = 5.0 * sigma + 0.75;
    let mut needs_sub = false;
    let mut flat = 0.0;
    for &i in near {
        let d = &ink.disks[i];
        let rho = (u - d.centre[0]).hypot(v - d.centre[1]);
        let dist = rho - d.radius_px;
        if dist.abs() < band {
            needs_sub = true;
            break;
        }
        if dist < 0.0 {
            flat += d.sign;
        }
    }
    for &i in near_rects {
        let r = &ink.rects[i];
        let dx = (u - r.centre[0]).abs() - r.half[0];
        let dy = (v - r.centre[1]).abs() - r.half[1];
        if dx.abs() < band || dy.abs() < band {
            if dx < band && dy < band {
                needs_sub = true;
            }
        } else if dx < 0.0 && dy < 0.0 {
            flat += 1.0;
        }
    }
    if !needs_sub {
        return flat.clamp(0.0, 1.0);
    }
    let n = cam.supersample.max(1);
    let step = 1.0 / n as f64;
    let mut sum = 0.0;
    for j in 0..n {
        let y = v - 0.5 + (j as f64 + 0.5) * step;
        for i in 0..n {
            let x = u - 0.5 + (i as f64 + 0.5) * step;
            let mut c = 0.0;
            for &di in near {
                let d = &ink.disks[di];
                let rho = (x - d.centre[0]).hypot(y - d.centre[1]);
                c += d.sign * edge(rho - d.radius_px, k);
            }
            for &ri in near_rects {
                let r = &ink.rects[ri];
                let ex = edge((x - r.centre[0]).abs() - r.half[0], k);
                let ey = edge((y - r.centre[1]).abs() - r.half[1], k);
                c += ex * ey;
            }
            sum += c.clamp(0.0, 1.0);
        }
    }
    sum * step * step
}

/// The expected (noise-free) image in DN, RGB interleaved f32, for pixels `x0..x0+w`,
/// `y0..y0+h`, with the illumination scaled by `light` (flicker).
pub fn expected_rgb(
    board: &Board,
    cam: &CameraModel,
    view: &View,
    roi: [u32; 4],
    light: f64,
) -> Vec<f32> {
    let [x0, y0, w, h] = roi;
    let ink = Ink::new(board, cam, view);
    let margin = 5.0 * cam.psf_sigma_px + 2.0;
    let mut out = vec![0f32; (w * h * 3) as usize];
    out.par_chunks_mut((w * 3) as usize)
        .enumerate()
        .for_each(|(row, line)| {
            let v = (y0 + row as u32) as f64;
            // Shapes whose reach covers this row.
            let near: Vec<usize> = (0..ink.disks.len())
                .filter(|&i| (v - ink.disks[i].centre[1]).abs() <= ink.disks[i].radius_px + margin)
                .collect();
            let near_rects: Vec<usize> = (0..ink.rects.len())
                .filter(|&i| (v - ink.rects[i].centre[1]).abs() <= ink.rects[i].half[1] + margin)
                .collect();
            let mut near_x = Vec::with_capacity(near.len());
            let mut near_rx = Vec::with_capacity(near_rects.len());
            for col in 0..w {
                let u = (x0 + col) as f64;
                near_x.clear();
                near_x.extend(near.iter().copied().filter(|&i| {
                    (u - ink.disks[i].centre[0]).abs() <= ink.disks[i].radius_px + margin
                }));
                near_rx.clear();
                near_rx.extend(near_rects.iter().copied().filter(|&i| {
                    (u - ink.rects[i].centre[0]).abs() <= ink.rects[i].half[0] + margin
                }));
                let cov = if near_x.is_empty() && near_rx.is_empty() {
                    0.0
                } else {
                    pixel_coverage(&ink, &near_x, &near_rx, u, v, cam)
                };
                let lum = cam.white_dn * light * cam.illumination(u, v);
                for c in 0..3 {
                    let refl = board.paper_rgb[c] - (board.paper_rgb[c] - board.ink_rgb[c]) * cov;
                    line[(col * 3) as usize + c] = (lum * refl) as f32;
                }
            }
        });
    out
}

/// Add shot, read and quantisation noise to an expected image; seeded per row so the result
/// does not depend on how rows are spread over threads.
pub fn add_noise(expected: &[f32], width: u32, cam: &CameraModel, seed: u64) -> Vec<u8> {
    let mut out = vec![0u8; expected.len()];
    let row_len = (width * 3) as usize;
    out.par_chunks_mut(row_len)
        .zip(expected.par_chunks(row_len))
        .enumerate()
        .for_each(|(row, (dst, src))| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            rng.set_stream(row as u64);
            for (d, &s) in dst.iter_mut().zip(src) {
                let s = s as f64;
                let var = s.max(0.0) / cam.gain_e_per_dn + cam.read_noise_dn * cam.read_noise_dn;
                let z: f64 = StandardNormal.sample(&mut rng);
                *d = (s + var.sqrt() * z).round().clamp(0.0, 255.0) as u8;
            }
        });
    out
}

/// Render one full noisy 8-bit frame (no flicker, vibration or compression: see `frames`).
pub fn render_frame(
    board: &Board,
    cam: &CameraModel,
    view: &View,
    light: f64,
    seed: u64,
) -> RgbImage {
    let exp = expected_rgb(board, cam, view, [0, 0, cam.width, cam.height], light);
    let px = add_noise(&exp, cam.width, cam, seed);
    RgbImage::from_raw(cam.width, cam.height, px).expect("buffer matches the frame size")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn board_point_maps_to_the_pixel_that_sees_it() {
        let cam = CameraModel::default();
        let v = View::at([0.0, 0.0]);
        // The top-left corner of pixel (0,0) is image point (-0.5,-0.5).
        let p = v.board_to_image(&cam, [0.0, 0.0]);
        assert!((p[0] + 0.5).abs() < 1e-12 && (p[1] + 0.5).abs() < 1e-12);
        // Moving the camera +774 µm moves the scene one pixel left.
        let q = View::at([774.0, 0.0]).board_to_image(&cam, [0.0, 0.0]);
        assert!((q[0] + 1.5).abs() < 1e-12);
    }

    #[test]
    fn ink_area_matches_the_printed_area() {
        let board = Board::paper();
        let cam = CameraModel {
            vignetting: 0.0,
            light_gradient: 0.0,
            ..Default::default()
        };
        let t = &board.targets[0];
        let view = View::at([0.3 * 774.0, 0.2 * 774.0]);
        let c = view.board_to_image(&cam, t.centre_um);
        let (x0, y0) = ((c[0] - 30.0) as u32, (c[1] - 30.0) as u32);
        let img = expected_rgb(&board, &cam, &view, [x0, y0, 61, 61], 1.0);
        // Green channel: ink coverage summed over the ROI equals ring + disk area in px².
        let (pg, ig) = (board.paper_rgb[1], board.ink_rgb[1]);
        let cov: f64 = img
            .chunks(3)
            .map(|p| (pg - p[1] as f64 / cam.white_dn) / (pg - ig))
            .sum();
        let s = cam.scale_um_per_px;
        let area = std::f64::consts::PI
            * ((17000.0f64 / s).powi(2) - (13000.0f64 / s).powi(2) + (6000.0f64 / s).powi(2));
        assert!(
            (cov - area).abs() / area < 2e-3,
            "coverage {cov} vs area {area}"
        );
    }
}
