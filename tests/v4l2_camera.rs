//! The V4L2 camera backend against a real kernel driver (vivid in docs/vivid.md's VM
//! harness, or any camera). Set RIGD_V4L2_DEVICE to the capture node (e.g. /dev/video0);
//! without it every test prints `SKIPPED: <test>: <why>` (shown even when output is
//! captured) and passes; a node named there that does not exist fails the tests.
//!
//! Optional: RIGD_V4L2_FORMAT (YUYV, RGB3 or MJPG; default YUYV), RIGD_V4L2_SIZE (WxH;
//! default 1280x720).
#![cfg(feature = "v4l2")]

#[path = "support/skip.rs"]
mod skip;

use rigd::hw::pixfmt::PixelFormat;
use rigd::hw::v4l2::{describe, list_devices, V4l2Camera, V4l2Options};
use rigd::hw::{Camera, HwError};
use std::sync::Mutex;
use std::time::{Duration, SystemTime};

const SKIP_REASON: &str =
    "RIGD_V4L2_DEVICE is not set (no V4L2 device here; tests/vivid/run.sh runs these in a VM)";

/// One stream at a time: the tests share the device node.
static DEVICE: Mutex<()> = Mutex::new(());

/// The device under test, or None after saying `SKIPPED: <test>: <why>` when
/// RIGD_V4L2_DEVICE is unset. A device named there that does not exist is an error, not a
/// skip: whoever set it meant the tests to run.
fn device(test: &str) -> Option<String> {
    match std::env::var("RIGD_V4L2_DEVICE") {
        Ok(d) if !d.is_empty() => {
            assert!(
                std::path::Path::new(&d).exists(),
                "{test}: RIGD_V4L2_DEVICE={d} does not exist"
            );
            Some(d)
        }
        _ => {
            skip::skipped(test, SKIP_REASON);
            None
        }
    }
}
fn options(dev: &str) -> V4l2Options {
    let format = std::env::var("RIGD_V4L2_FORMAT")
        .ok()
        .map(|f| f.parse::<PixelFormat>().expect("RIGD_V4L2_FORMAT"))
        .unwrap_or(PixelFormat::Yuyv);
    let (w, h) = std::env::var("RIGD_V4L2_SIZE")
        .ok()
        .and_then(|s| {
            let (w, h) = s.split_once('x')?;
            Some((w.parse().ok()?, h.parse().ok()?))
        })
        .unwrap_or((1280, 720));
    let mut o = V4l2Options::new(dev, w, h, format);
    o.frame_timeout = Duration::from_secs(3);
    o
}

fn lock() -> std::sync::MutexGuard<'static, ()> {
    DEVICE.lock().unwrap_or_else(|e| e.into_inner())
}

#[test]
fn lists_and_describes_the_device() {
    let Some(dev) = device("lists_and_describes_the_device") else {
        return;
    };
    let _g = lock();
    let info = describe(std::path::Path::new(&dev)).unwrap();
    println!("{}: {} ({}, {})", dev, info.name, info.driver, info.bus);
    for f in &info.formats {
        println!(
            "  {} {:?} supported={} sizes={:?}",
            f.fourcc, f.description, f.supported, f.sizes
        );
    }
    assert!(!info.formats.is_empty(), "a capture node offers formats");
    assert!(
        info.formats.iter().any(|f| f.supported),
        "at least one of YUYV, MJPG, RGB3"
    );
    assert!(list_devices().iter().any(|d| d.path == info.path));
}

#[test]
fn negotiates_and_captures_a_stream() {
    let Some(dev) = device("negotiates_and_captures_a_stream") else {
        return;
    };
    let _g = lock();
    let opts = options(&dev);
    let mut cam = V4l2Camera::open(&opts).unwrap();
    let (w, h) = cam.size();
    println!(
        "asked {}x{} {}, got {w}x{h} {} stride {}; controls {:?}",
        opts.width,
        opts.height,
        opts.format,
        cam.format(),
        cam.stride(),
        cam.controls()
    );
    assert!(w > 0 && h > 0);
    if let Some(min) = cam.format().min_stride(w) {
        assert!(cam.stride() >= min);
    }
    let before = SystemTime::now();
    let frames: Vec<_> = (0..5)
        .map(|_| cam.grab(Duration::from_secs(3)).unwrap())
        .collect();
    for f in &frames {
        assert_eq!(f.image.dimensions(), (w, h));
        // Real content, not an empty buffer: the pixels are not all one value.
        let first = f.image.as_raw()[0];
        assert!(f.image.as_raw().iter().any(|&b| b != first));
    }
    for p in frames.windows(2) {
        assert!(p[1].sequence > p[0].sequence, "sequence increases");
        assert!(p[1].timestamp > p[0].timestamp, "timestamps increase");
    }
    // Monotonic timestamps put on the system clock land within the capture, give or take.
    let slack = Duration::from_millis(500);
    assert!(frames[0].timestamp + slack >= before);
    assert!(frames[4].timestamp <= SystemTime::now() + slack);
}

