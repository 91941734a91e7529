//! Frames decoded only down to the rows the pipeline reads (`rigctl process`'s fast path)
//! give exactly the whole frames' result, and a frame that would need more rows is refused
//! without changing the pipeline.

use crate::support::*;
use rigd::pipeline::{Combine, Estimator, Pipeline, ProcessOptions, ProcessResult};
use rigd::sim::render::SceneRenderer;
use rigd::sim::View;

fn scan(n: usize) -> (Vec<image::RgbImage>, Vec<f64>) {
    let scene = SceneRenderer::new(small_board(), small_camera());
    (0..n)
        .map(|i| {
            let pos = 50.0 * i as f64;
            let view = View::at([123.0 + pos, 456.0]);
            (frame(&scene, view, 70 + i as u64), pos)
        })
        .unzip()
}

fn opts(combine: Combine) -> ProcessOptions {
    ProcessOptions {
        k: 4,
        combine,
        estimator: Estimator::Fit,
        ..ProcessOptions::default()
    }
}

fn whole(frames: &[image::RgbImage], pos: &[f64], o: &ProcessOptions) -> ProcessResult {
    let mut p = Pipeline::new(o.clone().validate().unwrap(), None);
    for (f, &x) in frames.iter().zip(pos) {
        p.push(f, x).unwrap();
    }
    p.finish().unwrap().result
}

#[test]
fn rows_below_the_needed_ones_are_never_read() {
    let (frames, pos) = scan(5);
    let height = frames[0].height();
    for combine in [Combine::Interp, Combine::Mean] {
        let o = opts(combine);
        let want = whole(&frames, &pos, &o);
        let mut p = Pipeline::new(o.clone().validate().unwrap(), None);
        assert_eq!(p.rows_needed(0), None, "frame 0 is searched whole");
        p.push(&frames[0], pos[0]).unwrap();
        for (f, &x) in frames.iter().zip(&pos).skip(1) {
            let rows = p.rows_needed(2).expect("targets placed");
            assert!(rows < height, "the small board leaves rows below: {rows}");
            // Garbage below the decoded rows, as a reused buffer holds.
            let mut g = f.clone();
            for y in rows..height {
                for x in 0..g.width() {
                    g.put_pixel(x, y, image::Rgb([255, 0, 255]));
                }
            }
            let rep = p.push_rows(&g, rows, x).unwrap();
            assert!(rep.is_some(), "{combine:?}: {rows} rows are enough");
        }
        assert_eq!(p.finish().unwrap().result, want, "{combine:?}");
    }
}

#[test]
fn too_few_rows_leave_the_pipeline_unchanged() {
    let (frames, pos) = scan(3);
    let o = opts(Combine::Interp);
    let want = whole(&frames, &pos, &o);
    let mut p = Pipeline::new(o.validate().unwrap(), None);
    // Frame 0 is never taken partial.
    assert!(p.push_rows(&frames[0], 10, pos[0]).unwrap().is_none());
    assert_eq!(p.frames(), 0);
    p.push(&frames[0], pos[0]).unwrap();
    for (f, &x) in frames.iter().zip(&pos).skip(1) {
        assert!(
            p.push_rows(f, 10, x).unwrap().is_none(),
            "10 rows miss the targets"
        );
        assert!(p.push_rows(f, f.height(), x).unwrap().is_some());
    }
    assert_eq!(p.frames(), 3);
    assert_eq!(p.finish().unwrap().result, want);
}

#[test]
fn whole_frame_runs_need_every_row_and_images_can_be_left_out() {
    let (frames, pos) = scan(2);
    let mut o = opts(Combine::Interp);
    o.whole_frame = true;
    let mut p = Pipeline::new(o.clone().validate().unwrap(), None);
    p.push(&frames[0], pos[0]).unwrap();
    assert_eq!(p.rows_needed(0), None);
    assert!(p.push_rows(&frames[1], 150, pos[1]).unwrap().is_none());
    p.push(&frames[1], pos[1]).unwrap();
    let with = p.finish().unwrap();
    assert_eq!(with.images.len(), 3, "two targets and the whole frame");

    let mut p = Pipeline::new(o.validate().unwrap(), None);
    p.keep_images(false);
    for (f, &x) in frames.iter().zip(&pos) {
        p.push(f, x).unwrap();
    }
    let without = p.finish().unwrap();
    assert!(without.images.is_empty());
    assert_eq!(without.result, with.result);
}

