//! Real cameras through V4L2 (the `v4l` crate), behind the cargo feature `v4l2`.
//!
//! - Open by device path or by the name the kernel gives the device.
//! - Negotiate YUYV, MJPG or RGB3 at the configured size; the driver may adjust the size or
//!   refuse the format, and the camera then uses what the driver returned (and says so).
//! - Memory-mapped streaming; each buffer is sliced to its `bytesused`, every dequeue has a
//!   deadline, buffers the driver flags as errored are skipped.
//! - Manual exposure, gain and white balance from config (metrology needs them fixed): the
//!   controls that exist are set (auto modes off first) and read back; the ones that don't are
//!   reported, not fatal.
//! - Timestamps: the driver's are CLOCK_MONOTONIC; each is put on the system clock with the
//!   monotonic-to-wall offset measured at dequeue, so `grab_fresh` can compare them with the
//!   instant a move settled.

use super::pixfmt::{self, PixelFormat};
pub use super::v4l2_options::V4l2Options;
use super::{Camera, Frame, HwError};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};
use v4l::buffer::{Flags as BufFlags, Type as BufType};
use v4l::control::{Control, Value};
use v4l::io::mmap::Stream;
use v4l::io::traits::CaptureStream;
use v4l::video::Capture;
use v4l::{Device, FourCC};

/// Control ids from linux/v4l2-controls.h (stable kernel ABI).
mod cid {
    pub const AUTO_WHITE_BALANCE: u32 = 0x0098_090c;
    pub const AUTOGAIN: u32 = 0x0098_0912;
    pub const GAIN: u32 = 0x0098_0913;
    pub const WHITE_BALANCE_TEMPERATURE: u32 = 0x0098_091a;
    /// Menu: 0 auto, 1 manual, 2 shutter priority, 3 aperture priority.
    pub const EXPOSURE_AUTO: u32 = 0x009a_0901;
    pub const EXPOSURE_MANUAL: i64 = 1;
    /// In units of 100 µs.
    pub const EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
    pub const SHARPNESS: u32 = 0x0098_091b;
}

/// Longest single wait (the v4l crate's poll timeout is an i32 of milliseconds).
const MAX_WAIT: Duration = Duration::from_secs(3600);

/// How the controls went.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ControlReport {
    /// (control, requested, read back)
    pub applied: Vec<(String, i64, i64)>,
    /// Controls the config asked for that the device does not have.
    pub missing: Vec<String>,
    /// (control, error) for controls that exist but refused the value.
    pub failed: Vec<(String, String)>,
}

/// What a device offers.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct DeviceInfo {
    pub path: PathBuf,
    pub name: String,
    pub driver: String,
    pub bus: String,
    pub formats: Vec<FormatInfo>,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FormatInfo {
    pub fourcc: String,
    pub description: String,
    /// rigd can convert it.
    pub supported: bool,
    /// `1280x720`, or `16x16 - 1920x1080 step 2/2`.
    pub sizes: Vec<String>,
}

pub struct V4l2Camera {
    label: String,
    path: PathBuf,
    // Declared before `dev`: the stream (STREAMOFF, buffers freed) goes first.
    stream: Option<Stream<'static>>,
    dev: Device,
    format: PixelFormat,
    width: u32,
    height: u32,
    stride: usize,
    buffers: u32,
    timeout: Duration,
    requested: (u32, u32, PixelFormat),
    controls: ControlReport,
    /// Frames dropped by `grab_fresh` as older than asked (since open).
    pub dropped_stale: u64,
    /// Buffers the driver flagged as errored (since open).
    pub dropped_errored: u64,
}

fn hw_err(device: &str, message: impl std::fmt::Display) -> HwError {
    HwError::Other {
        device: device.to_string(),
        message: message.to_string(),
    }
}

fn fourcc_of(f: PixelFormat) -> FourCC {
    FourCC::new(&f.fourcc())
}

fn fourcc_str(f: FourCC) -> String {
    f.str()
        .map(str::to_string)
        .unwrap_or_else(|_| format!("{:?}", f.repr))
}

