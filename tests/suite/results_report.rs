//! Results a lab can use: the flat `results.csv` beside every `result.json`
//! (a daemon's session on the sim rig, `rigctl process --out`), and `rigctl report`'s
//! labelled figures and report of a study session.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{assert_finished, run_job, Daemon};
use rigd::acquisition::study::JobResult;
use rigd::acquisition::{JobRegistration, JobSpec, PaperCase};
use rigd::pipeline::{ObjectResult, ProcessResult};
use rigd::plot::Series;
use rigd::rig::{simulated, SimSettings};
use std::collections::HashMap;
use std::path::Path;
use std::process::{Command, Output};

/// results.csv parsed on its own (not through rigd's reader): one map per row, by column.
fn csv_rows(path: &Path) -> Vec<HashMap<String, String>> {
    let mut rd = csv::Reader::from_path(path).unwrap();
    let heads: Vec<String> = rd.headers().unwrap().iter().map(String::from).collect();
    assert_eq!(
        heads.join(","),
        "run,case,repeat,target,dx_um,dy_um,u_dx_um,u_dy_um,nominal_dx_um,nominal_dy_um,\
         bias_dx_um,bias_dy_um,frames,k,estimator,combine,registration"
    );
    rd.records()
        .map(|r| {
            heads
                .iter()
                .cloned()
                .zip(r.unwrap().iter().map(String::from))
                .collect()
        })
        .collect()
}

/// A number cell: the very f64 written, or None when empty.
fn num(row: &HashMap<String, String>, col: &str) -> Option<f64> {
    let v = &row[col];
    (!v.is_empty()).then(|| v.parse().unwrap_or_else(|e| panic!("{col} = {v}: {e}")))
}

/// `row` holds exactly `o`'s figures as `result.json` has them.
fn assert_row_is(row: &HashMap<String, String>, o: &ObjectResult, r: &ProcessResult) {
    assert_eq!(num(row, "dx_um"), Some(o.offset_um[0]), "{row:?}");
    assert_eq!(num(row, "dy_um"), Some(o.offset_um[1]), "{row:?}");
    assert_eq!(
        num(row, "u_dx_um"),
        o.u_um.or(o.sigma_um).map(|s| s[0]),
        "{row:?}"
    );
    assert_eq!(
        num(row, "u_dy_um"),
        o.u_um.or(o.sigma_um).map(|s| s[1]),
        "{row:?}"
    );
    let nominal = o.nominal_um.expect("the board names every target");
    assert_eq!(num(row, "nominal_dx_um"), Some(nominal[0]));
    assert_eq!(num(row, "nominal_dy_um"), Some(nominal[1]));
    assert_eq!(num(row, "bias_dx_um"), Some(o.offset_um[0] - nominal[0]));
    assert_eq!(num(row, "bias_dy_um"), Some(o.offset_um[1] - nominal[1]));
    assert_eq!(row["frames"], o.frames.to_string());
    assert_eq!(row["k"], r.options.k.to_string());
    let names = serde_json::to_value(&r.options).unwrap();
    assert_eq!(row["estimator"], names["estimator"].as_str().unwrap());
    assert_eq!(row["combine"], names["combine"].as_str().unwrap());
}

/// A small fast sim rig looking at the small two-target board (H: 2000 µm on x, V: 3000 µm
/// on y), its XL-80 logging.
fn sim_settings(dir: &Path) -> SimSettings {
    crate::support::daemon::small_board_sim(dir)
}

fn rigctl(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(args)
        .output()
        .expect("rigctl runs")
}

/// The paper's three cases, 3 repeats, registered by the interferometer, on the sim rig:
/// results.csv, then `rigctl report` on the session.
#[test]
fn a_study_session_has_its_results_table_and_rigctl_report_draws_its_figures() {
    let dir = tempfile::tempdir().unwrap();
    let settings = sim_settings(dir.path());
    let d = Daemon::start(simulated(&settings).unwrap());
    let mut c = d.subscribed();
    let job = JobSpec {
        study: Some(PaperCase::ALL.to_vec()),
        repeats: 3,
        repeat_shift_um: 258.0,
        settle_ms: 30,
        registration: Some(JobRegistration::Interferometer),
        ..JobSpec::default()
    };
    let (_, ev) = run_job(&mut c, job);
    assert_finished(&ev);
    let s = d.session(&ev);
    let result: JobResult =
        serde_json::from_slice(&std::fs::read(s.dir.join("result.json")).unwrap()).unwrap();
    let rows = csv_rows(&s.dir.join("results.csv"));
    // Every run measured both targets: 9 runs x 2 targets, in run order.
    assert_eq!(result.runs.len(), 9);
    assert_eq!(rows.len(), 18, "{rows:?}");
    for (run, pair) in result.runs.iter().zip(rows.chunks(2)) {
        let r = run.result.as_ref().expect("every run processed");
        for (row, o) in pair.iter().zip(&r.objects) {
            assert_eq!(row["run"], run.run.to_string());
            assert_eq!(row["case"], run.case);
            assert_eq!(row["repeat"], run.repeat.to_string());
            assert_eq!(Some(row["target"].as_str()), o.name.as_deref());
            assert_row_is(row, o, r);
            // The job's registration, not the pipeline's "positions".
            assert_eq!(row["registration"], "interferometer");
        }
    }
    check_residuals(&result, &s);
    check_report(&s.dir, dir.path());
}

