//! The frame-clock camera against a moving axis: motion blur mid-move, a sharp frame after
//! settling, stale queued frames showing the old position, V4L2-like dropping.

mod common;
use common::*;
use rigd_sim::camera::CameraModel;
use rigd_sim::motion::{Axis, AxisParams, TruePosition};
use rigd_sim::{Board, FrameClockCamera, FrameRenderer};
use std::sync::Arc;
use std::time::{Duration, Instant};

const TIMEOUT: Duration = Duration::from_secs(5);

fn fast_axis() -> Arc<Axis> {
    Arc::new(Axis::new(AxisParams {
        max_speed_um_s: 300_000.0,
        accel_um_s2: 30_000_000.0,
        position_error_rms_um: 0.0,
        ..Default::default()
    }))
}

fn camera(cam: CameraModel, axis: &Arc<Axis>) -> (FrameClockCamera, Board, [f64; 2]) {
    let board = Board::paper();
    let origin = origin_centring(&board, &cam, "A");
    let r = FrameRenderer::new(board.clone(), cam, 11)
        .unwrap()
        .with_origin(origin);
    let src: Arc<dyn TruePosition> = axis.clone();
    (FrameClockCamera::start(r, src), board, origin)
}

fn clock_cam() -> CameraModel {
    CameraModel {
        exposure_ms: 20.0,
        frame_period_ms: 25.0,
        buffer_frames: 8,
        ..quiet(small_cam())
    }
}

#[test]
fn a_frame_exposed_mid_move_is_smeared_and_one_after_settling_is_sharp() {
    let axis = fast_axis();
    let (cam, board, origin) = camera(clock_cam(), &axis);
    let ink = board.ink_rgb[1] * 235.0;
    let sharp_before = cam.fresh_frame(Instant::now(), TIMEOUT).unwrap();

    // 30 mm at up to 300 mm/s: ~0.11 s, ~6 mm (7.8 px) of travel per 20 ms exposure.
    let start = Instant::now();
    let duration = axis.command_move(30_000.0).unwrap();
    let moving = cam.fresh_frame(start + duration / 3, TIMEOUT).unwrap();
    let settled = cam
        .fresh_frame(start + duration + Duration::from_millis(1), TIMEOUT)
        .unwrap();
    assert!(moving.exposed_at + Duration::from_millis(20) < start + duration);

    // Along the row through the target centre, motion along x smears the 5 px ring and the
    // 15 px disk by the travel during the exposure (~7.8 px): few pixels stay full ink.
    let row = |f: &rigd_sim::SimFrame| {
        let y = predicted_px(&board, cam.renderer().camera(), origin, f.mean_los_um, "A")[1];
        row_ink_pixels(&f.image, y.round() as u32, ink)
    };
    let (e_before, e_moving, e_settled) = (row(&sharp_before), row(&moving), row(&settled));
    assert!(
        moving.mean_los_um[0] > 3_000.0 && moving.mean_los_um[0] < 27_000.0,
        "mid-move frame exposed at {:?} µm",
        moving.mean_los_um
    );
    assert!(
        (e_moving as f64) < 0.6 * e_before as f64,
        "full-ink pixels on the centre row: moving {e_moving}, still {e_before}"
    );
    assert!(
        e_settled.abs_diff(e_before) <= 2,
        "full-ink pixels: settled {e_settled}, before {e_before}"
    );
    // Sharper still: the moving frame is not the still render at its mean position.
    let still_mid = cam
        .renderer()
        .render_at(moving.sequence, moving.mean_los_um);
    let diff: u64 = still_mid
        .as_raw()
        .iter()
        .zip(moving.image.as_raw())
        .map(|(a, b)| a.abs_diff(*b) as u64)
        .sum();
    assert!(
        diff > 20_000,
        "blurred vs still frame differ by {diff} DN in total"
    );
    // The settled frame is exactly the still render at the final position.
    let still = cam.renderer().render_at(settled.sequence, [30_000.0, 0.0]);
    assert_eq!(settled.image, still);
    assert_eq!(settled.mean_los_um, [30_000.0, 0.0]);
}

