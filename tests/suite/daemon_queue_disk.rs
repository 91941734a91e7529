//! The pre-flight disk check counts the jobs already queued or running: a job that fits the
//! free space alone is refused while another one still has that space to fill, naming the
//! figures, and accepted once that one has ended.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{capture_job, end_of, rig_from_toml, submit, Daemon, SIM_RIG_SMALL};
use rigd::acquisition::plan::{estimated_bytes, free_bytes};
use rigd::acquisition::JobSpec;
use rigd::daemon::protocol::{EventBody, Request};

#[test]
fn a_job_is_refused_when_the_queued_ones_have_claimed_the_free_space() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).unwrap();
    let free = free_bytes(&data).expect("statvfs of the data root");
    let mut rig = rig_from_toml(dir.path(), SIM_RIG_SMALL);
    // The frames written are tiny, but the check plans for frames of about a tenth of the
    // free space each (it estimates from the rig's frame size): six fit, twelve do not.
    rig.info.frame_size = (1000, (free / 30_000).max(1) as u32);
    let size = rig.info.frame_size;
    let d = Daemon::start_in(rig, dir);
    assert_eq!(d.data, data);
    let mut c = d.subscribed();
    // Six frames with a long settle: still running when the next ones are submitted.
    let slow = JobSpec {
        start_um: Some(1_000.0),
        ..capture_job(100.0, 6, 10_000)
    };
    let first = submit(&mut c, slow.clone());
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
    let end = end_of(&mut c, first);
    assert!(matches!(end, EventBody::Cancelled { .. }), "{end:?}");
    let quick = JobSpec {
        settle_ms: 0,
        ..slow
    };
    c.request(&Request::Submit { job: quick }).unwrap();
}
