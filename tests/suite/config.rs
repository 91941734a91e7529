//! The rig config: the documented example loads and holds what it documents, and bad files
//! fail with errors that name the file and the key.

use rigd::config::{CameraDriver, Config, ConfigError, StageDriver};
use rigd::hw::grbl::OnAlarm;
use rigd::hw::pixfmt::PixelFormat;
use rigd::pipeline::Estimator;
use rigd::xl80::Xl80Format;
use std::path::{Path, PathBuf};

fn example() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigd.toml")
}

fn parse(text: &str) -> Result<Config, ConfigError> {
    Config::from_toml_str(text, Path::new("/etc/rigd/test.toml"))
}

fn err(text: &str) -> String {
    parse(text).unwrap_err().to_string()
}

const AXIS: &str = "[axis]\ndriver = \"grbl\"\nport = \"/dev/ttyUSB0\"\nsoft_min_um = 0.0\nsoft_max_um = 1000.0\nmax_step_um = 100.0\n";

#[test]
fn documented_example_loads() {
    let cfg = Config::load(example()).unwrap();
    let axis = cfg.axis("test").unwrap();
    assert_eq!(axis.driver, StageDriver::Grbl);
    assert_eq!(axis.port.as_deref(), Some("/dev/ttyUSB0"));
    assert_eq!(axis.baud, 115_200);
    assert_eq!(axis.soft_max_um, 250_000.0);
    assert_eq!(axis.default_start_um, Some(1000.0));
    assert_eq!(cfg.pipeline.axis_dir, [-1.0, 0.0]);
    assert_eq!(axis.on_alarm, OnAlarm::Fail);
    let piezo = cfg.piezo("test").unwrap();
    assert_eq!(piezo.driver, StageDriver::Gcs);
    assert_eq!(piezo.gcs_axis, "1");
    let cam = cfg.camera("test").unwrap();
    assert_eq!(cam.driver, CameraDriver::V4l2);
    assert_eq!(cam.format, PixelFormat::Yuyv);
    assert_eq!((cam.width, cam.height), (1280, 720));
    assert_eq!(cam.exposure_us, Some(10_000));
    // The camera's sharpening off, as the V4L2 driver is told.
    assert_eq!(cam.sharpness, Some(0));
    assert_eq!(cam.v4l2_options().sharpness, Some(0));
    let x = cfg.xl80("test").unwrap();
    assert_eq!(x.format, Xl80Format::Rtx);
    assert_eq!(cfg.daemon.group.as_deref(), Some("rigd"));
    assert_eq!(cfg.pipeline.k, Some(10));
    assert_eq!(cfg.pipeline.estimator, Some(Estimator::Fit));
    // The board path is relative to the config file, and the board is there.
    let board = cfg.board.as_ref().unwrap();
    assert_eq!(
        board.path,
        example().parent().unwrap().join("boards/paper.toml")
    );
    rigd::sim::Board::load(&board.path).unwrap();
}

#[test]
#[cfg(feature = "sim")] // reads the typed [axis.sim] and [camera.sim] tables
fn every_documented_key_is_a_real_key() {
    // Uncomment every commented-out `key = value` line of the example: it must still load,
    // so the documentation cannot drift from the struct.
    let text = std::fs::read_to_string(example()).unwrap();
    let uncommented: String = text
        .lines()
        .map(|l| match l.strip_prefix("# ") {
            Some(rest)
                if is_key_line(rest) || (rest.starts_with('[') && rest.ends_with(".sim]")) =>
            {
                rest.to_string()
            }
            _ => l.to_string(),
        })
        .collect::<Vec<_>>()
        .join("\n");
    let cfg = Config::from_toml_str(&uncommented, &example()).unwrap();
    assert_eq!(
        cfg.axis
            .as_ref()
            .unwrap()
            .sim
            .as_ref()
            .unwrap()
            .max_speed_um_s,
        20_000.0
    );
    assert_eq!(
        cfg.camera
            .as_ref()
            .unwrap()
            .sim
            .as_ref()
            .unwrap()
            .mjpeg_quality,
        Some(90)
    );
}

/// `key = value` with a bare snake_case key.
fn is_key_line(s: &str) -> bool {
    match s.split_once(" = ") {
        Some((k, _)) => {
            !k.is_empty()
                && k.chars()
                    .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
        }
        None => false,
    }
}

#[test]
fn minimal_sections_take_defaults() {
    let cfg = parse(AXIS).unwrap();
    let a = cfg.axis.as_ref().unwrap();
    assert_eq!(a.baud, 115_200);
    assert_eq!(a.reply_timeout_ms, 1_000);
    assert!(cfg.camera.is_none());
    assert_eq!(cfg.daemon, rigd::config::DaemonSettings::default());
    let e = cfg.camera("grab a frame").unwrap_err().to_string();
    assert_eq!(
        e,
        "/etc/rigd/test.toml: no [camera] section (needed to grab a frame)"
    );
}