/// Find a device: a path as given, else by name among /sys/class/video4linux.
pub fn resolve_device(device: &str) -> Result<PathBuf, HwError> {
    if device.starts_with('/') || device.starts_with('.') {
        return Ok(PathBuf::from(device));
    }
    let mut names = Vec::new();
    for (path, name) in video_nodes() {
        if name.eq_ignore_ascii_case(device.trim()) {
            // A camera often has a second node for metadata: take the one that captures.
            if let Ok(dev) = Device::with_path(&path) {
                if dev.enum_formats().map(|f| !f.is_empty()).unwrap_or(false) {
                    return Ok(path);
                }
            }
        }
        names.push(format!("{} ({name})", path.display()));
    }
    Err(hw_err(
        device,
        format!(
            "no capture device of that name; devices: {}",
            if names.is_empty() {
                "none".into()
            } else {
                names.join(", ")
            }
        ),
    ))
}

/// (/dev/videoN, name) for every node the kernel lists, sorted by path.
fn video_nodes() -> Vec<(PathBuf, String)> {
    let mut out = Vec::new();
    if let Ok(entries) = std::fs::read_dir("/sys/class/video4linux") {
        for e in entries.flatten() {
            let node = e.file_name().to_string_lossy().to_string();
            let name = std::fs::read_to_string(e.path().join("name")).unwrap_or_default();
            out.push((Path::new("/dev").join(&node), name.trim().to_string()));
        }
    }
    out.sort();
    out
}

/// Describe one device: identity and the capture formats and sizes it offers.
pub fn describe(path: &Path) -> Result<DeviceInfo, HwError> {
    let label = path.display().to_string();
    let dev = Device::with_path(path).map_err(|e| hw_err(&label, format!("cannot open: {e}")))?;
    let caps = dev
        .query_caps()
        .map_err(|e| hw_err(&label, format!("VIDIOC_QUERYCAP: {e}")))?;
    let mut formats = Vec::new();
    for d in dev.enum_formats().unwrap_or_default() {
        let sizes = dev
            .enum_framesizes(d.fourcc)
            .unwrap_or_default()
            .into_iter()
            .map(|s| match s.size {
                v4l::framesize::FrameSizeEnum::Discrete(d) => format!("{}x{}", d.width, d.height),
                v4l::framesize::FrameSizeEnum::Stepwise(s) => format!(
                    "{}x{} - {}x{} step {}/{}",
                    s.min_width,
                    s.min_height,
                    s.max_width,
                    s.max_height,
                    s.step_width,
                    s.step_height
                ),
            })
            .collect();
        formats.push(FormatInfo {
            fourcc: fourcc_str(d.fourcc),
            description: d.description.clone(),
            supported: PixelFormat::from_fourcc(d.fourcc.repr).is_some(),
            sizes,
        });
    }
    Ok(DeviceInfo {
        path: path.to_path_buf(),
        name: caps.card,
        driver: caps.driver,
        bus: caps.bus,
        formats,
    })
}

/// Every video node that can capture (has at least one capture format).
pub fn list_devices() -> Vec<DeviceInfo> {
    video_nodes()
        .into_iter()
        .filter_map(|(p, _)| describe(&p).ok())
        .filter(|d| !d.formats.is_empty())
        .collect()
}

/// CLOCK_MONOTONIC now.
fn monotonic_now() -> Duration {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec into the pointer we own.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
}

/// A monotonic buffer timestamp on the system clock.
pub fn monotonic_to_system(ts: Duration) -> SystemTime {
    let (mono, wall) = (monotonic_now(), SystemTime::now());
    match mono.checked_sub(ts) {
        Some(age) => wall.checked_sub(age).unwrap_or(wall),
        None => wall + (ts - mono),
    }
}

