//! What a calibration is fitted from: a scan of known stage displacements and the targets'
//! outer-circle centres in each frame, as the pipeline measured them.

use serde::{Deserialize, Serialize};

/// Which positions are the length reference.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum Reference {
    /// The commanded positions (`steps.csv`'s `position_um`).
    Commanded,
    /// The interferometer's readings (`interferometer_um`).
    Interferometer,
}

impl Reference {
    /// The relative standard uncertainty of the reference's length scale assumed when the
    /// caller states none: a commanded ballscrew axis 1e-4 (10 µm over 100 mm, its
    /// leadscrew's periodic error is in the residuals), an XL-80 1e-6 (its ±0.5 ppm with
    /// the environment's compensation).
    pub fn default_rel_u(self) -> f64 {
        match self {
            Reference::Commanded => 1e-4,
            Reference::Interferometer => 1e-6,
        }
    }
}

/// One target over the scan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TargetTrack {
    /// The board's name, when the board was given and it matched.
    pub name: Option<String>,
    /// Outer-circle centre in each frame (`None` where it was not measured).
    pub centres_px: Vec<Option<[f64; 2]>>,
    /// Rim radii in frame 0, px.
    pub outer_radius_px: f64,
    pub inner_radius_px: f64,
}

/// A scan of known displacements.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Scan {
    pub frame_size: (u32, u32),
    /// The global scale the scan was processed with (the consumer's fingerprint).
    pub scale_um_per_px: f64,
    /// Image displacement per unit of axis travel, as the options gave it (a starting
    /// guess for the stage's direction).
    pub axis_dir: [f64; 2],
    pub reference: Reference,
    /// The stage's position of each frame, µm (the reference).
    pub positions_um: Vec<f64>,
    /// The piezo's, in a 2-D scan.
    pub piezo_um: Option<Vec<f64>>,
    pub targets: Vec<TargetTrack>,
    /// Each target's ink density over the scan ([`Pipeline::record_tracks`] reads it):
    /// what the print's statistics are learnt from. Empty: not learnt.
    ///
    /// [`Pipeline::record_tracks`]: crate::pipeline::Pipeline::record_tracks
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub ink_maps: Vec<super::InkMap>,
    /// The lens's lateral colour as the scan's frames show it
    /// ([`Pipeline::record_tracks`] measures it). `None`: not measured.
    ///
    /// [`Pipeline::record_tracks`]: crate::pipeline::Pipeline::record_tracks
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lateral_colour: Option<crate::pipeline::lateral::LateralColourFit>,
}

/// Why a scan cannot be calibrated, or a calibration not applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    #[error("{got} steps: a calibration needs at least {need} frames of known displacement")]
    TooFewSteps { got: usize, need: usize },
    #[error("the scan travels {travel_px:.1} px in the image: at least {need_px} px are needed to measure the local scale")]
    TooShortTravel { travel_px: f64, need_px: f64 },
    #[error("{got} targets measured in at least {steps} frames: the field model needs {need}")]
    TooFewTargets {
        got: usize,
        need: usize,
        steps: usize,
    },
    #[error("{what}: {positions} positions for {frames} frames")]
    Positions {
        what: &'static str,
        positions: usize,
        frames: usize,
    },
    #[error(
        "the field-model fit did not converge or its parameters are not fixed by the scan ({0})"
    )]
    Fit(String),
    #[error("calibration record version {got}: this rigd reads version {want}")]
    Version { got: u32, want: u32 },
    #[error("calibration {id} was fitted on {cal_w}x{cal_h} frames; these are {got_w}x{got_h}")]
    FrameSize {
        id: String,
        cal_w: u32,
        cal_h: u32,
        got_w: u32,
        got_h: u32,
    },
    #[error("calibration {id}: ink_fields[{index}] {what}")]
    InkField {
        id: String,
        index: usize,
        what: String,
    },
    #[error("calibration {id}: lateral_colour {what}")]
    LateralColour { id: String, what: String },
}

impl Scan {
    /// Travel of frame `i` from frame 0: (stage, piezo), µm.
    pub(crate) fn travel_um(&self, i: usize) -> [f64; 2] {
        let q = |v: &Vec<f64>| v[i] - v[0];
        [
            self.positions_um[i] - self.positions_um[0],
            self.piezo_um.as_ref().map_or(0.0, q),
        ]
    }

    /// Whether the piezo moves in the scan.
    pub(crate) fn moves_piezo(&self) -> bool {
        self.piezo_um
            .as_ref()
            .is_some_and(|v| v.iter().any(|&q| (q - v[0]).abs() > 1e-9))
    }

    pub(crate) fn check(&self) -> Result<(), CalibrationError> {
        let frames = self
            .targets
            .iter()
            .map(|t| t.centres_px.len())
            .max()
            .unwrap_or(0);
        if self.positions_um.len() != frames {
            return Err(CalibrationError::Positions {
                what: "stage",
                positions: self.positions_um.len(),
                frames,
            });
        }
        if let Some(q) = self.piezo_um.as_ref().filter(|q| q.len() != frames) {
            return Err(CalibrationError::Positions {
                what: "piezo",
                positions: q.len(),
                frames,
            });
        }
        Ok(())
    }
}
