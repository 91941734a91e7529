//! What a V4L2 camera is asked for. Outside the `v4l2` feature's module so a build without
//! it still reads a `[camera]` table (and says how to rebuild when one asks for V4L2).

use super::pixfmt::PixelFormat;
use std::time::Duration;

/// What the camera was asked for.
#[derive(Debug, Clone, PartialEq)]
pub struct V4l2Options {
    /// A device path, or a device name (case-insensitive) as `hw::v4l2::list_devices` shows it.
    pub device: String,
    pub width: u32,
    pub height: u32,
    pub format: PixelFormat,
    pub exposure_us: Option<u32>,
    pub gain: Option<i64>,
    pub white_balance_k: Option<u32>,
    /// The camera's sharpening (V4L2 `sharpness`, its own units; 0 on most UVC webcams is
    /// off). Absent: leave the camera's setting alone.
    pub sharpness: Option<i64>,
    pub buffers: u32,
    pub frame_timeout: Duration,
}

impl V4l2Options {
    pub fn new(device: impl Into<String>, width: u32, height: u32, format: PixelFormat) -> Self {
        V4l2Options {
            device: device.into(),
            width,
            height,
            format,
            exposure_us: None,
            gain: None,
            white_balance_k: None,
            sharpness: None,
            buffers: 4,
            frame_timeout: Duration::from_secs(2),
        }
    }
}