impl V4l2Camera {
    pub fn open(opts: &V4l2Options) -> Result<Self, HwError> {
        let path = resolve_device(&opts.device)?;
        let label = path.display().to_string();
        let dev = Device::with_path(&path).map_err(|e| {
            hw_err(
                &label,
                format!("cannot open: {e} (is the user in the `video` group?)"),
            )
        })?;
        let caps = dev
            .query_caps()
            .map_err(|e| hw_err(&label, format!("VIDIOC_QUERYCAP: {e}")))?;
        let label = format!("{} ({})", label, caps.card);

        // Negotiate: ask for the configured format and size, take what comes back.
        let mut want = dev
            .format()
            .map_err(|e| hw_err(&label, format!("VIDIOC_G_FMT: {e}")))?;
        want.width = opts.width;
        want.height = opts.height;
        want.fourcc = fourcc_of(opts.format);
        let got = dev
            .set_format(&want)
            .map_err(|e| hw_err(&label, format!("VIDIOC_S_FMT {}: {e}", opts.format)))?;
        let Some(format) = PixelFormat::from_fourcc(got.fourcc.repr) else {
            let offered: Vec<String> = dev
                .enum_formats()
                .unwrap_or_default()
                .iter()
                .map(|d| fourcc_str(d.fourcc))
                .collect();
            return Err(hw_err(
                &label,
                format!(
                    "asked for {}, the driver chose {} which rigd cannot convert; it offers {}",
                    opts.format,
                    fourcc_str(got.fourcc),
                    offered.join(", ")
                ),
            ));
        };
        if (got.width, got.height, format) != (opts.width, opts.height, opts.format) {
            tracing::warn!(
                "{label}: asked for {}x{} {}, the driver gave {}x{} {}; using that",
                opts.width,
                opts.height,
                opts.format,
                got.width,
                got.height,
                format
            );
        }
        let mut cam = V4l2Camera {
            label,
            path,
            stream: None,
            dev,
            format,
            width: got.width,
            height: got.height,
            stride: got.stride as usize,
            buffers: opts.buffers.max(1),
            timeout: opts.frame_timeout,
            requested: (opts.width, opts.height, opts.format),
            controls: ControlReport::default(),
            dropped_stale: 0,
            dropped_errored: 0,
        };
        cam.controls = cam.apply_controls(opts);
        for m in &cam.controls.missing {
            tracing::warn!(
                "{}: has no {m} control; it stays as the camera sets it",
                cam.label
            );
        }
        for (c, e) in &cam.controls.failed {
            tracing::warn!("{}: setting {c} failed: {e}", cam.label);
        }
        Ok(cam)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
    pub fn format(&self) -> PixelFormat {
        self.format
    }
    /// Bytes per line the driver uses.
    pub fn stride(&self) -> usize {
        self.stride
    }
    /// What was asked for (width, height, format), to compare with what was negotiated.
    pub fn requested(&self) -> (u32, u32, PixelFormat) {
        self.requested
    }
    pub fn controls(&self) -> &ControlReport {
        &self.controls
    }
    /// The configured per-frame deadline (`[camera] frame_timeout_ms`), for callers to pass
    /// to `grab`/`grab_fresh`.
    pub fn frame_timeout(&self) -> Duration {
        self.timeout
    }

    /// Set one control if the device has it; read it back.
    fn set(&self, report: &mut ControlReport, name: &str, id: u32, value: i64) {
        let current = match self.dev.control(id) {
            Ok(c) => c,
            Err(_) => {
                report.missing.push(name.to_string());
                return;
            }
        };
        let v = match current.value {
            Value::Boolean(_) => Value::Boolean(value != 0),
            _ => Value::Integer(value),
        };
        if let Err(e) = self.dev.set_control(Control { id, value: v }) {
            report.failed.push((name.to_string(), e.to_string()));
            return;
        }
        let back = match self.dev.control(id).map(|c| c.value) {
            Ok(Value::Integer(v)) => v,
            Ok(Value::Boolean(b)) => i64::from(b),
            _ => value,
        };
        report.applied.push((name.to_string(), value, back));
    }

    fn apply_controls(&self, o: &V4l2Options) -> ControlReport {
        let mut r = ControlReport::default();
        if let Some(us) = o.exposure_us {
            // Manual mode first: most cameras refuse an exposure time while in auto.
            self.set(
                &mut r,
                "auto_exposure",
                cid::EXPOSURE_AUTO,
                cid::EXPOSURE_MANUAL,
            );
            self.set(
                &mut r,
                "exposure_time_absolute",
                cid::EXPOSURE_ABSOLUTE,
                i64::from((us / 100).max(1)),
            );
        }
        if let Some(g) = o.gain {
            self.set(&mut r, "gain_automatic", cid::AUTOGAIN, 0);
            self.set(&mut r, "gain", cid::GAIN, g);
        }
        if let Some(k) = o.white_balance_k {
            self.set(
                &mut r,
                "white_balance_automatic",
                cid::AUTO_WHITE_BALANCE,
                0,
            );
            self.set(
                &mut r,
                "white_balance_temperature",
                cid::WHITE_BALANCE_TEMPERATURE,
                i64::from(k),
            );
        }
        if let Some(s) = o.sharpness {
            self.set(&mut r, "sharpness", cid::SHARPNESS, s);
        }
        // An absent *auto* control is no problem when the manual one exists.
        let have = |n: &str| r.applied.iter().any(|(a, _, _)| a == n);
        let pairs = [
            ("auto_exposure", "exposure_time_absolute"),
            ("gain_automatic", "gain"),
            ("white_balance_automatic", "white_balance_temperature"),
        ];
        r.missing
            .retain(|m| !pairs.iter().any(|(auto, manual)| m == auto && have(manual)));
        r
    }

    /// Stop streaming and free the buffers (the next grab starts again).
    pub fn stop(&mut self) {
        self.stream = None;
    }

    /// Start streaming if not already.
    pub fn start(&mut self) -> Result<(), HwError> {
        if self.stream.is_none() {
            let s = Stream::with_buffers(&self.dev, BufType::VideoCapture, self.buffers)
                .map_err(|e| hw_err(&self.label, format!("VIDIOC_REQBUFS/mmap: {e}")))?;
            self.stream = Some(s);
        }
        Ok(())
    }

    /// Dequeue the next good buffer before `deadline`; returns it decoded only if `keep`
    /// accepts its timestamp (else `Ok(None)`: dropped).
    fn next_frame(
        &mut self,
        deadline: Instant,
        timeout: Duration,
        keep: impl Fn(SystemTime) -> bool,
    ) -> Result<Option<Frame>, HwError> {
        self.start()?;
        let label = self.label.clone();
        let (format, width, height, stride) = (self.format, self.width, self.height, self.stride);
        let stream = self.stream.as_mut().expect("started");
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(self.timeout_err(timeout));
        }
        // poll(2) takes whole milliseconds; never 0 (that would not wait at all).
        stream.set_timeout(left.max(Duration::from_millis(1)));
        let (buf, meta) = match stream.next() {
            Ok(x) => x,
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {
                // v4l's Stream re-queues its last buffer before each dequeue; after a timeout
                // that buffer is still queued and the next call fails with EINVAL (seen on
                // vivid). Restart the stream on the next grab instead.
                self.stream = None;
                return Err(self.timeout_err(timeout));
            }
            Err(e) if e.raw_os_error() == Some(libc::ENODEV) => {
                self.stream = None;
                return Err(HwError::PortGone {
                    device: label,
                    message: e.to_string(),
                });
            }
            Err(e) => {
                let msg = format!("VIDIOC_DQBUF: {e}");
                self.stream = None;
                return Err(hw_err(&label, msg));
            }
        };
        if meta.flags.contains(BufFlags::ERROR) {
            self.dropped_errored += 1;
            return Ok(None);
        }
        let ts: Duration = meta.timestamp.into();
        let timestamp = if ts.is_zero() {
            SystemTime::now()
        } else {
            monotonic_to_system(ts)
        };
        if !keep(timestamp) {
            self.dropped_stale += 1;
            return Ok(None);
        }
        let used = (meta.bytesused as usize).min(buf.len());
        let image = pixfmt::to_rgb(format, &buf[..used], width, height, stride)
            .map_err(|e| hw_err(&label, format!("frame {}: {e}", meta.sequence)))?;
        Ok(Some(Frame {
            image,
            sequence: u64::from(meta.sequence),
            timestamp,
        }))
    }

    /// The error names the caller's timeout (not the configured default).
    fn timeout_err(&self, timeout: Duration) -> HwError {
        HwError::Timeout {
            device: self.label.clone(),
            timeout_ms: timeout.as_millis() as u64,
            waiting_for: "a frame".into(),
        }
    }
}

impl Camera for V4l2Camera {
    fn name(&self) -> &str {
        &self.label
    }

    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    fn grab(&mut self, timeout: Duration) -> Result<Frame, HwError> {
        let timeout = timeout.min(MAX_WAIT);
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(f) = self.next_frame(deadline, timeout, |_| true)? {
                return Ok(f);
            }
        }
    }

    fn grab_fresh(&mut self, not_before: SystemTime, timeout: Duration) -> Result<Frame, HwError> {
        let timeout = timeout.min(MAX_WAIT);
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(f) = self.next_frame(deadline, timeout, |t| t >= not_before)? {
                return Ok(f);
            }
        }
    }
}
