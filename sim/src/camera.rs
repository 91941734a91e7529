//! The camera model: every parameter of how the simulated camera turns the board into 8-bit
//! RGB, with defaults that match a cheap 1280x720 video-mode camera at ~774 µm per pixel.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraModel {
    pub width: u32,
    pub height: u32,
    /// Size of one pixel on the board.
    pub scale_um_per_px: f64,
    /// Gaussian lens blur (standard deviation) in pixels.
    pub psf_sigma_px: f64,
    /// DN that a reflectance of 1.0 gives at the image centre.
    pub white_dn: f64,
    /// Relative illumination loss at the image corners (quadratic falloff from the centre).
    pub vignetting: f64,
    /// Illumination gradient across the frame, relative change from left to right edge.
    pub light_gradient: f64,
    /// Frame-to-frame illumination flicker, relative RMS.
    pub flicker_rms: f64,
    /// Conversion gain: electrons per DN; shot-noise variance in DN² is signal_dn / gain.
    pub gain_e_per_dn: f64,
    /// Read noise in DN RMS.
    pub read_noise_dn: f64,
    /// Camera vibration: RMS displacement of the line of sight per frame, in µm on the board.
    pub vibration_um: f64,
    /// MJPEG compression at this quality (1-100); `None` delivers raw frames.
    pub mjpeg_quality: Option<u8>,
    /// Sub-samples per pixel side where a pixel straddles an edge (area integration).
    pub supersample: u32,
    /// Frame period and exposure time (the frame clock).
    pub frame_period_ms: f64,
    pub exposure_ms: f64,
}

impl Default for CameraModel {
    fn default() -> Self {
        CameraModel {
            width: 1280,
            height: 720,
            scale_um_per_px: 774.0,
            psf_sigma_px: 0.7,
            white_dn: 235.0,
            vignetting: 0.25,
            light_gradient: 0.08,
            flicker_rms: 0.005,
            gain_e_per_dn: 40.0,
            read_noise_dn: 1.0,
            vibration_um: 2.0,
            mjpeg_quality: None,
            supersample: 8,
            frame_period_ms: 1000.0 / 30.0,
            exposure_ms: 10.0,
        }
    }
}

impl CameraModel {
    /// Relative illumination at pixel (u, v): vignetting and a left-to-right gradient.
    pub fn illumination(&self, u: f64, v: f64) -> f64 {
        let (cx, cy) = (self.width as f64 / 2.0, self.height as f64 / 2.0);
        let (du, dv) = ((u + 0.5 - cx) / cx, (v + 0.5 - cy) / cy);
        // Normalised so the corner (du, dv) = (1, 1) has r² = 1.
        let r2 = (du * du + dv * dv) / 2.0;
        (1.0 - self.vignetting * r2) * (1.0 + 0.5 * self.light_gradient * du)
    }

    /// Noise variance in DN² for an expected signal in DN (shot + read + quantisation).
    pub fn noise_var_dn2(&self, signal_dn: f64) -> f64 {
        signal_dn.max(0.0) / self.gain_e_per_dn
            + self.read_noise_dn * self.read_noise_dn
            + 1.0 / 12.0
    }
}
