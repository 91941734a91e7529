//! The pre-flight disk check counts the jobs already queued or running: a job that fits the
//! free space alone is refused while another one still has that space to fill, naming the
//! figures, and accepted once that one has ended.

use rigd::cli::client::Client;
use rigd::config::Config;
use rigd::daemon::hwrig::rig_from_config;
use rigd::daemon::plan::{estimated_bytes, free_bytes};
use rigd::daemon::protocol::{EventBody, JobSpec, Request};
use rigd::daemon::server::Background;
use rigd::daemon::DaemonSettings;

const SIM_RIG: &str = r#"
[axis]
driver = "sim"
soft_min_um = 0.0
soft_max_um = 100000.0
max_step_um = 100000.0
[camera]
driver = "sim"
[camera.sim]
width = 48
height = 32
supersample = 2
frame_period_ms = 2.0
exposure_ms = 1.0
"#;

#[test]
fn a_job_is_refused_when_the_queued_ones_have_claimed_the_free_space() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).unwrap();
    let free = free_bytes(&data).expect("statvfs of the data root");
    let cfg = Config::from_toml_str(SIM_RIG, &dir.path().join("rig.toml")).unwrap();
    let mut rig = rig_from_config(&cfg).unwrap();
    // The frames written are tiny, but the check plans for frames of about a tenth of the
    // free space each (it estimates from the rig's frame size): six fit, twelve do not.
    rig.info.frame_size = (1000, (free / 30_000).max(1) as u32);
    let size = rig.info.frame_size;
    let settings = DaemonSettings {
        socket: dir.path().join("rigd.sock"),
        group: None,
        data_root: data.clone(),
    };
    let bg = Background::start(settings, rig).unwrap();
    let mut c = Client::connect(&bg.socket).unwrap();
    c.request(&Request::Subscribe { job_id: None }).unwrap();
    // Six frames with a long settle: still running when the next ones are submitted.
    let slow = JobSpec {
        start_um: Some(1_000.0),
        step_um: Some(100.0),
        steps: Some(6),
        settle_ms: 10_000,
        process: false,
        ..JobSpec::default()
    };
    let first = c.request(&Request::Submit { job: slow.clone() }).unwrap()["job_id"]
        .as_u64()
        .unwrap();
    let e = c
        .request(&Request::Submit { job: slow.clone() })
        .unwrap_err()
        .to_string();
    assert!(e.contains("6 frames need about "), "{e}");
    // At most six frames of the first job are left to write, at least five (one settle
    // of 10 s has not passed).
    let committed_mb = |n| estimated_bytes(n, size) >> 20;
    assert!(
        e.contains(&format!(" {} MB are already committed", committed_mb(6)))
            || e.contains(&format!(" {} MB are already committed", committed_mb(5))),
        "{e}"
    );
    assert!(
        e.contains(&format!("{} has ", data.display())) && e.contains("MB free"),
        "{e}"
    );
    // The first job ends (cancelled): its space is free again, the same job is accepted.
    c.request(&Request::Cancel { job_id: first }).unwrap();
    loop {
        let ev = c.next_event().unwrap();
        if ev.job_id == first && ev.body.is_terminal() {
            assert!(
                matches!(ev.body, EventBody::Cancelled { .. }),
                "{:?}",
                ev.body
            );
            break;
        }
    }
    let quick = JobSpec {
        settle_ms: 0,
        ..slow
    };
    c.request(&Request::Submit { job: quick }).unwrap();
}
