//! The renderer: board + camera model + where the camera is -> what the sensor sees.
//!
//! Pixels integrate area: a pixel that straddles an edge is sampled on a fine sub-grid
//! (`CameraModel::supersample` per side) of the Gaussian-blurred edge profile, so a
//! sub-pixel move of the camera changes the image the way it does on a real sensor.
//! Pixels far from every edge are exactly ink or exactly paper. Image coordinates put pixel
//! centres at integers (OpenCV's convention): pixel (u, v) covers [u-0.5, u+0.5] x [v-0.5, v+0.5].

use crate::board::{Board, ClutterShape, Shape};
use crate::camera::CameraModel;
use crate::warp::{Print, WarpInk};
use image::RgbImage;
use rand::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use std::sync::Arc;

/// Where the camera looks: the board point (µm) seen at the top-left corner of pixel (0, 0)
/// when the roll is zero, and a roll of the board about the image centre.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct View {
    pub camera_um: [f64; 2],
    pub roll_rad: f64,
    /// How much farther the board is than at the rail's origin, µm along the optical axis
    /// (a rail along the sensor: `CameraModel::rail_pose`).
    pub depth_um: f64,
}

impl View {
    pub fn at(camera_um: [f64; 2]) -> View {
        View {
            camera_um,
            roll_rad: 0.0,
            depth_um: 0.0,
        }
    }

