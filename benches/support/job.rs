//! The job both step-interval benches time (`capture_overhead`, `preview_latency`): 40 frames
//! at 50 µm, settle 20 ms, processed at k = 10, followed to its end on the caller's
//! subscribed client.

use rigd::acquisition::JobSpec;
use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::session::Session;
use std::path::Path;

/// Follow job `id` on the subscribed client `c` until it finishes; its session's name
/// (panics if it ends otherwise).
pub fn finished(c: &mut Client, id: u64) -> String {
    loop {
        let e = c.next_event().unwrap();
        match e.body {
            EventBody::Finished { session } if e.job_id == id => return session,
            b if e.job_id == id && b.is_terminal() => panic!("job {id} ended: {b:?}"),
            _ => {}
        }
    }
}

/// Run the job; its id, its session and the intervals between its frames' exposures, ms.
pub fn forty_frames(c: &mut Client, data: &Path) -> (u64, Session, Vec<f64>) {
    let job = JobSpec {
        step_um: Some(50.0),
        steps: Some(40),
        k: Some(10),
        settle_ms: 20,
        ..JobSpec::default()
    };
    let r = c.request(&Request::Submit { job }).unwrap();
    let id = r["job_id"].as_u64().unwrap();
    let s = Session::open(&data.join(finished(c, id))).unwrap();
    let intervals = s
        .steps
        .windows(2)
        .map(|w| (w[1].t_unix_s - w[0].t_unix_s) * 1e3)
        .collect();
    (id, s, intervals)
}