#[test]
fn a_driver_that_takes_the_queued_frame_after_a_move_sees_the_old_position() {
    let axis = fast_axis();
    let (cam, board, origin) = camera(clock_cam(), &axis);
    let c = clock_cam();
    let paper = board.paper_rgb[1] * c.white_dn;
    // Let the ring fill with frames at position 0, then move 5 mm and wait for the settle.
    std::thread::sleep(Duration::from_millis(5 * 25));
    let d = axis.command_move(5_000.0).unwrap();
    std::thread::sleep(d + Duration::from_millis(5));
    let settled_at = Instant::now();

    let stale = cam.next_frame(TIMEOUT).unwrap();
    let fresh = cam.fresh_frame(settled_at, TIMEOUT).unwrap();
    assert!(fresh.sequence > stale.sequence);
    assert!(stale.exposed_at < settled_at && fresh.exposed_at >= settled_at);

    // The stale frame shows where the axis was when it was exposed, not where it is now.
    let cs = ink_centroid(&stale.image, paper);
    let cf = ink_centroid(&fresh.image, paper);
    let shift = cf[0] - cs[0];
    let want = -(fresh.mean_los_um[0] - stale.mean_los_um[0]) / c.scale_um_per_px;
    assert!(
        stale.mean_los_um[0] < 2_500.0,
        "the oldest queued frame was exposed at {} µm",
        stale.mean_los_um[0]
    );
    assert!(shift < -3.0, "stale vs fresh frame moved {shift} px");
    assert!(
        (shift - want).abs() < 0.3,
        "moved {shift} px, true motion says {want}"
    );
    // And the fresh frame is where the settled axis puts the target.
    let p = predicted_px(&board, &c, origin, [5_000.0, 0.0], "A");
    let p0 = predicted_px(&board, &c, origin, [0.0, 0.0], "A");
    assert!(((p[0] - p0[0]) - shift).abs() < 0.5);
}

#[test]
fn frames_are_numbered_timestamped_and_old_ones_dropped() {
    let axis = fast_axis();
    let cam_model = CameraModel {
        buffer_frames: 3,
        frame_period_ms: 10.0,
        exposure_ms: 5.0,
        ..quiet(CameraModel {
            width: 64,
            height: 48,
            ..small_cam()
        })
    };
    let (cam, _, _) = camera(cam_model, &axis);
    std::thread::sleep(Duration::from_millis(200));
    // ~20 frames exposed, 3 kept: the ring holds the newest and counts the rest as dropped.
    assert_eq!(cam.queued(), 3);
    assert!(cam.dropped() >= 10, "dropped {}", cam.dropped());
    let a = cam.next_frame(TIMEOUT).unwrap();
    let b = cam.next_frame(TIMEOUT).unwrap();
    assert_eq!(b.sequence, a.sequence + 1);
    let dt = b.timestamp.duration_since(a.timestamp).unwrap();
    assert_eq!(dt, Duration::from_millis(10));
    let (epoch, _) = cam.epoch();
    assert_eq!(a.exposed_at, epoch + Duration::from_millis(10 * a.sequence));
    // After stop, grabbing fails instead of hanging.
    cam.stop();
    assert!(cam.next_frame(Duration::from_millis(50)).is_err());
}

#[test]
fn a_stalled_stream_times_out_every_grab_until_it_is_restarted() {
    let axis = fast_axis();
    let cam_model = CameraModel {
        exposure_ms: 2.0,
        frame_period_ms: 5.0,
        ..quiet(small_cam())
    };
    let (cam, _, _) = camera(cam_model, &axis);
    cam.stall_from_grab(3);
    let first = cam.next_frame(TIMEOUT).unwrap();
    let second = cam.fresh_frame(Instant::now(), TIMEOUT).unwrap();
    assert!(second.sequence > first.sequence);
    assert!(!cam.is_stalled());
    // Grab 3 stalls the stream: no frame, however long the clock runs.
    let short = Duration::from_millis(60);
    let e = cam.next_frame(short).unwrap_err();
    assert_eq!(
        e,
        rigd_sim::camera_clock::ClockError::Timeout { timeout_ms: 60 }
    );
    assert!(cam.is_stalled());
    assert_eq!(cam.queued(), 0, "a stalled stream queues nothing");
    assert!(cam.fresh_frame(Instant::now(), short).is_err());
    assert_eq!(cam.grabs(), 4);
    // A stream restart clears it; frames come again, numbered on from the clock.
    cam.restart_stream();
    let again = cam.next_frame(TIMEOUT).unwrap();
    assert!(again.sequence > second.sequence + 10, "{}", again.sequence);
}
