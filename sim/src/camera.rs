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

/// Colour filter array in front of the sensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Cfa {
    /// Every pixel sees all three channels (the ideal camera).
    #[default]
    None,
    /// Bayer RGGB: red at (even x, even y), blue at (odd, odd), green elsewhere.
    Rggb,
}

/// How the camera fills in the two channels a Bayer pixel did not see.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Demosaic {
    /// Average of the nearest samples of the channel.
    #[default]
    Bilinear,
    /// Green along the direction of the smaller gradient, red and blue as bilinear colour
    /// differences to green (what cheap ISPs do).
    EdgeAware,
}

/// The camera's output transfer curve.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Gamma {
    /// DN proportional to light (the ideal camera).
    #[default]
    Linear,
    /// The sRGB curve (linear toe, 1/2.4 power), as webcams deliver.
    Srgb,
}

/// The pixel format of the uncompressed path (`mjpeg_quality` unset).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Uncompressed {
    /// Full RGB per pixel (the ideal camera).
    #[default]
    Rgb,
    /// YUYV 4:2:2: luma per pixel, chroma per horizontal pair (UVC's uncompressed format).
    Yuyv,
}

/// A named set of camera parameters (`[camera] profile = "webcam"`); the table's other
/// keys override the profile's values.
pub const PROFILES: [&str; 3] = ["ideal", "webcam", "stress"];

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, remote = "Self")]
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

    // --- optics and geometry (all off in the ideal camera) ---
    /// Focal length in px: sets the perspective of a tilted board and normalises the radial
    /// distortion (1000 px: a ~65° horizontal field at 1280 px).
    pub focal_length_px: f64,
    /// Board tilt about the image x axis, degrees: positive puts the bottom edge farther.
    pub tilt_x_deg: f64,
    /// Board tilt about the image y axis, degrees: positive puts the right edge farther.
    pub tilt_y_deg: f64,
    /// How the stage's rail lies: 0 moves the board in its own plane (the rail parallel to
    /// the board), 1 moves the camera parallel to its sensor, so a tilted board's distance
    /// changes over the travel (a zoom of `tan(tilt)/distance` per µm); in between, a rail
    /// between the two.
    pub rail_along_sensor: f64,
    /// Brown radial distortion `r_d = r_u (1 + k1 r² + k2 r⁴)`, r normalised by the focal
    /// length (k1 < 0: barrel).
    pub distortion_k1: f64,
    pub distortion_k2: f64,
    /// Lateral colour: magnification of the red image relative to the green (0.0004 = red
    /// lands 0.04 % farther from the centre).
    pub lateral_colour_r: f64,
    /// Lateral colour of the blue image relative to the green.
    pub lateral_colour_b: f64,

    // --- sensor and image processing ---
    /// Colour filter array (`"none"` or `"rggb"`).
    pub cfa: Cfa,
    /// Colour crosstalk: fraction of each other channel a Bayer pixel picks up.
    pub crosstalk: f64,
    /// Demosaicing of the Bayer mosaic (`"bilinear"` or `"edge_aware"`).
    pub demosaic: Demosaic,
    /// Output curve (`"linear"` or `"srgb"`).
    pub gamma: Gamma,
    /// Unsharp mask on luma: `Y += amount·(Y − blur(Y))` (0 = off).
    pub sharpen_amount: f64,
    /// Width of the unsharp mask's Gaussian, px.
    pub sharpen_sigma_px: f64,
    /// Fraction of the vignetting the camera's lens-shading correction undoes (a gain after
    /// the noise, so corners get noisier).
    pub vignetting_correction: f64,

    // --- transport ---
    /// Pixel format without MJPEG (`"rgb"` or `"yuyv"`).
    pub uncompressed: Uncompressed,

    // --- light ---
    /// Auto-exposure wander: RMS relative gain change from one frame to the next.
    pub ae_wander_rms: f64,
    /// Auto-exposure bounds: the gain stays within 1 ± this (it reflects off them).
    pub ae_gain_range: f64,
    /// Depth of the light's modulation at `flicker_hz` (mains lighting), relative.
    pub flicker_band_depth: f64,
    /// Frequency of the light's modulation, Hz (twice the mains frequency).
    pub flicker_hz: f64,
    /// Rolling shutter: time between the exposure starts of successive rows, µs.
    pub row_time_us: f64,

    // --- printed targets ---
    /// RMS radial roughness of every printed edge, µm on the board.
    pub edge_roughness_um: f64,
    /// Correlation length of the roughness along the edge, µm.
    pub edge_roughness_corr_um: f64,
    /// RMS relative variation of the ink's density (low-frequency).
    pub ink_density_rms: f64,
    /// Correlation length of the ink density variation, µm.
    pub ink_density_corr_um: f64,
    /// Seed of the print's roughness and ink (the print is the same in every frame).
    pub print_seed: u64,
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
            focal_length_px: 1000.0,
            tilt_x_deg: 0.0,
            tilt_y_deg: 0.0,
            rail_along_sensor: 0.0,
            distortion_k1: 0.0,
            distortion_k2: 0.0,
            lateral_colour_r: 0.0,
            lateral_colour_b: 0.0,
            cfa: Cfa::None,
            crosstalk: 0.0,
            demosaic: Demosaic::Bilinear,
            gamma: Gamma::Linear,
            sharpen_amount: 0.0,
            sharpen_sigma_px: 1.0,
            vignetting_correction: 0.0,
            uncompressed: Uncompressed::Rgb,
            ae_wander_rms: 0.0,
            ae_gain_range: 0.05,
            flicker_band_depth: 0.0,
            flicker_hz: 100.0,
            row_time_us: 30.0,
            edge_roughness_um: 0.0,
            edge_roughness_corr_um: 1000.0,
            ink_density_rms: 0.0,
            ink_density_corr_um: 3000.0,
            print_seed: 1,
        }
    }
}

