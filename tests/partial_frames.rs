//! Frames decoded only down to the rows the pipeline reads (`rigctl process`'s fast path)
//! give exactly the whole frames' result, and a frame that would need more rows is refused
//! without changing the pipeline.

mod support;

use rigd::pipeline::{Combine, Estimator, Pipeline, ProcessOptions, ProcessResult};
use rigd::sim::render::SceneRenderer;
use rigd::sim::View;
use support::*;

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