    /// The view from `origin_um` after the stage's travel `travel_um`, on `cam`'s rail.
    pub fn on_rail(cam: &CameraModel, origin_um: [f64; 2], travel_um: [f64; 2]) -> View {
        let (b, depth_um) = cam.rail_pose(travel_um);
        View {
            camera_um: [origin_um[0] + b[0], origin_um[1] + b[1]],
            roll_rad: 0.0,
            depth_um,
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

    /// Image coordinates of a board point through the camera's whole lens (tilt, distortion)
    /// in `channel` (0 R, 1 G, 2 B: lateral colour); `board_to_image` for an ideal lens.
    pub fn project(&self, cam: &CameraModel, channel: usize, p_um: [f64; 2]) -> [f64; 2] {
        self.lens(cam).to_image(channel, p_um)
    }

    /// Where the circles of `radii_um` about board point `c_um` image, in `channel`: each
    /// circle's image's area centroid (a tilted circle images as an ellipse whose centre is
    /// not the projected one), averaged over the radii. The truth a calibration's
    /// conversion is held to.
    pub fn apparent_centre(
        &self,
        cam: &CameraModel,
        channel: usize,
        c_um: [f64; 2],
        radii_um: &[f64],
    ) -> [f64; 2] {
        let lens = self.lens(cam);
        let mut sum = [0.0; 2];
        for &r in radii_um {
            let pts: Vec<[f64; 2]> = (0..96)
                .map(|i| {
                    let t = std::f64::consts::TAU * i as f64 / 96.0;
                    lens.to_image(channel, [c_um[0] + r * t.cos(), c_um[1] + r * t.sin()])
                })
                .collect();
            let c = rigd_core::calibration::model::polygon_centroid(&pts);
            sum = [sum[0] + c[0], sum[1] + c[1]];
        }
        sum.map(|v| v / radii_um.len() as f64)
    }

    /// The camera's whole lens at this view, on a bare board.
    fn lens(&self, cam: &CameraModel) -> WarpInk {
        let mut bare = Board::paper();
        bare.targets.clear();
        bare.clutter.clear();
        let print = Arc::new(Print::new(&bare, cam));
        WarpInk::new(&bare, cam, self, print)
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

/// Everything inked on the board, in image coordinates for one view (or, through a real
/// lens or with an imperfect print, on the board: `warp`).
struct Ink {
    disks: Vec<Disk>,
    rects: Vec<Rect>,
    warp: Option<WarpInk>,
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
    /// The ink of `view`; `print` is the board's cached print when the camera warps.
    fn new(board: &Board, cam: &CameraModel, view: &View, print: Option<&Arc<Print>>) -> Ink {
        if cam.needs_warp() {
            let print = print
                .cloned()
                .unwrap_or_else(|| Arc::new(Print::new(board, cam)));
            return Ink {
                disks: Vec::new(),
                rects: Vec::new(),
                warp: Some(WarpInk::new(board, cam, view, print)),
            };
        }
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
        Ink {
            disks,
            rects,
            warp: None,
        }
    }
}

/// The blurred edge profile `0.5·erfc(d / (√2·σ))` of a half-plane at signed distance `d`
/// (px, positive outside), tabulated: the renderer evaluates it millions of times per
/// frame and a table with linear interpolation is ~10x cheaper than `erfc` (error < 1e-6).
#[derive(Debug, Clone)]
pub(crate) struct EdgeTable {
    /// Beyond ±reach the profile is 0 or 1 to within 3e-7.
    reach: f64,
    inv_step: f64,
    values: Vec<f64>,
}

impl EdgeTable {
    const STEPS_PER_PX: f64 = 512.0;

    pub(crate) fn new(psf_sigma_px: f64) -> EdgeTable {
        let sigma = psf_sigma_px.max(1e-3);
        let k = 1.0 / (std::f64::consts::SQRT_2 * sigma);
        let reach = 5.0 * sigma + 1.0;
        let n = (2.0 * reach * Self::STEPS_PER_PX).ceil() as usize + 2;
        let values = (0..n)
            .map(|i| 0.5 * libm::erfc((i as f64 / Self::STEPS_PER_PX - reach) * k))
            .collect();
        EdgeTable {
            reach,
            inv_step: Self::STEPS_PER_PX,
            values,
        }
    }

    #[inline]
    pub(crate) fn at(&self, d: f64) -> f64 {
        if d <= -self.reach {
            return 1.0;
        }
        if d >= self.reach {
            return 0.0;
        }
        let x = (d + self.reach) * self.inv_step;
        let i = x as usize;
        let f = x - i as f64;
        let a = self.values[i];
        a + (self.values[i + 1] - a) * f
    }

    /// The profile and its slope d/dd (the table's difference: the slope of the normal
    /// density to ~1e-6 of its peak).
    #[inline]
    pub(crate) fn at_slope(&self, d: f64) -> (f64, f64) {
        if d <= -self.reach {
            return (1.0, 0.0);
        }
        if d >= self.reach {
            return (0.0, 0.0);
        }
        let x = (d + self.reach) * self.inv_step;
        let i = x as usize;
        let f = x - i as f64;
        let (a, b) = (self.values[i], self.values[i + 1]);
        (a + (b - a) * f, (b - a) * self.inv_step)
    }
}

/// Ink coverage (0..1) of pixel (u, v), area-integrated.
///
/// Shapes whose edge is farther than the blur's reach from the pixel contribute a constant
/// (all ink or none); only the others are evaluated on the sub-sample grid.
fn pixel_coverage(
    ink: &Ink,
    near: &[usize],
    near_rects: &[usize],
    u: f64,
    v: f64,
    cam: &CameraModel,
    edge: &EdgeTable,
) -> f64 {
    const MAX_ACTIVE: usize = 8;
    let sigma = cam.psf_sigma_px.max(1e-3);
    // Beyond this distance from an edge the blurred, pixel-integrated profile is flat.
    let band = 5.0 * sigma + 0.75;
    let mut flat = 0.0;
    let mut disks = [0usize; MAX_ACTIVE];
    let mut n_disks = 0;
    let mut rects = [0usize; MAX_ACTIVE];
    let mut n_rects = 0;
    let mut overflow = false;
    for &i in near {
        let d = &ink.disks[i];
        let rho = (u - d.centre[0]).hypot(v - d.centre[1]);
        let dist = rho - d.radius_px;
        if dist.abs() < band {
            if n_disks == MAX_ACTIVE {
                overflow = true;
                break;
            }
            disks[n_disks] = i;
            n_disks += 1;
        } else if dist < 0.0 {
            flat += d.sign;
        }
    }
    for &i in near_rects {
        let r = &ink.rects[i];
        let dx = (u - r.centre[0]).abs() - r.half[0];
        let dy = (v - r.centre[1]).abs() - r.half[1];
        if dx.abs() < band || dy.abs() < band {
            if dx < band && dy < band {
                if n_rects == MAX_ACTIVE {
                    overflow = true;
                    break;
                }
                rects[n_rects] = i;
                n_rects += 1;
            }
        } else if dx < 0.0 && dy < 0.0 {
            flat += 1.0;
        }
    }
    // Many shapes crowding one pixel: evaluate them all on the grid (slow, exact).
    let (disks, rects, flat): (&[usize], &[usize], f64) = if overflow {
        (near, near_rects, 0.0)
    } else {
        (&disks[..n_disks], &rects[..n_rects], flat)
    };
    if disks.is_empty() && rects.is_empty() {
        return flat.clamp(0.0, 1.0);
    }
    // Close to an edge the profile bends within the pixel: the full sub-grid. Farther out
    // (but still inside the blur's reach) it is smooth and a 3x3 midpoint rule is exact to
    // ~1e-4 of the ink contrast.
    let close = 2.0 * sigma + 0.1;
    let near_edge = overflow
        || disks.iter().any(|&i| {
            let d = &ink.disks[i];
            ((u - d.centre[0]).hypot(v - d.centre[1]) - d.radius_px).abs() < close
        })
        || rects.iter().any(|&i| {
            let r = &ink.rects[i];
            ((u - r.centre[0]).abs() - r.half[0]).abs() < close
                || ((v - r.centre[1]).abs() - r.half[1]).abs() < close
        });
    let n = if near_edge {
        cam.supersample.max(1)
    } else {
        cam.supersample.clamp(1, 3)
    };
    let step = 1.0 / n as f64;
    let mut sum = 0.0;
    for j in 0..n {
        let y = v - 0.5 + (j as f64 + 0.5) * step;
        for i in 0..n {
            let x = u - 0.5 + (i as f64 + 0.5) * step;
            let mut c = flat;
            for &di in disks {
                let d = &ink.disks[di];
                let dx = x - d.centre[0];
                let dy = y - d.centre[1];
                let rho = (dx * dx + dy * dy).sqrt();
                c += d.sign * edge.at(rho - d.radius_px);
            }
            for &ri in rects {
                let r = &ink.rects[ri];
                let ex = edge.at((x - r.centre[0]).abs() - r.half[0]);
                let ey = edge.at((y - r.centre[1]).abs() - r.half[1]);
                c += ex * ey;
            }
            sum += c.clamp(0.0, 1.0);
        }
    }
    sum * step * step
}

/// Render the expected DN of the rows `y0..y0+rows` of the ROI `[x0, y0, w, h]` into `out`
/// (RGB interleaved, `w*3` per row), at illumination `light`.
#[allow(clippy::too_many_arguments)]
fn render_rows(
    board: &Board,
    cam: &CameraModel,
    ink: &Ink,
    edge: &EdgeTable,
    x0: u32,
    w: u32,
    v: f64,
    line: &mut [f32],
    light: f64,
) {
    if let Some(warp) = &ink.warp {
        return crate::warp::render_row(board, cam, warp, edge, x0, w, v, line, light);
    }
    let margin = 5.0 * cam.psf_sigma_px + 2.0;
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
        near_x.extend(
            near.iter()
                .copied()
                .filter(|&i| (u - ink.disks[i].centre[0]).abs() <= ink.disks[i].radius_px + margin),
        );
        near_rx.clear();
        near_rx.extend(
            near_rects
                .iter()
                .copied()
                .filter(|&i| (u - ink.rects[i].centre[0]).abs() <= ink.rects[i].half[0] + margin),
        );
        let cov = if near_x.is_empty() && near_rx.is_empty() {
            0.0
        } else {
            pixel_coverage(ink, &near_x, &near_rx, u, v, cam, edge)
        };
        let lum = cam.white_dn * light * cam.illumination(u, v);
        for c in 0..3 {
            let refl = board.paper_rgb[c] - (board.paper_rgb[c] - board.ink_rgb[c]) * cov;
            line[(col * 3) as usize + c] = (lum * refl) as f32;
        }
    }
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
    let ink = Ink::new(board, cam, view, None);
    let edge = EdgeTable::new(cam.psf_sigma_px);
    let mut out = vec![0f32; (w * h * 3) as usize];
    if w == 0 {
        return out;
    }
    out.par_chunks_mut((w * 3) as usize)
        .enumerate()
        .for_each(|(row, line)| {
            let v = (y0 + row as u32) as f64;
            render_rows(board, cam, &ink, &edge, x0, w, v, line, light);
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
        .for_each(|(row, (dst, src))| noise_row(dst, src, 1.0, cam, seed, row as u64));
    out
}

/// Standard normal deviates by inverse CDF at 65536 equiprobable points: 16 random bits
/// give one deviate (tails cut at 4.3σ, variance 0.9997), 4x faster than a ziggurat and,
/// once quantised to 8 bits, indistinguishable from it.
fn normal_table() -> &'static [f32] {
    static TABLE: std::sync::OnceLock<Vec<f32>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        (0..65536)
            .map(|i| {
                let p = (i as f64 + 0.5) / 65536.0;
                // Φ⁻¹(p) = -√2 · erfc⁻¹(2p), by Newton on erfc from a good start.
                let mut z = if p < 0.5 { -1.0 } else { 1.0 };
                for _ in 0..60 {
                    let f = 0.5 * libm::erfc(-z / std::f64::consts::SQRT_2) - p;
                    let pdf = (-0.5 * z * z).exp() / (2.0 * std::f64::consts::PI).sqrt();
                    let step = f / pdf.max(1e-300);
                    z -= step.clamp(-1.0, 1.0);
                    if step.abs() < 1e-13 {
                        break;
                    }
                }
                z as f32
            })
            .collect()
    })
}

/// One row of noisy 8-bit samples from expected DN scaled by `light`.
#[inline]
fn noise_row(dst: &mut [u8], src: &[f32], light: f32, cam: &CameraModel, seed: u64, row: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(row);
    let table = normal_table();
    let inv_gain = (1.0 / cam.gain_e_per_dn) as f32;
    let read_var = (cam.read_noise_dn * cam.read_noise_dn) as f32;
    for (d4, s4) in dst.chunks_mut(4).zip(src.chunks(4)) {
        let bits = rng.next_u64();
        for (k, (d, &s)) in d4.iter_mut().zip(s4).enumerate() {
            let z = table[((bits >> (16 * k)) & 0xffff) as usize];
            let s = s * light;
            let var = s.max(0.0) * inv_gain + read_var;
            // Round half up by truncation after the clamp: `f32::round` is a libm call here.
            *d = ((s + var.sqrt() * z).clamp(0.0, 255.0) + 0.5) as u8;
        }
    }
}

/// One row of sensor samples from expected DN (RGB) scaled by `light`: one mosaic sample
/// per pixel (with colour crosstalk) for a Bayer sensor, else RGB; shot and read noise as in
/// `noise_row`; quantised to `isp::RAW_STEP_DN` (10-bit raw).
fn raw_row(dst: &mut [f32], src: &[f32], light: f32, cam: &CameraModel, seed: u64, row: usize) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(row as u64);
    let table = normal_table();
    let inv_gain = (1.0 / cam.gain_e_per_dn) as f32;
    let read_var = (cam.read_noise_dn * cam.read_noise_dn) as f32;
    let bayer = crate::isp::bayer(cam);
    let c = cam.crosstalk as f32;
    let top = 255.0 + 1.0 - crate::isp::RAW_STEP_DN;
    let inv_step = 1.0 / crate::isp::RAW_STEP_DN;
    for (k4, d4) in dst.chunks_mut(4).enumerate() {
        let bits = rng.next_u64();
        for (k, d) in d4.iter_mut().enumerate() {
            let i = k4 * 4 + k;
            let expected = if bayer {
                crate::isp::mixed(&src[i * 3..i * 3 + 3], crate::isp::cfa_channel(i, row), c)
            } else {
                src[i]
            };
            let s = expected * light;
            let z = table[((bits >> (16 * k)) & 0xffff) as usize];
            let var = s.max(0.0) * inv_gain + read_var;
            let q = ((s + var.sqrt() * z).clamp(0.0, top) * inv_step + 0.5).floor();
            *d = q * crate::isp::RAW_STEP_DN;
        }
    }
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

/// A re-rendered patch of the frame: `[x0, y0, w, h]` and its expected DN (RGB f32).
struct Patch {
    roi: [u32; 4],
    rgb: Vec<f32>,
}

/// Renders frames of one board through one camera fast: the expected background (paper x
/// illumination, which does not move with the camera) is computed once, and per pose only
/// the pixel boxes around the inked shapes are re-rendered. Noise is added row by row while
/// the patches are laid over the background, so no full-frame float image is built.
pub struct SceneRenderer {
    board: Board,
    cam: CameraModel,
    edge: EdgeTable,
    /// Expected DN of bare paper, RGB f32, full frame, at light 1.
    background: Vec<f32>,
    /// The print's rough edges and ink, built once (when the camera has them or a lens).
    print: Option<Arc<Print>>,
}

impl SceneRenderer {
    pub fn new(board: Board, cam: CameraModel) -> SceneRenderer {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let mut background = vec![0f32; w * h * 3];
        background
            .par_chunks_mut(w * 3)
            .enumerate()
            .for_each(|(v, line)| {
                for u in 0..w {
                    let lum = cam.white_dn * cam.illumination(u as f64, v as f64);
                    for c in 0..3 {
                        line[u * 3 + c] = (lum * board.paper_rgb[c]) as f32;
                    }
                }
            });
        let edge = EdgeTable::new(cam.psf_sigma_px);
        let print = cam.needs_warp().then(|| Arc::new(Print::new(&board, &cam)));
        SceneRenderer {
            board,
            cam,
            edge,
            background,
            print,
        }
    }

    pub fn board(&self) -> &Board {
        &self.board
    }

    pub fn camera(&self) -> &CameraModel {
        &self.cam
    }

    /// Pixel boxes `[x0, y0, w, h]` that hold every inked shape for any of `views`, clipped
    /// to the frame (boxes of shapes out of view are left out).
    pub fn ink_rois(&self, views: &[View]) -> Vec<[u32; 4]> {
        if let Some(print) = &self.print {
            return self.warped_rois(views, print);
        }
        let cam = &self.cam;
        let s = cam.scale_um_per_px;
        let margin = 5.0 * cam.psf_sigma_px + 2.0;
        let mut shapes: Vec<([f64; 2], [f64; 2])> = Vec::new();
        for t in &self.board.targets {
            let r = t.outer.outer_radius_um() / s;
            shapes.push((t.centre_um, [r, r]));
        }
        for c in &self.board.clutter {
            let half = match c.shape {
                ClutterShape::Disk { radius_um } => [radius_um / s; 2],
                ClutterShape::Rect {
                    width_um,
                    height_um,
                } => [width_um / s / 2.0, height_um / s / 2.0],
            };
            shapes.push((c.centre_um, half));
        }
        let (fw, fh) = (cam.width as f64, cam.height as f64);
        let mut rois = Vec::new();
        for (centre_um, half) in shapes {
            let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
            for view in views {
                let c = view.board_to_image(cam, centre_um);
                for a in 0..2 {
                    lo[a] = lo[a].min(c[a] - half[a] - margin);
                    hi[a] = hi[a].max(c[a] + half[a] + margin);
                }
            }
            let x0 = lo[0].floor().max(0.0);
            let y0 = lo[1].floor().max(0.0);
            let x1 = (hi[0].ceil() + 1.0).min(fw);
            let y1 = (hi[1].ceil() + 1.0).min(fh);
            if x1 > x0 && y1 > y0 {
                rois.push([x0 as u32, y0 as u32, (x1 - x0) as u32, (y1 - y0) as u32]);
            }
        }
        rois
    }

    /// `ink_rois` through the lens: each shape's boxes (its boundary mapped through the lens)
    /// joined over the views.
    fn warped_rois(&self, views: &[View], print: &Arc<Print>) -> Vec<[u32; 4]> {
        let mut joined: Vec<[f64; 4]> = Vec::new();
        for view in views {
            let ink = WarpInk::new(&self.board, &self.cam, view, Arc::clone(print));
            let boxes = crate::warp::shape_boxes(&ink, &self.board);
            if joined.is_empty() {
                joined = boxes;
            } else {
                for (j, b) in joined.iter_mut().zip(boxes) {
                    *j = [
                        j[0].min(b[0]),
                        j[1].max(b[1]),
                        j[2].min(b[2]),
                        j[3].max(b[3]),
                    ];
                }
            }
        }
        let (fw, fh) = (self.cam.width as f64, self.cam.height as f64);
        joined
            .into_iter()
            .filter_map(|b| {
                let x0 = b[0].floor().max(0.0);
                let y0 = b[2].floor().max(0.0);
                let x1 = (b[1].ceil() + 1.0).min(fw);
                let y1 = (b[3].ceil() + 1.0).min(fh);
                (x1 > x0 && y1 > y0).then_some([
                    x0 as u32,
                    y0 as u32,
                    (x1 - x0) as u32,
                    (y1 - y0) as u32,
                ])
            })
            .collect()
    }

    /// Expected DN (light 1) of `roi`, averaged over `views` (several views = the scene moved
    /// during the exposure: motion blur).
    fn patch(&self, views: &[View], roi: [u32; 4]) -> Patch {
        let [x0, y0, w, h] = roi;
        let mut rgb = vec![0f32; (w * h * 3) as usize];
        let mut line = vec![0f32; (w * 3) as usize];
        let weight = 1.0 / views.len() as f32;
        for view in views {
            let ink = Ink::new(&self.board, &self.cam, view, self.print.as_ref());
            for row in 0..h {
                let v = (y0 + row) as f64;
                render_rows(
                    &self.board,
                    &self.cam,
                    &ink,
                    &self.edge,
                    x0,
                    w,
                    v,
                    &mut line,
                    1.0,
                );
                let dst = &mut rgb[(row * w * 3) as usize..((row + 1) * w * 3) as usize];
                for (d, s) in dst.iter_mut().zip(&line) {
                    *d += s * weight;
                }
            }
        }
        Patch { roi, rgb }
    }

    fn patches(&self, views: &[View]) -> Vec<Patch> {
        assert!(!views.is_empty(), "at least one view to render");
        self.ink_rois(views)
            .into_par_iter()
            .map(|roi| self.patch(views, roi))
            .collect()
    }

    /// Lay the patches over the background for row `v` into `line`.
    fn compose_row(&self, patches: &[Patch], v: u32, line: &mut [f32]) {
        let row_len = self.cam.width as usize * 3;
        let start = v as usize * row_len;
        line.copy_from_slice(&self.background[start..start + row_len]);
        for p in patches {
            let [x0, y0, w, h] = p.roi;
            if v >= y0 && v < y0 + h {
                let src = &p.rgb[((v - y0) * w * 3) as usize..((v - y0 + 1) * w * 3) as usize];
                line[(x0 * 3) as usize..((x0 + w) * 3) as usize].copy_from_slice(src);
            }
        }
    }

    /// The expected (noise-free) full frame in DN at light 1, averaged over `views`.
    pub fn expected_frame(&self, views: &[View]) -> Vec<f32> {
        let patches = self.patches(views);
        let row_len = self.cam.width as usize * 3;
        let mut out = vec![0f32; row_len * self.cam.height as usize];
        out.par_chunks_mut(row_len)
            .enumerate()
            .for_each(|(v, line)| self.compose_row(&patches, v as u32, line));
        out
    }

    /// A noisy 8-bit frame (RGB interleaved): the scene seen over `views` (averaged), the
    /// illumination scaled by `light`, shot/read noise seeded by `seed` per row.
    pub fn expose(&self, views: &[View], light: f64, seed: u64) -> Vec<u8> {
        self.expose_lit(views, light, seed, 0.0)
    }

    /// `expose` with the light of each row also scaled by the rolling shutter's flicker
    /// bands (`light::row_gain` at modulation phase `flicker_phase`), and through the camera's
    /// sensor and processing (`isp`) when it has any.
    pub fn expose_lit(&self, views: &[View], light: f64, seed: u64, flicker_phase: f64) -> Vec<u8> {
        let patches = self.patches(views);
        let cam = &self.cam;
        let row_light = |v: usize| light * crate::light::row_gain(cam, flicker_phase, v as u32);
        if cam.needs_isp() {
            return self.expose_isp(&patches, &row_light, seed);
        }
        let row_len = cam.width as usize * 3;
        let mut out = vec![0u8; row_len * cam.height as usize];
        out.par_chunks_mut(row_len).enumerate().for_each_init(
            || vec![0f32; row_len],
            |line, (v, dst)| {
                self.compose_row(&patches, v as u32, line);
                noise_row(dst, line, row_light(v) as f32, cam, seed, v as u64);
            },
        );
        out
    }

    /// Sensor samples (a Bayer mosaic or RGB) with noise, demosaiced and processed to 8 bits.
    fn expose_isp(
        &self,
        patches: &[Patch],
        row_light: &(dyn Fn(usize) -> f64 + Sync),
        seed: u64,
    ) -> Vec<u8> {
        let cam = &self.cam;
        let (w, h) = (cam.width as usize, cam.height as usize);
        let bayer = crate::isp::bayer(cam);
        let per_px = if bayer { 1 } else { 3 };
        let mut raw = vec![0f32; w * h * per_px];
        raw.par_chunks_mut(w * per_px).enumerate().for_each_init(
            || vec![0f32; w * 3],
            |line, (v, dst)| {
                self.compose_row(patches, v as u32, line);
                raw_row(dst, line, row_light(v) as f32, cam, seed, v);
            },
        );
        let rgb = if bayer {
            crate::isp::demosaic(&raw, w, h, cam.demosaic)
        } else {
            raw
        };
        crate::isp::process(rgb, w, h, cam)
    }
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

    fn small_cam() -> CameraModel {
        CameraModel {
            width: 400,
            height: 240,
            scale_um_per_px: 2500.0,
            ..Default::default()
        }
    }

    #[test]
    fn edge_table_matches_erfc() {
        let t = EdgeTable::new(0.7);
        let k = 1.0 / (std::f64::consts::SQRT_2 * 0.7);
        for i in -5000..5000 {
            let d = i as f64 * 1.3e-3;
            let want = 0.5 * libm::erfc(d * k);
            assert!((t.at(d) - want).abs() < 1e-6, "d={d}");
        }
    }

    #[test]
    fn scene_renderer_equals_the_direct_render() {
        let board = Board::paper();
        let cam = small_cam();
        let view = View::at([1234.0, -567.0]);
        let direct = expected_rgb(&board, &cam, &view, [0, 0, cam.width, cam.height], 1.0);
        let sr = SceneRenderer::new(board, cam);
        let fast = sr.expected_frame(&[view]);
        let worst = direct
            .iter()
            .zip(&fast)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(worst < 1e-3, "largest difference {worst} DN");
        // And the inked boxes do hold ink: the frame is not just background.
        let bg_diff = fast
            .iter()
            .zip(&sr.background)
            .filter(|(a, b)| (*a - *b).abs() > 1.0)
            .count();
        assert!(bg_diff > 1000, "{bg_diff} inked samples");
    }

    #[test]
    fn two_views_average_to_the_mean_of_each() {
        let sr = SceneRenderer::new(Board::paper(), small_cam());
        let (a, b) = (View::at([0.0, 0.0]), View::at([1500.0, 0.0]));
        let ea = sr.expected_frame(&[a]);
        let eb = sr.expected_frame(&[b]);
        let eab = sr.expected_frame(&[a, b]);
        for ((x, y), m) in ea.iter().zip(&eb).zip(&eab) {
            assert!(((x + y) / 2.0 - m).abs() < 1e-3);
        }
    }

    #[test]
    fn normal_table_is_a_standard_normal() {
        let t = normal_table();
        let n = t.len() as f64;
        let mean = t.iter().map(|&z| z as f64).sum::<f64>() / n;
        let var = t.iter().map(|&z| (z as f64).powi(2)).sum::<f64>() / n;
        assert!(
            mean.abs() < 1e-6 && (var - 1.0).abs() < 1e-3,
            "{mean} {var}"
        );
        // The median deviate, the 84th percentile near +1σ.
        assert!(t[32768].abs() < 1e-4);
        assert!((t[(0.841_344_7 * n) as usize] - 1.0).abs() < 1e-3);
    }
}