impl CameraModel {
    /// The camera of a named profile: `"ideal"` (the default: a clean, matched camera),
    /// `"webcam"` (every webcam effect at a realistic strength) or `"stress"` (strong
    /// distortion, 3° tilt, MJPEG q50, dim light, a soft lens). docs/sim.md lists the values.
    pub fn profile(name: &str) -> Result<CameraModel, CameraError> {
        let ideal = CameraModel::default();
        match name {
            "ideal" => Ok(ideal),
            "webcam" => Ok(CameraModel {
                psf_sigma_px: 0.8,
                white_dn: 200.0,
                vignetting: 0.35,
                light_gradient: 0.12,
                gain_e_per_dn: 20.0,
                read_noise_dn: 1.5,
                exposure_ms: 8.0,
                mjpeg_quality: Some(85),
                mjpeg_chroma: ChromaSubsampling::Yuv420,
                tilt_x_deg: 1.0,
                tilt_y_deg: 1.5,
                distortion_k1: -0.03,
                distortion_k2: 0.005,
                lateral_colour_r: 4e-4,
                lateral_colour_b: -4e-4,
                cfa: Cfa::Rggb,
                crosstalk: 0.05,
                demosaic: Demosaic::EdgeAware,
                gamma: Gamma::Srgb,
                sharpen_amount: 0.8,
                sharpen_sigma_px: 1.0,
                vignetting_correction: 0.7,
                uncompressed: Uncompressed::Yuyv,
                ae_wander_rms: 0.003,
                ae_gain_range: 0.04,
                flicker_band_depth: 0.1,
                edge_roughness_um: 8.0,
                ink_density_rms: 0.04,
                ..ideal
            }),
            "stress" => Ok(CameraModel {
                psf_sigma_px: 1.2,
                white_dn: 110.0,
                vignetting: 0.45,
                light_gradient: 0.3,
                gain_e_per_dn: 8.0,
                read_noise_dn: 2.5,
                exposure_ms: 15.0,
                mjpeg_quality: Some(50),
                tilt_x_deg: 1.0,
                tilt_y_deg: 3.0,
                distortion_k1: -0.1,
                distortion_k2: 0.03,
                lateral_colour_r: 1e-3,
                lateral_colour_b: -1e-3,
                crosstalk: 0.08,
                demosaic: Demosaic::Bilinear,
                sharpen_amount: 1.2,
                sharpen_sigma_px: 1.5,
                vignetting_correction: 0.5,
                ae_wander_rms: 0.01,
                ae_gain_range: 0.08,
                flicker_band_depth: 0.25,
                edge_roughness_um: 15.0,
                ink_density_rms: 0.08,
                ..CameraModel::profile("webcam")?
            }),
            _ => Err(CameraError {
                field: "profile",
                value: name.to_string(),
                message: "must be one of \"ideal\", \"webcam\", \"stress\"",
            }),
        }
    }

