//! The camera model: every parameter of how the simulated camera turns the board into 8-bit
//! RGB, with defaults that match a cheap 1280x720 video-mode camera at ~774 µm per pixel.
//!
//! Deserialised from the `[camera]` table of a sim config; every field has a default, so an
//! empty table is the default camera. `validate` names the first bad field.

use serde::{Deserialize, Serialize};

/// How MJPEG halves the chroma resolution before the DCT (YCbCr sampling).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum ChromaSubsampling {
    /// Full chroma resolution.
    #[serde(rename = "444")]
    Yuv444,
    /// Chroma halved horizontally: what UVC MJPEG webcams send.
    #[default]
    #[serde(rename = "422")]
    Yuv422,
    /// Chroma halved both ways (still-image JPEG, H.264).
    #[serde(rename = "420")]
    Yuv420,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraModel {
    /// Frame width in pixels (video mode 1280x720).
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// Size of one pixel on the board, µm (the paper: ~774 µm/px).
    pub scale_um_per_px: f64,
    /// Gaussian lens blur (standard deviation) in pixels.
    pub psf_sigma_px: f64,
    /// DN that a reflectance of 1.0 gives at the image centre.
    pub white_dn: f64,
    /// Relative illumination loss at the image corners (quadratic falloff from the centre).
    pub vignetting: f64,
    /// Illumination gradient across the frame, relative change from left to right edge.
    pub light_gradient: f64,
    /// Frame-to-frame illumination flicker, relative RMS (one random gain per frame).
    pub flicker_rms: f64,
    /// Conversion gain: electrons per DN; shot-noise variance in DN² is signal_dn / gain.
    pub gain_e_per_dn: f64,
    /// Read noise in DN RMS.
    pub read_noise_dn: f64,
    /// Camera vibration: RMS displacement of the line of sight per frame and per axis, in µm
    /// on the board (one random offset per frame, constant during its exposure).
    pub vibration_um: f64,
    /// MJPEG compression at this quality (1-100); `None` delivers raw frames.
    pub mjpeg_quality: Option<u8>,
    /// Chroma subsampling applied before the JPEG round trip (only with `mjpeg_quality`).
    pub mjpeg_chroma: ChromaSubsampling,
    /// Sub-samples per pixel side where a pixel straddles an edge (area integration).
    pub supersample: u32,
    /// Frame period of the frame clock, ms (30 fps).
    pub frame_period_ms: f64,
    /// Exposure time, ms (at most the frame period).
    pub exposure_ms: f64,
    /// Sub-exposure renders averaged when the scene moves during an exposure (motion blur).
    pub motion_samples: u32,
    /// Driver buffers queued like V4L2: when the ring is full the oldest frame is dropped.
    pub buffer_frames: u32,
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
            mjpeg_chroma: ChromaSubsampling::default(),
            supersample: 8,
            frame_period_ms: 1000.0 / 30.0,
            exposure_ms: 10.0,
            motion_samples: 8,
            buffer_frames: 4,
        }
    }
}

/// A camera parameter out of range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("camera parameter {field} = {value}: {message}")]
pub struct CameraError {
    pub field: &'static str,
    pub value: String,
    pub message: &'static str,
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

    /// Check every parameter; the error names the first bad one.
    pub fn validate(&self) -> Result<(), CameraError> {
        fn bad(field: &'static str, value: impl ToString, message: &'static str) -> CameraError {
            CameraError {
                field,
                value: value.to_string(),
                message,
            }
        }
        let pos = |field, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(bad(field, v, "must be a finite number > 0"))
            }
        };
        let nonneg = |field, v: f64| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(bad(field, v, "must be a finite number >= 0"))
            }
        };
        if self.width == 0 || self.width > 16384 {
            return Err(bad("width", self.width, "must be 1..=16384"));
        }
        if self.height == 0 || self.height > 16384 {
            return Err(bad("height", self.height, "must be 1..=16384"));
        }
        pos("scale_um_per_px", self.scale_um_per_px)?;
        nonneg("psf_sigma_px", self.psf_sigma_px)?;
        pos("white_dn", self.white_dn)?;
        if !(0.0..1.0).contains(&self.vignetting) {
            return Err(bad("vignetting", self.vignetting, "must be in [0, 1)"));
        }
        if !self.light_gradient.is_finite() || self.light_gradient.abs() >= 2.0 {
            return Err(bad(
                "light_gradient",
                self.light_gradient,
                "must be in (-2, 2)",
            ));
        }
        if !(0.0..0.5).contains(&self.flicker_rms) {
            return Err(bad("flicker_rms", self.flicker_rms, "must be in [0, 0.5)"));
        }
        pos("gain_e_per_dn", self.gain_e_per_dn)?;
        nonneg("read_noise_dn", self.read_noise_dn)?;
        nonneg("vibration_um", self.vibration_um)?;
        if let Some(q) = self.mjpeg_quality {
            if !(1..=100).contains(&q) {
                return Err(bad("mjpeg_quality", q, "must be 1..=100"));
            }
        }
        if !(1..=64).contains(&self.supersample) {
            return Err(bad("supersample", self.supersample, "must be 1..=64"));
        }
        pos("frame_period_ms", self.frame_period_ms)?;
        pos("exposure_ms", self.exposure_ms)?;
        if self.exposure_ms > self.frame_period_ms {
            return Err(bad(
                "exposure_ms",
                self.exposure_ms,
                "must not exceed frame_period_ms",
            ));
        }
        if !(1..=256).contains(&self.motion_samples) {
            return Err(bad(
                "motion_samples",
                self.motion_samples,
                "must be 1..=256",
            ));
        }
        if !(1..=64).contains(&self.buffer_frames) {
            return Err(bad("buffer_frames", self.buffer_frames, "must be 1..=64"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_valid_and_empty_toml_is_default() {
        CameraModel::default().validate().unwrap();
        let c: CameraModel = toml::from_str("").unwrap();
        assert_eq!(c, CameraModel::default());
        let c: CameraModel = toml::from_str("mjpeg_quality = 80\nmjpeg_chroma = \"420\"").unwrap();
        assert_eq!(c.mjpeg_chroma, ChromaSubsampling::Yuv420);
    }

    #[test]
    fn bad_parameter_is_named() {
        let c = CameraModel {
            exposure_ms: 50.0,
            ..Default::default()
        };
        let e = c.validate().unwrap_err();
        assert_eq!(e.field, "exposure_ms");
        let c = CameraModel {
            mjpeg_quality: Some(0),
            ..Default::default()
        };
        assert!(c
            .validate()
            .unwrap_err()
            .to_string()
            .contains("mjpeg_quality"));
    }
}
