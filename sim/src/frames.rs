//! Per-frame effects and the frame renderer: what makes frame i differ from frame j beyond
//! the pose — illumination flicker, camera vibration, noise, MJPEG compression.
//!
//! Everything random about frame i is drawn from `(seed, i)` alone, so a frame is the same
//! whichever thread renders it and whenever, given the same line-of-sight samples.

use crate::board::Board;
use crate::camera::{CameraError, CameraModel, ChromaSubsampling, Uncompressed};
use crate::render::{SceneRenderer, View};
use image::codecs::jpeg::JpegEncoder;
use image::RgbImage;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// The random draws of one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameEffects {
    /// Illumination gain (1 + flicker).
    pub light: f64,
    /// Line-of-sight displacement by vibration, µm on the board.
    pub jitter_um: [f64; 2],
    /// Seed of the frame's shot and read noise.
    pub noise_seed: u64,
    /// Auto-exposure gain (1 without AE wander; `light::ae_gain`).
    pub ae_gain: f64,
    /// Phase of the mains flicker when the exposure starts, rad (`light::flicker_phase`).
    pub flicker_phase: f64,
}

/// SplitMix64 finaliser: decorrelates (seed, sequence) pairs into independent seeds.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

impl FrameEffects {
    /// The effects of frame `sequence` of a camera seeded with `seed`.
    pub fn draw(cam: &CameraModel, seed: u64, sequence: u64) -> FrameEffects {
        let frame_seed = mix(mix(seed) ^ sequence);
        let mut rng = ChaCha8Rng::seed_from_u64(frame_seed);
        let mut n = || -> f64 { StandardNormal.sample(&mut rng) };
        // Drawn in a fixed order whatever the parameters, so switching one effect off does
        // not change the others.
        let flicker = n();
        let jx = n();
        let jy = n();
        FrameEffects {
            light: (1.0 + cam.flicker_rms * flicker).max(0.05),
            jitter_um: [cam.vibration_um * jx, cam.vibration_um * jy],
            noise_seed: mix(frame_seed),
            // Hashed from (seed, sequence) apart from the stream above, so they leave the
            // other draws as they were.
            ae_gain: crate::light::ae_gain(cam, seed, sequence),
            flicker_phase: crate::light::flicker_phase(cam, seed, sequence),
        }
    }
}

/// Halve the chroma resolution the way an MJPEG encoder does: to YCbCr (JFIF), chroma
/// averaged over 2x1 (4:2:2) or 2x2 (4:2:0) blocks, back to RGB.
pub fn subsample_chroma(img: &mut RgbImage, chroma: ChromaSubsampling) {
    let (bw, bh) = match chroma {
        ChromaSubsampling::Yuv444 => return,
        ChromaSubsampling::Yuv422 => (2, 1),
        ChromaSubsampling::Yuv420 => (2, 2),
    };
    let (w, h) = img.dimensions();
    let ycc = |p: &image::Rgb<u8>| {
        let [r, g, b] = p.0.map(f32::from);
        (
            0.299 * r + 0.587 * g + 0.114 * b,
            -0.168_736 * r - 0.331_264 * g + 0.5 * b,
            0.5 * r - 0.418_688 * g - 0.081_312 * b,
        )
    };
    for by in (0..h).step_by(bh) {
        for bx in (0..w).step_by(bw) {
            let (x1, y1) = ((bx + bw as u32).min(w), (by + bh as u32).min(h));
            let (mut cb, mut cr, mut n) = (0f32, 0f32, 0f32);
            for y in by..y1 {
                for x in bx..x1 {
                    let (_, b, r) = ycc(img.get_pixel(x, y));
                    cb += b;
                    cr += r;
                    n += 1.0;
                }
            }
            let (cb, cr) = (cb / n, cr / n);
            for y in by..y1 {
                for x in bx..x1 {
                    let (yy, _, _) = ycc(img.get_pixel(x, y));
                    let to = |v: f32| v.round().clamp(0.0, 255.0) as u8;
                    img.put_pixel(
                        x,
                        y,
                        image::Rgb([
                            to(yy + 1.402 * cr),
                            to(yy - 0.344_136 * cb - 0.714_136 * cr),
                            to(yy + 1.772 * cb),
                        ]),
                    );
                }
            }
        }
    }
}

/// A real MJPEG round trip: chroma subsampled, JPEG-encoded at `quality`, decoded again.
pub fn mjpeg_round_trip(img: &RgbImage, quality: u8, chroma: ChromaSubsampling) -> RgbImage {
    let mut sub = img.clone();
    subsample_chroma(&mut sub, chroma);
    let mut jpeg = Vec::with_capacity(img.len() / 8);
    JpegEncoder::new_with_quality(&mut jpeg, quality.clamp(1, 100))
        .encode_image(&sub)
        .expect("a validated frame size encodes as JPEG");
    image::load_from_memory_with_format(&jpeg, image::ImageFormat::Jpeg)
        .expect("our own JPEG decodes")
        .to_rgb8()
}