#[test]
fn unknown_key_names_file_and_key() {
    let e = err(&format!("{AXIS}soft_max = 3\n"));
    assert!(e.starts_with("/etc/rigd/test.toml: "), "{e}");
    assert!(e.contains("soft_max"), "{e}");
    assert!(e.contains("line 7"), "{e}");
    let e = err("[camera]\ndriver = \"v4l2\"\ndevice = \"/dev/video0\"\nexposure = 5\n");
    assert!(e.contains("unknown field `exposure`"), "{e}");
    let e = err("[cameras]\ndriver = \"sim\"\n");
    assert!(e.contains("unknown field `cameras`"), "{e}");
}

#[test]
fn wrong_values_name_the_key() {
    let e = err(
        "[axis]\ndriver = \"marlin\"\nsoft_min_um = 0.0\nsoft_max_um = 1.0\nmax_step_um = 1.0\n",
    );
    assert!(e.contains("marlin") && e.contains("grbl"), "{e}");
    let e =
        err("[axis]\ndriver = \"grbl\"\nsoft_min_um = 0.0\nsoft_max_um = 1.0\nmax_step_um = 1.0\n");
    assert_eq!(
        e,
        "/etc/rigd/test.toml: key `axis.port`: required with a serial driver"
    );
    let e = err(&AXIS.replace("soft_max_um = 1000.0", "soft_max_um = -5.0"));
    assert!(e.contains("key `axis.soft_max_um`"), "{e}");
    let e = err(&AXIS.replace("max_step_um = 100.0", "max_step_um = 0.0"));
    assert!(e.contains("key `axis.max_step_um`"), "{e}");
    let e = err(&format!("{AXIS}reply_timeout_ms = 0\n"));
    assert!(e.contains("key `axis.reply_timeout_ms`"), "{e}");
    for hz in ["0", "20", "nan"] {
        let e = err(&format!("{AXIS}status_poll_hz = {hz}\n"));
        assert!(
            e.contains("key `axis.status_poll_hz`") && e.contains("at most 10"),
            "{e}"
        );
    }
    let e = err("[camera]\ndriver = \"v4l2\"\n");
    assert!(e.contains("key `camera.device`"), "{e}");
    let e = err("[camera]\ndriver = \"sim\"\nformat = \"H264\"\n");
    assert!(e.contains("H264"), "{e}");
    let e = err("[camera]\ndriver = \"sim\"\nwidth = 0\n");
    assert!(e.contains("key `camera.width`"), "{e}");
    let e = err("[xl80]\npath = \"x.csv\"\nformat = \"xls\"\n");
    assert!(e.contains("xls") && e.contains("rtx"), "{e}");
    let e = err("[xl80]\npath = \"x.rtx\"\nformat = \"rtx\"\nrtx_unit = \"furlong\"\n");
    assert!(e.contains("key `xl80.rtx_unit`"), "{e}");
    let e = err("[pipeline]\nk = 0\n");
    assert!(e.contains("key `pipeline.k`"), "{e}");
    let e = err("[pipeline]\nestimator = \"magic\"\n");
    assert!(e.contains("magic"), "{e}");
    let e = err(&format!("{AXIS}baud = \"fast\"\n"));
    assert!(e.contains("baud"), "{e}");
    let cam = "[camera]\ndriver = \"sim\"\nink_prior = { density_rms = 0.9, corr_um = 3000 }\n";
    let e = err(cam);
    assert!(
        e.contains("key `camera.ink_prior`") && e.contains("0.9"),
        "{e}"
    );
}

#[test]
fn the_prints_ink_statistics_are_read() {
    let cfg =
        parse("[camera]\ndriver = \"sim\"\nink_prior = { density_rms = 0.04, corr_um = 3000 }\n")
            .unwrap();
    let p = cfg.camera("t").unwrap().ink_prior.unwrap();
    assert_eq!((p.density_rms, p.corr_um), (0.04, 3000.0));
}

#[test]
fn missing_file_is_named() {
    let e = Config::load("/nonexistent/rigd.toml")
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("/nonexistent/rigd.toml: cannot read"), "{e}");
}

#[test]
fn relative_paths_follow_the_file() {
    let cfg = parse(
        "[xl80]\npath = \"logs/run.csv\"\nformat = \"csv\"\n[board]\npath = \"/abs/b.toml\"\n",
    )
    .unwrap();
    assert_eq!(
        cfg.xl80.unwrap().path,
        PathBuf::from("/etc/rigd/logs/run.csv")
    );
    assert_eq!(cfg.board.unwrap().path, PathBuf::from("/abs/b.toml"));
}

#[test]
fn stage_sections_map_to_the_driver_options() {
    let cfg = Config::load(example()).unwrap();
    let g = cfg.axis("test").unwrap().grbl_options();
    g.validate().unwrap();
    assert_eq!(g.port, "/dev/ttyUSB0");
    assert_eq!(g.banner_timeout_ms, 2_500);
    assert_eq!(g.feed_um_s, 10_000.0);
    assert_eq!(g.status_poll_hz, 5.0);
    assert_eq!(
        (g.limits.min_um, g.limits.max_um, g.limits.max_step_um),
        (0.0, 250_000.0, 50_000.0)
    );
    let p = cfg.piezo("test").unwrap().gcs_options();
    p.validate().unwrap();
    assert_eq!(p.axis, "1");
    assert_eq!(p.limits.max_um, 100.0);
    assert!(p.servo_on_connect);
    // The limits refuse what the config says they refuse.
    let l = cfg.axis("test").unwrap().limits();
    l.check_abs("axis", 100.0).unwrap();
    assert!(l.check_abs("axis", 250_000.5).is_err());
    assert!(l.check_rel("axis", 0.0, 50_001.0).is_err());
}

