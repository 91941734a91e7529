//! The two speed yardsticks for the 20-frame k = 10 job, as whole processes measured
//! side by side in one run on this machine (docs/performance.md):
//!
//! - **floor**: this binary run again with `RIGD_DECODE_ONLY=DIR`: it reads and decodes every
//!   frame whole on as many threads as `rigctl process` decodes on (each taking every W-th
//!   frame into a reused buffer, as `rigctl process`'s decoders do) and does nothing else.
//!   No processing of the frames can take less.
//! - **rigd**: `rigctl process DIR --k 10 --json` (the default `fit` estimator), output
//!   discarded.
//! - **OpenCV**: `python3 benches/opencv_baseline.py DIR --k 10`, when `cv2` imports
//!   (`pip install opencv-python-headless numpy`).
//!
//! `cargo bench --bench decode_floor`; `RIGD_FOLDER=DIR` measures another folder (default:
//! the paper job written to a temporary folder), `RIGD_RUNS=N` the runs of each (default 15,
//! taken in turn so that a slow spell of the machine hits all three alike). Prints the
//! median and the fastest wall time of each and the ratios of the medians.

#[path = "support/paper_job.rs"]
mod paper_job;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Instant;

fn main() {
    if let Some(dir) = std::env::var_os("RIGD_DECODE_ONLY") {
        decode_only(Path::new(&dir));
        return;
    }
    // `cargo bench` passes `--bench`; this bench has no options of its own.
    let tmp = tempfile::tempdir().unwrap();
    let dir = match std::env::var_os("RIGD_FOLDER") {
        Some(d) => d.into(),
        None => {
            paper_job::write_folder(tmp.path());
            tmp.path().to_path_buf()
        }
    };
    let runs: usize = std::env::var("RIGD_RUNS").map_or(15, |v| v.parse().expect("RIGD_RUNS"));
    let me = std::env::current_exe().unwrap();
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/opencv_baseline.py");
    let mut floor = Command::new(&me);
    floor.env("RIGD_DECODE_ONLY", &dir);
    let mut rigd = Command::new(env!("CARGO_BIN_EXE_rigctl"));
    rigd.arg("process").arg(&dir).args(["--k", "10", "--json"]);
    let mut opencv = Command::new("python3");
    opencv.arg(script).arg(&dir).args(["--k", "10"]);
    let mut cmds = vec![("floor (decode only)", floor), ("rigctl process", rigd)];
    if has_cv2() {
        cmds.push(("OpenCV + numpy", opencv));
    } else {
        println!("(no cv2: the OpenCV baseline is skipped)");
    }
    let mut times = vec![Vec::new(); cmds.len()];
    for _ in 0..runs {
        for ((_, cmd), t) in cmds.iter_mut().zip(&mut times) {
            t.push(wall_s(cmd));
        }
    }
    report(
        &cmds.iter().map(|c| c.0).collect::<Vec<_>>(),
        &mut times,
        &dir,
    );
}

/// Decode every frame of `dir` whole, on `rigctl process`'s decoder count.
fn decode_only(dir: &Path) {
    let folder = rigd::folder::open(dir, None).unwrap();
    let workers = rigd::offline::push::decoders_for_one_run();
    std::thread::scope(|s| {
        for w in 0..workers {
            let frames = &folder.frames;
            s.spawn(move || {
                let mut reader = rigd::folder::FrameReader::default();
                let mut buf = None;
                for f in frames.iter().skip(w).step_by(workers) {
                    buf = Some(reader.read(f, buf.take()).unwrap());
                }
                std::hint::black_box(buf);
            });
        }
    });
}

fn has_cv2() -> bool {
    Command::new("python3")
        .args(["-c", "import cv2, numpy"])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// One whole process's wall time, s; its output (and the baseline's stage times on
/// stderr) discarded, a failure fatal.
fn wall_s(cmd: &mut Command) -> f64 {
    let t = Instant::now();
    let st = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .unwrap();
    let s = t.elapsed().as_secs_f64();
    assert!(st.success(), "{cmd:?} failed: {st}");
    s
}

fn report(names: &[&str], times: &mut [Vec<f64>], dir: &Path) {
    println!("{} runs each, {}", times[0].len(), dir.display());
    let mut medians = Vec::new();
    for (name, t) in names.iter().zip(times.iter_mut()) {
        t.sort_by(f64::total_cmp);
        let median = t[t.len() / 2];
        medians.push(median);
        println!(
            "{name:>20}: median {:6.1} ms, fastest {:6.1} ms",
            median * 1e3,
            t[0] * 1e3
        );
    }
    println!(
        "rigctl process / floor: {:.2}x (goal: within 1.5x)",
        medians[1] / medians[0]
    );
    if let Some(cv) = medians.get(2) {
        println!(
            "OpenCV / rigctl process: {:.1}x (goal: at least 10x)",
            cv / medians[1]
        );
    }
}