/// Renders the frames of one camera over one board: pose(s) in, finished 8-bit frame out.
pub struct FrameRenderer {
    scene: SceneRenderer,
    seed: u64,
    /// Board point at the top-left corner of pixel (0, 0) when the line of sight is at 0.
    origin_um: [f64; 2],
}

impl FrameRenderer {
    /// A renderer for `board` through `cam`, its random effects seeded by `seed`.
    pub fn new(board: Board, cam: CameraModel, seed: u64) -> Result<FrameRenderer, CameraError> {
        cam.validate()?;
        Ok(FrameRenderer {
            scene: SceneRenderer::new(board, cam),
            seed,
            origin_um: [0.0, 0.0],
        })
    }

    /// Where the camera looks when the line of sight is at 0 (see `origin_um`).
    pub fn with_origin(mut self, origin_um: [f64; 2]) -> FrameRenderer {
        self.origin_um = origin_um;
        self
    }

    pub fn scene(&self) -> &SceneRenderer {
        &self.scene
    }

    pub fn camera(&self) -> &CameraModel {
        self.scene.camera()
    }

    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The views of frame `sequence` for line-of-sight samples over its exposure (µm of
    /// travel; one sample = the scene stood still). Identical samples collapse to one.
    pub fn views(&self, sequence: u64, los_um: &[[f64; 2]]) -> Vec<View> {
        let fx = FrameEffects::draw(self.camera(), self.seed, sequence);
        let still = los_um.windows(2).all(|w| w[0] == w[1]);
        let los = if still { &los_um[..1] } else { los_um };
        let origin = [
            self.origin_um[0] + fx.jitter_um[0],
            self.origin_um[1] + fx.jitter_um[1],
        ];
        los.iter()
            .map(|p| View::on_rail(self.camera(), origin, *p))
            .collect()
    }

    /// Frame `sequence` with the line of sight at `los_um` for its whole exposure.
    pub fn render_at(&self, sequence: u64, los_um: [f64; 2]) -> RgbImage {
        self.render(sequence, &[los_um])
    }

    /// Frame `sequence` exposed while the line of sight passed through `los_um` (evenly
    /// spaced samples over the exposure: motion blur when they differ).
    ///
    /// # Panics
    /// If `los_um` is empty.
    pub fn render(&self, sequence: u64, los_um: &[[f64; 2]]) -> RgbImage {
        assert!(!los_um.is_empty(), "a frame needs at least one pose");
        let cam = self.camera();
        let fx = FrameEffects::draw(cam, self.seed, sequence);
        let views = self.views(sequence, los_um);
        let px = self.scene.expose_lit(
            &views,
            fx.light * fx.ae_gain,
            fx.noise_seed,
            fx.flicker_phase,
        );
        let mut img = RgbImage::from_raw(cam.width, cam.height, px).expect("frame-sized buffer");
        match (cam.mjpeg_quality, cam.uncompressed) {
            (Some(q), _) => mjpeg_round_trip(&img, q, cam.mjpeg_chroma),
            (None, Uncompressed::Rgb) => img,
            (None, Uncompressed::Yuyv) => {
                subsample_chroma(&mut img, ChromaSubsampling::Yuv422);
                img
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn effects_depend_on_seed_and_sequence_only() {
        let cam = CameraModel::default();
        let a = FrameEffects::draw(&cam, 7, 3);
        assert_eq!(a, FrameEffects::draw(&cam, 7, 3));
        assert_ne!(a, FrameEffects::draw(&cam, 7, 4));
        assert_ne!(a, FrameEffects::draw(&cam, 8, 3));
        let still = CameraModel {
            flicker_rms: 0.0,
            vibration_um: 0.0,
            ..cam
        };
        let b = FrameEffects::draw(&still, 7, 3);
        assert_eq!((b.light, b.jitter_um, b.ae_gain), (1.0, [0.0, 0.0], 1.0));
        assert_eq!(b.noise_seed, a.noise_seed);
    }

    #[test]
    fn chroma_subsampling_keeps_luma_and_blurs_colour_edges() {
        // A red/white column edge on an odd column: 4:2:2 mixes the pair's chroma.
        let img = RgbImage::from_fn(8, 2, |x, _| {
            if x < 3 {
                image::Rgb([200, 40, 40])
            } else {
                image::Rgb([220, 220, 210])
            }
        });
        let mut s = img.clone();
        subsample_chroma(&mut s, ChromaSubsampling::Yuv422);
        // Pixels of uniform pairs are unchanged (to rounding), the straddling pair is not.
        for x in [0, 1, 4, 5, 6, 7] {
            let (a, b) = (img.get_pixel(x, 0).0, s.get_pixel(x, 0).0);
            assert!(a.iter().zip(b).all(|(p, q)| p.abs_diff(q) <= 1), "x={x}");
        }
        assert!(img.get_pixel(2, 0).0[1].abs_diff(s.get_pixel(2, 0).0[1]) > 20);
        let mut same = img.clone();
        subsample_chroma(&mut same, ChromaSubsampling::Yuv444);
        assert_eq!(same, img);
    }
}