#[test]
fn axis_dir_and_default_start_are_read_and_checked() {
    let cfg = parse(&format!(
        "{AXIS}default_start_um = 250.0\n[pipeline]\naxis_dir = [0.0, -1.0]\n"
    ))
    .unwrap();
    let axis = cfg.axis("test").unwrap();
    assert_eq!(axis.default_start_um, Some(250.0));
    assert_eq!(axis.scan_start_um(), 250.0);
    assert_eq!(cfg.pipeline.axis_dir, [0.0, -1.0]);
    // Absent: the soft minimum (not below 0).
    let cfg = parse(AXIS).unwrap();
    assert_eq!(cfg.axis("test").unwrap().scan_start_um(), 0.0);
    assert_eq!(cfg.pipeline.axis_dir, [-1.0, 0.0]);
    let below = AXIS.replace("soft_min_um = 0.0", "soft_min_um = -500.0");
    assert_eq!(
        parse(&below).unwrap().axis("t").unwrap().scan_start_um(),
        0.0
    );

    for (extra, key, says) in [
        (
            "default_start_um = 1500.0\n",
            "axis.default_start_um",
            "outside the soft limits",
        ),
        (
            "default_start_um = -1.0\n",
            "axis.default_start_um",
            "outside the soft limits",
        ),
        (
            "default_start_um = nan\n",
            "axis.default_start_um",
            "outside the soft limits",
        ),
        (
            "[pipeline]\naxis_dir = [0.0, 0.0]\n",
            "pipeline.axis_dir",
            "non-zero",
        ),
        (
            "[pipeline]\naxis_dir = [inf, 0.0]\n",
            "pipeline.axis_dir",
            "finite",
        ),
    ] {
        let e = err(&format!("{AXIS}{extra}"));
        assert!(e.starts_with("/etc/rigd/test.toml: key `"), "{e}");
        assert!(e.contains(key) && e.contains(says), "{extra}: {e}");
    }
    // A wrong shape or type is toml's error, still naming the file and the key.
    let e = err(&format!("{AXIS}[pipeline]\naxis_dir = [1.0]\n"));
    assert!(
        e.contains("/etc/rigd/test.toml") && e.contains("axis_dir"),
        "{e}"
    );
    let e = err(&format!("{AXIS}default_start_um = \"near\"\n"));
    assert!(e.contains("default_start_um"), "{e}");
    // The piezo has no default start of its own.
    let piezo = "[piezo]\ndriver = \"sim\"\nsoft_min_um = 0.0\nsoft_max_um = 100.0\nmax_step_um = 100.0\ndefault_start_um = 5.0\n";
    let e = err(piezo);
    assert!(
        e.contains("piezo.default_start_um") && e.contains("only [axis]"),
        "{e}"
    );
}

#[test]
fn piezo_dir_is_read_and_checked_and_reaches_the_rig() {
    let cfg = parse(&format!("{AXIS}[pipeline]\npiezo_dir = [0.0, -1.0]\n")).unwrap();
    assert_eq!(cfg.pipeline.piezo_dir, Some([0.0, -1.0]));
    assert_eq!(parse(AXIS).unwrap().pipeline.piezo_dir, None);
    let e = err(&format!("{AXIS}[pipeline]\npiezo_dir = [0.0, 0.0]\n"));
    assert!(
        e.starts_with("/etc/rigd/test.toml: key `pipeline.piezo_dir`")
            && e.contains("per unit of piezo travel"),
        "{e}"
    );
    // An all-sim rig: its piezo moves against the configured direction.
    let sim = "[axis]\ndriver = \"sim\"\nsoft_min_um = 0.0\nsoft_max_um = 100000.0\nmax_step_um = 100000.0\n\
               [piezo]\ndriver = \"sim\"\nsoft_min_um = 0.0\nsoft_max_um = 100.0\nmax_step_um = 100.0\n\
               [camera]\ndriver = \"sim\"\nwidth = 64\nheight = 48\n\
               [pipeline]\npiezo_dir = [0.0, -1.0]\n";
    let cfg = parse(sim).unwrap();
    let hw = rigd::rig::sim::open_sim_rig(&cfg).unwrap();
    assert_eq!(hw.rig.config().piezo_dir, [0.0, 1.0]);
    let rig = rigd::rig::from_config(&cfg).unwrap();
    assert_eq!(rig.info.piezo_dir, Some([0.0, -1.0]));
    assert_eq!(
        rig.info.dir(rigd::acquisition::StageKind::Piezo),
        [0.0, -1.0]
    );
}