/// `push_frames` over PNG files on disk, longer than its decoders' window: on 1, 2 and 3
/// decoders every frame is pushed, in order, to the in-memory result (the decoded rows are
/// all the pipeline reads); a damaged frame past the window is named, and the frames
/// before it were pushed.
#[test]
fn frames_from_disk_on_any_decoder_count_give_the_in_memory_result() {
    use rigd::folder::FrameFile;
    use rigd::offline::push::{push_frames, FrameIn, PushError};
    let (frames, pos) = scan(11);
    let dir = tempfile::tempdir().unwrap();
    let files: Vec<FrameIn> = frames
        .iter()
        .zip(&pos)
        .enumerate()
        .map(|(i, (f, &x))| {
            let path = dir.path().join(format!("{i:04}.png"));
            f.save(&path).unwrap();
            FrameIn {
                file: FrameFile::Path(path),
                position_um: x,
                piezo_um: None,
            }
        })
        .collect();
    let o = opts(Combine::Interp);
    let want = whole(&frames, &pos, &o);
    for decoders in [1, 2, 3] {
        let mut p = Pipeline::new(o.clone().validate().unwrap(), None);
        p.keep_images(false);
        push_frames(&mut p, &files, decoders).unwrap();
        assert_eq!(p.frames(), 11);
        let got = p.finish().unwrap().result;
        assert_eq!(
            serde_json::to_value(&got.objects).unwrap(),
            serde_json::to_value(&want.objects).unwrap(),
            "{decoders} decoders"
        );
    }
    // Frame 9 cut short: named, after frames 0..9 went in.
    let bad = files[9].file.path().to_path_buf();
    let bytes = std::fs::read(&bad).unwrap();
    std::fs::write(&bad, &bytes[..bytes.len() / 2]).unwrap();
    for decoders in [1, 2] {
        let mut p = Pipeline::new(o.clone().validate().unwrap(), None);
        let err = push_frames(&mut p, &files, decoders).unwrap_err();
        assert!(matches!(err, PushError::Read(_)), "{err}");
        assert!(err.to_string().contains("0009.png"), "{err}");
        assert_eq!(p.frames(), 9, "{decoders} decoders");
    }
}

/// A frame measured ahead by the pipeline's `Measurer` (as a decoder does, on its own
/// thread) gives the very result of the pipeline measuring it; estimates handed in for
/// another frame or position are not used; a frame whose prediction comes from a frame
/// not pushed yet is left to the pipeline.
#[test]
fn frames_measured_ahead_are_the_pipelines_own_measurement() {
    use rigd::pipeline::measure::PREDICT_LAG;
    use std::sync::{Arc, OnceLock};
    let n = PREDICT_LAG + 4;
    let (frames, pos) = scan(n);
    let o = opts(Combine::Interp);
    let want = whole(&frames, &pos, &o);
    let mut p = Pipeline::new(o.clone().validate().unwrap(), None);
    let cell = Arc::new(OnceLock::new());
    p.share_measurer(cell.clone());
    let h = frames[0].height();
    p.push(&frames[0], pos[0]).unwrap();
    let m = cell.get().expect("shared once frame 0 is in").clone();
    // Frame PREDICT_LAG + 1 is predicted from frame 1, not pushed yet.
    let far = PREDICT_LAG + 1;
    assert!(m.measure(&frames[far], h, far, [pos[far], 0.0]).is_none());
    // Every frame measured ahead; frame 2 handed frame 3's estimates (ignored).
    let ahead: Vec<_> = (1..n)
        .map(|i| m.measure(&frames[i], h, i, [pos[i], 0.0]))
        .take_while(Option::is_some)
        .flatten()
        .collect();
    assert_eq!(ahead.len(), PREDICT_LAG, "frames 1..=PREDICT_LAG");
    for i in 1..n {
        let pre = match i {
            2 => Some(ahead[2].clone()),
            i if i <= PREDICT_LAG => Some(ahead[i - 1].clone()),
            i => m.measure(&frames[i], h, i, [pos[i], 0.0]),
        };
        assert!(
            pre.is_some(),
            "frame {i}: the frame it is predicted from is in"
        );
        p.push_measured(&frames[i], h, (pos[i], None), pre).unwrap();
    }
    assert_eq!(p.finish().unwrap().result, want);
}