    /// Where the stage's travel `travel_um` (µm along the image's x and y) puts the camera:
    /// the board point it moves the line of sight by, and how much farther the board is.
    /// A rail along the sensor moves the axis' point on a board tilted by `t` by
    /// `travel / cos t` and its distance by `travel · tan t`; a rail along the board, by
    /// `travel` and nothing.
    pub fn rail_pose(&self, travel_um: [f64; 2]) -> ([f64; 2], f64) {
        let f = self.rail_along_sensor;
        let (tx, ty) = (self.tilt_x_deg.to_radians(), self.tilt_y_deg.to_radians());
        let along = |p: f64, t: f64| p * (1.0 - f + f / t.cos());
        let board = [along(travel_um[0], ty), along(travel_um[1], tx)];
        let depth = f * (travel_um[0] * ty.tan() + travel_um[1] * tx.tan());
        (board, depth)
    }

    /// Whether the scene's geometry or print departs from the ideal (tilt, distortion,
    /// lateral colour, rough edges, uneven ink): such shapes are rendered through `Lens`.
    pub fn needs_warp(&self) -> bool {
        self.tilt_x_deg != 0.0
            || self.tilt_y_deg != 0.0
            || self.distortion_k1 != 0.0
            || self.distortion_k2 != 0.0
            || self.lateral_colour_r != 0.0
            || self.lateral_colour_b != 0.0
            || self.edge_roughness_um != 0.0
            || self.ink_density_rms != 0.0
    }

    /// Whether frames go through the sensor and image processing of a webcam (Bayer,
    /// demosaicing, gamma, sharpening, lens-shading correction) rather than straight to 8 bits.
    pub fn needs_isp(&self) -> bool {
        self.cfa != Cfa::None
            || self.gamma != Gamma::Linear
            || self.sharpen_amount != 0.0
            || self.vignetting_correction != 0.0
    }
}

// `[camera] profile = "webcam"` starts from the profile and the table's other keys override
// it; without `profile` the table starts from the ideal camera. Serialising writes
// every field (no profile), so a written config reads back the same camera.
impl Serialize for CameraModel {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        CameraModel::serialize(self, s)
    }
}

impl<'de> Deserialize<'de> for CameraModel {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<CameraModel, D::Error> {
        use serde::de::Error;
        let mut table = toml::Table::deserialize(d)?;
        let base = match table.remove("profile") {
            None => {
                return CameraModel::deserialize(toml::Value::Table(table))
                    .map_err(D::Error::custom)
            }
            Some(toml::Value::String(name)) => {
                CameraModel::profile(&name).map_err(D::Error::custom)?
            }
            Some(other) => {
                return Err(D::Error::custom(format!(
                    "camera parameter profile = {other}: must be a string"
                )))
            }
        };
        let mut merged = match toml::Value::try_from(ProfileBase(&base)) {
            Ok(toml::Value::Table(t)) => t,
            _ => {
                return Err(D::Error::custom(
                    "camera profile does not serialise as a table",
                ))
            }
        };
        merged.extend(table);
        CameraModel::deserialize(toml::Value::Table(merged)).map_err(D::Error::custom)
    }
}

/// Serialises a camera through the derived (remote) impl.
struct ProfileBase<'a>(&'a CameraModel);