/// The residual chart's numbers: each step's displacement within the sim's errors of the
/// commanded one (a sign or unit slip would put them hundreds of µm off).
fn check_residuals(result: &JobResult, s: &rigd::session::Session) {
    let chart = rigd::figures::residuals(&result.runs, &s.steps);
    let series: HashMap<&str, &Series> =
        chart.series.iter().map(|x| (x.label.as_str(), x)).collect();
    let image = series["image − commanded"];
    let laser = series["interferometer − commanded"];
    assert_eq!(image.points.len(), s.steps.len());
    assert_eq!(laser.points.len(), s.steps.len());
    // The axis settles within its 2 µm RMS positioning error; a frame's image displacement
    // is measured to a few µm on these small frames.
    let worst = |p: &[(f64, f64)]| p.iter().map(|q| q.1.abs()).fold(0.0, f64::max);
    assert!(worst(&laser.points) < 12.0, "{:?}", laser.points);
    assert!(worst(&image.points) < 40.0, "{:?}", image.points);
    // The first frame of each run is where its displacements start: exactly 0.
    assert_eq!(image.points[0], (0.0, 0.0));
}

/// `rigctl report SESSION --out DIR`: report.txt, and each figure as PNG (its size, not
/// blank) and SVG (its axis labels and legend).
fn check_report(session: &Path, tmp: &Path) {
    let out = tmp.join("report");
    let o = rigctl(&[
        "report".as_ref(),
        session.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(out.join("report.txt")).unwrap();
    assert!(text.contains("Table 3") && text.contains("case3"), "{text}");
    let figures: [(&str, (u32, u32), &[&str]); 5] = [
        (
            "figure4-case1",
            (800, 500),
            &[
                "repeat (experiment number)",
                "measured offset − nominal (µm)",
                "H (nominal 2000 µm)",
                "V (nominal 3000 µm)",
                "case1",
            ],
        ),
        (
            "figure4-case2",
            (800, 500),
            &["H (nominal 2000 µm)", "10 frame(s) 100 µm apart, k = 5"],
        ),
        (
            "figure4-case3",
            (800, 500),
            &["H (nominal 2000 µm)", "20 frame(s) 50 µm apart, k = 10"],
        ),
        (
            "figure5",
            (800, 500),
            &[
                "averaging case (frames, k)",
                "standard deviation over repeats (µm)",
                "RMS over targets",
                "target H",
                "case3 (20, k = 10)",
            ],
        ),
        (
            "residuals",
            (900, 500),
            &[
                "frame (index in the session)",
                "displacement − commanded (µm)",
                "image − commanded",
                "interferometer − commanded",
                "axis (reported) − commanded",
            ],
        ),
    ];
    for (stem, size, texts) in figures {
        let rgb = image::open(out.join(format!("{stem}.png")))
            .unwrap_or_else(|e| panic!("{stem}.png: {e}"))
            .to_rgb8();
        assert_eq!(rgb.dimensions(), size, "{stem}");
        let grey = image::DynamicImage::ImageRgb8(rgb.clone()).to_luma8();
        let n = grey.len() as f64;
        let mean = grey.iter().map(|&v| v as f64).sum::<f64>() / n;
        let var = grey.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n;
        // A blank page has none; the axes, grid, text and data of these charts give 900+.
        assert!(var > 300.0, "{stem}.png: pixel variance {var:.0}");
        // The data are drawn: the first series' colour (blue) on many pixels.
        let blue = rgb.pixels().filter(|p| p.0 == [31, 119, 180]).count();
        assert!(blue > 100, "{stem}.png: {blue} pixels of the first series");
        let svg = std::fs::read_to_string(out.join(format!("{stem}.svg"))).unwrap();
        for t in texts {
            assert!(svg.contains(t), "{stem}.svg lacks {t:?}");
        }
    }
}

#[test]
fn rigctl_process_out_writes_results_csv_with_result_jsons_figures() {
    let d = tempfile::tempdir().unwrap();
    let board = d.path().join("small.toml");
    std::fs::write(&board, crate::support::SMALL_BOARD).unwrap();
    let folder = d.path().join("folder");
    crate::support::write_folder(
        &folder,
        &crate::support::small_board(),
        &crate::support::small_camera(),
        [310.0, 150.0],
        154.8,
        5,
        7,
    );
    let out = d.path().join("out");
    let o = rigctl(&[
        "process".as_ref(),
        folder.as_os_str(),
        "--k".as_ref(),
        "5".as_ref(),
        "--board".as_ref(),
        board.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: ProcessResult =
        serde_json::from_slice(&std::fs::read(out.join("result.json")).unwrap()).unwrap();
    let rows = csv_rows(&out.join("results.csv"));
    assert_eq!(rows.len(), r.objects.len());
    assert_eq!(rows.len(), 2);
    for (row, o) in rows.iter().zip(&r.objects) {
        assert_eq!(
            (
                row["run"].as_str(),
                row["case"].as_str(),
                row["repeat"].as_str()
            ),
            ("0", "", "0")
        );
        assert_eq!(Some(row["target"].as_str()), o.name.as_deref());
        assert_row_is(row, o, &r);
        assert_eq!(
            (row["combine"].as_str(), row["registration"].as_str()),
            ("interp", "image")
        );
    }
}

#[test]
fn rigctl_report_on_a_folder_without_result_json_names_the_file() {
    let d = tempfile::tempdir().unwrap();
    std::fs::write(d.path().join("steps.csv"), "index,position_um\n").unwrap();
    let o = rigctl(&["report".as_ref(), d.path().as_os_str()]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    let want = d.path().join("result.json");
    assert!(err.contains(&*want.to_string_lossy()), "{err}");
    // Nothing was written.
    assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
}
