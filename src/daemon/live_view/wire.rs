//! The live view's wire types (docs/protocol.md, "Live view"): what `snap` answers and what a
//! `preview` event carries, and the options both take. Part of the protocol: the requests
//! and the reply/event variants that carry these are in `daemon::protocol`.

use serde::{Deserialize, Serialize};

/// Highest `max_fps` a preview may ask for.
pub const MAX_FPS: f64 = 60.0;
/// Lowest `max_fps` a preview may ask for: a frame every 100 s.
pub const MIN_FPS: f64 = 0.01;

/// How a frame is shown: a region of it (`crop`: x, y, w, h in frame pixels; default the
/// whole frame), then scaled by `scale` (0 < scale <= 1; default 1).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ViewOptions {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crop: Option<[u32; 4]>,
}

/// Where the stages were when the frame was taken (µm; a stage not read is left out).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize, schemars::JsonSchema)]
pub struct StagePositions {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_um: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub piezo_um: Option<f64>,
}

/// One target found in the frame (in whole-frame coordinates, whatever the crop).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ViewTarget {
    /// The board's name for it (none when the layout does not match).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// The outer ring's centre, frame px, and that times the rig's scale, µm.
    pub centre_px: [f64; 2],
    pub centre_um: [f64; 2],
    /// Inner centre minus outer centre, µm at the global scale (`scale_um_per_px`): one
    /// frame, no calibration applied, unlike a job's `offset_um`.
    pub offset_um: [f64; 2],
    pub outer_radius_px: f64,
    pub inner_radius_px: f64,
    /// Gradient energy per px of edge over contrast² (1/px; higher is sharper): see
    /// `rigd_core::pipeline::focus`. None when the target's box has no contrast.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub focus: Option<f64>,
    /// The Gaussian edge blur σ that focus means, px.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub edge_sigma_px: Option<f64>,
    /// Why the estimator could not measure it (the centre is then detection's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// One frame of the live view: a `snap`'s result and a `preview` event's body.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ViewFrame {
    /// The job's frame index, when the frame is a job's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub index: Option<u32>,
    /// Exposure time (the driver's timestamp), Unix seconds.
    pub t_unix_s: f64,
    /// The camera's frame number.
    pub sequence: u64,
    pub stage_um: StagePositions,
    /// The whole frame's size, px.
    pub frame_size: [u32; 2],
    /// The region shown, frame px: x, y, w, h.
    pub crop: [u32; 4],
    pub scale: f64,
    /// The image's size, px (the crop times the scale).
    pub width: u32,
    pub height: u32,
    /// The image: PNG (8-bit RGB), base64 (RFC 4648, with padding).
    pub png_base64: String,
    pub targets: Vec<ViewTarget>,
}

/// The result of `snap`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SnapReply {
    /// The job whose frame this is (none: the live view grabbed it, no job ran).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub job_id: Option<u64>,
    #[serde(flatten)]
    pub frame: ViewFrame,
}

/// The result of `preview`: the subscription as it runs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct PreviewReply {
    pub max_fps: f64,
    pub scale: f64,
    pub crop: [u32; 4],
    pub frame_size: [u32; 2],
}

/// The result of `preview_stop`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct PreviewStopReply {
    /// Whether a preview was running.
    pub stopped: bool,
}