impl Serialize for ProfileBase<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        CameraModel::serialize(self.0, s)
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

    /// Squared distance of pixel (u, v) from the image centre, 1 at the corners (the
    /// vignetting's radius).
    pub fn radius2(&self, u: f64, v: f64) -> f64 {
        let (cx, cy) = (self.width as f64 / 2.0, self.height as f64 / 2.0);
        let (du, dv) = ((u + 0.5 - cx) / cx, (v + 0.5 - cy) / cy);
        (du * du + dv * dv) / 2.0
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
        self.validate_webcam()
    }

    /// The webcam effects' parameters (see `validate`).
    fn validate_webcam(&self) -> Result<(), CameraError> {
        fn bad(field: &'static str, value: f64, message: &'static str) -> CameraError {
            CameraError {
                field,
                value: value.to_string(),
                message,
            }
        }
        let within = |field, v: f64, lo: f64, hi: f64, message| {
            if v.is_finite() && v >= lo && v < hi {
                Ok(())
            } else {
                Err(bad(field, v, message))
            }
        };
        within(
            "focal_length_px",
            self.focal_length_px,
            50.0,
            1e5,
            "must be in [50, 100000)",
        )?;
        within(
            "tilt_x_deg",
            self.tilt_x_deg.abs(),
            0.0,
            30.0,
            "must be in (-30, 30)",
        )?;
        within(
            "tilt_y_deg",
            self.tilt_y_deg.abs(),
            0.0,
            30.0,
            "must be in (-30, 30)",
        )?;
        within(
            "rail_along_sensor",
            self.rail_along_sensor,
            0.0,
            1.0 + 1e-12,
            "must be in [0, 1]",
        )?;
        within(
            "distortion_k1",
            self.distortion_k1.abs(),
            0.0,
            1.0,
            "must be in (-1, 1)",
        )?;
        within(
            "distortion_k2",
            self.distortion_k2.abs(),
            0.0,
            1.0,
            "must be in (-1, 1)",
        )?;
        // The distortion must stay monotonic out past the frame's corners.
        let r_corner = (self.width as f64).hypot(self.height as f64) / 2.0 / self.focal_length_px;
        for i in 0..=100 {
            let r2 = (1.3 * r_corner * i as f64 / 100.0).powi(2);
            if 1.0 + 3.0 * self.distortion_k1 * r2 + 5.0 * self.distortion_k2 * r2 * r2 < 0.2 {
                return Err(bad(
                    "distortion_k1",
                    self.distortion_k1,
                    "folds the image over within the frame (with distortion_k2 and focal_length_px)",
                ));
            }
        }
        let lat = "must be in (-0.01, 0.01)";
        within(
            "lateral_colour_r",
            self.lateral_colour_r.abs(),
            0.0,
            0.01,
            lat,
        )?;
        within(
            "lateral_colour_b",
            self.lateral_colour_b.abs(),
            0.0,
            0.01,
            lat,
        )?;
        within("crosstalk", self.crosstalk, 0.0, 0.3, "must be in [0, 0.3)")?;
        within(
            "sharpen_amount",
            self.sharpen_amount,
            0.0,
            5.0,
            "must be in [0, 5)",
        )?;
        within(
            "sharpen_sigma_px",
            self.sharpen_sigma_px,
            0.3,
            5.0,
            "must be in [0.3, 5)",
        )?;
        within(
            "vignetting_correction",
            self.vignetting_correction,
            0.0,
            1.0001,
            "must be in [0, 1]",
        )?;
        within(
            "ae_wander_rms",
            self.ae_wander_rms,
            0.0,
            0.1,
            "must be in [0, 0.1)",
        )?;
        within(
            "ae_gain_range",
            self.ae_gain_range,
            0.0,
            0.5,
            "must be in [0, 0.5)",
        )?;
        within(
            "flicker_band_depth",
            self.flicker_band_depth,
            0.0,
            1.0,
            "must be in [0, 1)",
        )?;
        within(
            "flicker_hz",
            self.flicker_hz,
            1e-3,
            1e6,
            "must be a finite number > 0",
        )?;
        within(
            "row_time_us",
            self.row_time_us,
            0.0,
            1e5,
            "must be in [0, 100000)",
        )?;
        within(
            "edge_roughness_um",
            self.edge_roughness_um,
            0.0,
            1e4,
            "must be in [0, 10000)",
        )?;
        within(
            "edge_roughness_corr_um",
            self.edge_roughness_corr_um,
            1.0,
            1e6,
            "must be in [1, 1e6)",
        )?;
        within(
            "ink_density_rms",
            self.ink_density_rms,
            0.0,
            0.5,
            "must be in [0, 0.5)",
        )?;
        within(
            "ink_density_corr_um",
            self.ink_density_corr_um,
            1.0,
            1e7,
            "must be in [1, 1e7)",
        )?;
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
