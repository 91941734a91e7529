//! The sim-session binary writes a folder `rigctl process` reads: frames, steps.csv, logs.

use std::process::Command;

#[test]
fn sim_session_writes_frames_steps_and_logs() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("session");
    let cfg = dir.path().join("sim.toml");
    // A small camera keeps the test fast; everything else is the default rig.
    std::fs::write(
        &cfg,
        "[camera]\nwidth = 160\nheight = 120\nscale_um_per_px = 6200.0\n",
    )
    .unwrap();
    let run = |extra: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_sim-session"))
            .args([
                "--out",
                out.to_str().unwrap(),
                "--config",
                cfg.to_str().unwrap(),
            ])
            .args([
                "--frames",
                "3",
                "--step-um",
                "100",
                "--start-um",
                "250",
                "--dwell-ms",
                "50",
            ])
            .args(extra)
            .output()
            .unwrap()
    };
    let o = run(&["--seed", "4"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    for i in 0..3 {
        let img = image::open(out.join(format!("frames/{i:04}.png"))).unwrap();
        assert_eq!(img.color(), image::ColorType::Rgb8);
        assert_eq!((img.width(), img.height()), (160, 120));
    }
    assert!(!out.join("frames/0003.png").exists());
    let steps = std::fs::read_to_string(out.join("steps.csv")).unwrap();
    assert_eq!(steps, "index,position_um\n0,250\n1,350\n2,450\n");
    let rtx = std::fs::read(out.join("xl80.rtx")).unwrap();
    assert!(rtx.starts_with(b"HEADER::\r\n") && rtx.ends_with(b"EOF::\r\n"));
    let csv = std::fs::read_to_string(out.join("xl80.csv")).unwrap();
    let last = csv.trim_end().lines().last().unwrap();
    let mm: f64 = last.split(',').nth(2).unwrap().parse().unwrap();
    // The log ends at the last step (axis error ~2 µm, interferometer noise 0.2 µm).
    assert!((mm * 1000.0 - 450.0).abs() < 10.0, "last reading {mm} mm");
    let sim: toml::Value =
        toml::from_str(&std::fs::read_to_string(out.join("sim.toml")).unwrap()).unwrap();
    assert_eq!(sim["seed"].as_integer(), Some(4));

    // A second run into the same folder is refused with a message naming it.
    let o = run(&[]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("already holds a session"), "{err}");

    // A bad camera parameter is named.
    std::fs::write(&cfg, "[camera]\nexposure_ms = 100.0\n").unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_sim-session"))
        .args(["--out", dir.path().join("s2").to_str().unwrap()])
        .args(["--config", cfg.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("exposure_ms"), "{err}");
}