#[test]
fn fresh_frame_after_a_settle_drops_queued_buffers() {
    let Some(dev) = device("fresh_frame_after_a_settle_drops_queued_buffers") else {
        return;
    };
    let _g = lock();
    let mut cam = V4l2Camera::open(&options(&dev)).unwrap();
    let first = cam.grab(Duration::from_secs(3)).unwrap();
    // The "move": buffers fill while we wait; then the axis has settled.
    std::thread::sleep(Duration::from_millis(300));
    let settled = SystemTime::now();
    let stale_before = cam.dropped_stale;
    let fresh = cam.grab_fresh(settled, Duration::from_secs(3)).unwrap();
    assert!(fresh.timestamp >= settled, "frame exposed after the settle");
    assert!(
        cam.dropped_stale > stale_before,
        "queued older frames were dropped"
    );
    assert!(fresh.sequence > first.sequence + 1);
}

#[test]
fn timeout_is_reported_and_stop_restart_works() {
    let Some(dev) = device("timeout_is_reported_and_stop_restart_works") else {
        return;
    };
    let _g = lock();
    let mut cam = V4l2Camera::open(&options(&dev)).unwrap();
    assert_eq!(cam.frame_timeout(), Duration::from_secs(3));
    let a = cam.grab(Duration::from_secs(3)).unwrap();
    cam.stop();
    // A freshly started stream has no frame within 1 ms.
    match cam.grab(Duration::from_millis(1)) {
        // The error names the caller's timeout, not the configured one.
        Err(HwError::Timeout { timeout_ms: 1, .. }) => {}
        other => panic!("expected a timeout, got {other:?}"),
    }
    // Not before 10 s from now: nothing within the deadline either.
    let later = SystemTime::now() + Duration::from_secs(10);
    match cam.grab_fresh(later, Duration::from_millis(200)) {
        Err(HwError::Timeout {
            timeout_ms: 200, ..
        }) => {}
        other => panic!("expected a timeout, got {other:?}"),
    }
    cam.stop();
    let b = cam.grab(Duration::from_secs(3)).unwrap();
    assert!(b.timestamp > a.timestamp);
    drop(cam);
    // The device is free again after drop: it reopens and streams.
    let mut again = V4l2Camera::open(&options(&dev)).unwrap();
    again.grab(Duration::from_secs(3)).unwrap();
}

#[test]
fn opens_by_name_and_refuses_unknown_names() {
    let Some(dev) = device("opens_by_name_and_refuses_unknown_names") else {
        return;
    };
    let _g = lock();
    let info = describe(std::path::Path::new(&dev)).unwrap();
    let e = V4l2Camera::open(&V4l2Options::new(
        "no such camera",
        640,
        480,
        PixelFormat::Yuyv,
    ))
    .err()
    .expect("unknown name");
    assert!(
        e.to_string().contains("no capture device of that name"),
        "{e}"
    );
    // The sysfs name usually equals the card name (vivid: "vivid"); only check when it does.
    let sys = std::path::Path::new("/sys/class/video4linux")
        .join(std::path::Path::new(&dev).file_name().unwrap())
        .join("name");
    if std::fs::read_to_string(sys)
        .map(|n| n.trim() == info.name)
        .unwrap_or(false)
    {
        let mut o = options(&dev);
        o.device = info.name.to_uppercase();
        let mut cam = V4l2Camera::open(&o).unwrap();
        cam.grab(Duration::from_secs(3)).unwrap();
    }
}

#[test]
fn manual_controls_are_applied_or_reported() {
    let Some(dev) = device("manual_controls_are_applied_or_reported") else {
        return;
    };
    let _g = lock();
    let mut o = options(&dev);
    o.exposure_us = Some(10_000);
    o.gain = Some(10);
    o.white_balance_k = Some(4600);
    o.sharpness = Some(0);
    let cam = V4l2Camera::open(&o).unwrap();
    let r = cam.controls();
    println!("controls: {r:?}");
    // Every requested manual control is accounted for exactly once.
    for name in [
        "exposure_time_absolute",
        "gain",
        "white_balance_temperature",
        "sharpness",
    ] {
        let n = r.applied.iter().filter(|(a, _, _)| a == name).count()
            + r.missing.iter().filter(|m| *m == name).count()
            + r.failed.iter().filter(|(f, _)| f == name).count();
        assert_eq!(n, 1, "{name} in {r:?}");
    }
}
